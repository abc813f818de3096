"""Helpers every benchmark shares: which machine and sources were measured, and percentiles."""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def provenance() -> dict[str, Any]:
    """Where and on what a result was measured: machine, load, source digest, time."""
    return {
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
        "src_digest": src_digest(),
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def src_digest() -> str:
    """sha256 over src/mso/**/*.py: which state of the sources a result was measured on."""
    h = hashlib.sha256()
    src = Path(__file__).resolve().parent.parent
    for f in sorted(src.rglob("*.py")):
        h.update(str(f.relative_to(src)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, from /proc (0 if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def per_call_us(fn: Callable[[], object], n: int) -> float:
    """Median CPU µs of ``fn()`` over 5 batches of ``n // 5`` (CPU time: a loaded machine's
    waits are not counted)."""
    batch = max(1, n // 5)
    out = []
    for _ in range(5):
        t = time.process_time()
        for _ in range(batch):
            fn()
        out.append((time.process_time() - t) / batch * 1e6)
    return statistics.median(out)


def percentile(values: list[float], q: float) -> float:
    """Linear-interpolated percentile (q in 0..100) of a non-empty list."""
    s = sorted(values)
    if len(s) == 1:
        return s[0]
    pos = (len(s) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


class SequenceCheck:
    """A sink's check of one producer's numbering 0, 1, 2, ...: the events seen, repeats (a
    number already passed) and arrivals out of order (a number ahead of the next expected).
    The benchmarks' and tests' order-checking sinks build on it."""

    def __init__(self) -> None:
        self.count = 0
        self.next = 0
        self.repeats = 0
        self.out_of_order = 0

    def see(self, seq: int) -> int:
        """Count event ``seq``; returns how many numbers it skipped (0 when in order)."""
        self.count += 1
        skipped = max(0, seq - self.next)
        if seq < self.next:
            self.repeats += 1
        elif skipped:
            self.out_of_order += 1
        self.next = max(self.next, seq + 1)
        return skipped


class Progress:
    """One line on stderr as each step of a long benchmark starts, with the time so far, so a
    run of minutes shows where it is (stdout keeps the table alone)."""

    def __init__(self, name: str, quiet: bool = False) -> None:
        self.name, self.quiet = name, quiet
        self.t0 = time.monotonic()

    def __call__(self, what: str) -> None:
        if not self.quiet:
            print(f"[{time.monotonic() - self.t0:6.1f} s] {self.name}: {what}", file=sys.stderr)


def write_results(out: Path, result: dict[str, Any], table: str) -> None:
    """Write a benchmark's JSON and its Markdown table beside it, and show the table."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(table)
    print(table)
    print(f"written: {out} and {out.with_suffix('.md')} ({result['seconds']:.0f} s)")
