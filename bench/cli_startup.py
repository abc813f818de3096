"""How long does a CLI command take, start to answer, as a user types it?

Starts a 4-node emulated line (no app), then runs each command ``--runs`` times as a fresh
process (``.venv/bin/mso ...``, the console script a user runs) and records the wall time of each
run: Python's start-up, the imports, finding the overlay's state file, asking a node, printing.
Target (issue 12): ``mso status`` answers in <= 150 ms. The commands measured:

- ``mso status --json`` and ``mso status`` (rendered with rich) against the running overlay;
- ``mso overlays`` (no node asked) and ``mso --help``.

Usage: .venv/bin/python bench/cli_startup.py [--runs 20] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import percentile, provenance, write_results
from mso.emu.controller import Emulator
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
MSO = Path(sys.executable).parent / "mso"
LINE = """\
name: startup-line
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""
COMMANDS = [["status", "--json"], ["status"], ["overlays"], ["--help"]]


def time_runs(args: list[str], runs: int, env: dict[str, str]) -> list[float]:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        done = subprocess.run([str(MSO), *args], env=env, capture_output=True, timeout=30)
        times.append(time.perf_counter() - t0)
        if done.returncode != 0:
            raise SystemExit(f"mso {' '.join(args)} failed: {done.stderr.decode()}")
    return times


async def measure(runs: int) -> dict[str, Any]:
    emu = Emulator(loads_scenario(LINE))
    await emu.start()
    try:
        env = dict(os.environ)
        rows = {}
        for args in COMMANDS:
            times = await asyncio.to_thread(time_runs, args, runs, env)
            rows["mso " + " ".join(args)] = {
                "runs": runs,
                "p50_ms": percentile(times, 50) * 1e3,
                "p90_ms": percentile(times, 90) * 1e3,
                "min_ms": min(times) * 1e3,
            }
        return rows
    finally:
        await emu.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "cli_startup.json")
    a = ap.parse_args(argv)
    tempfile.tempdir = tempfile.mkdtemp(prefix="mso-bench-cli-")  # our overlay only
    os.environ["TMPDIR"] = tempfile.tempdir
    t0 = time.perf_counter()
    rows = asyncio.run(measure(a.runs))
    result = {"benchmark": "cli_startup", "target_status_ms": 150, "commands": rows}
    result |= provenance() | {"seconds": time.perf_counter() - t0}
    load = result["machine"]["load_average"]
    lines = [
        f"CLI start to answer, {a.runs} runs each (load average {load[0]:.2f} on "
        f"{result['machine']['cpus']} CPUs)",
        "",
        "| command | p50 ms | p90 ms | min ms |",
        "|---|---:|---:|---:|",
    ]
    for cmd, r in rows.items():
        lines.append(f"| `{cmd}` | {r['p50_ms']:.0f} | {r['p90_ms']:.0f} | {r['min_ms']:.0f} |")
    write_results(a.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
