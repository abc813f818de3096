"""Benchmark of chain formation (``mso.model.chains.form_chains_indexed``, paper §3.2).

Usage::

    .venv/bin/python bench/chains.py [--sizes 10000,100000,1000000] [--repeat 3] \\
        [--out bench/results] [--workloads pipeline,random_dag,pipeline_tree]

Every (workload, size) pair is measured in a fresh child process (this script run with
``--worker``), so peak-memory figures are not polluted by earlier runs. In the child the graph is
generated first (not timed); then ``form_chains_indexed`` runs ``--repeat`` times under
``time.perf_counter`` with the kernel's peak-RSS counter reset just before (Linux
``/proc/self/clear_refs``; elsewhere ``ru_maxrss`` before/after), then once more under
``tracemalloc`` (numpy registers its buffers with tracemalloc), and finally the result is checked.
The parent prints a Markdown table and writes ``chains.json`` and ``chains.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]
ChainFn = Callable[[int, IntArray, IntArray], tuple[IntArray, IntArray]]

ROOT = Path(__file__).resolve().parents[1]
SEED = 20240611
WORKLOADS = ("pipeline", "random_dag", "pipeline_tree")

# Targets from the issue: 1M vertices / ~1.5M edges in <= 3 s and <= 1.5 GB;
# time(1M) / time(100k) <= 12.
TARGET_SECONDS = 3.0
TARGET_BYTES = 1.5 * 1024**3
TARGET_RATIO = 12.0
RATIO_BIG, RATIO_SMALL = 1_000_000, 100_000

MiB = 1024 * 1024


# --------------------------------------------------------------------------- workloads


def gen_pipeline(n: int, rng: np.random.Generator) -> tuple[IntArray, IntArray]:
    """A single path 0 -> 1 -> ... -> n-1 (one chain of n vertices: the list-ranking worst case)."""
    del rng
    src = np.arange(n - 1, dtype=np.int64)
    return src, src + 1


def gen_random_dag(n: int, rng: np.random.Generator) -> tuple[IntArray, IntArray]:
    """A random DAG with ~1.5 edges per vertex, every edge u -> v with u < v.

    Each vertex v >= 1 gets one edge from a uniformly random u < v (so every vertex appears and
    the graph is connected), plus ~n/2 extra random u < v pairs; duplicates are dropped and the
    edge order is shuffled.
    """
    v = np.arange(1, n, dtype=np.int64)
    parent = (rng.random(n - 1) * v).astype(np.int64)
    a = rng.integers(0, n, size=n // 2, dtype=np.int64)
    b = rng.integers(0, n, size=n // 2, dtype=np.int64)
    keep = a != b
    lo, hi = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])
    keys = np.unique(np.concatenate([parent * n + v, lo * n + hi]))
    rng.shuffle(keys)
    return keys // n, keys % n


def gen_pipeline_tree(n: int, rng: np.random.Generator) -> tuple[IntArray, IntArray]:
    """A tree of pipelines: pipelines of random length 5..50 hung off the tail of earlier ones.

    Vertex 0 is the root. Pipeline k (vertices ``start[k]..start[k]+len[k]-1``, consecutive
    numbers) is fed by the tail of a uniformly random earlier pipeline (the root for k = 0), so a
    tail with two or more followers is a junction and chains are 5..50+ vertices long. Every vertex
    has one incoming edge except the root; the edge order is shuffled.
    """
    lengths = rng.integers(5, 51, size=n // 5 + 1, dtype=np.int64)
    ends = 1 + np.cumsum(lengths)  # exclusive end of pipeline k (vertex 0 is the root)
    k_max = int(np.searchsorted(ends, n, side="left")) + 1
    ends = np.minimum(ends[:k_max], n)
    starts = np.concatenate([[1], ends[:-1]])
    tails = ends - 1
    # Feeder of pipeline k: tail of a random pipeline j < k, or the root for k = 0.
    pick = (rng.random(k_max) * np.arange(k_max)).astype(np.int64)
    feeder = np.where(np.arange(k_max) == 0, 0, tails[pick])
    dst = np.arange(1, n, dtype=np.int64)
    src = dst - 1
    src[starts - 1] = feeder  # the first vertex of each pipeline hangs off its feeder
    perm = rng.permutation(n - 1)
    return src[perm], dst[perm]


GENERATORS: dict[str, Callable[[int, np.random.Generator], tuple[IntArray, IntArray]]] = {
    "pipeline": gen_pipeline,
    "random_dag": gen_random_dag,
    "pipeline_tree": gen_pipeline_tree,
}


# --------------------------------------------------------------------------- child process


def load_chain_fn() -> tuple[ChainFn, str]:
    """Import ``form_chains_indexed`` from this checkout's ``src`` (not some installed copy)."""
    sys.path.insert(0, str(ROOT / "src"))
    from mso.model import chains

    return chains.form_chains_indexed, str(chains.__file__)


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM); False where that is unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return False
    return _status_kib("VmHWM") is not None


def _maxrss_bytes() -> int:
    scale = 1 if sys.platform == "darwin" else 1024  # bytes on macOS, KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def verify(n: int, src: IntArray, dst: IntArray, offsets: IntArray, verts: IntArray) -> None:
    """Check the partition: |chain vertices| = |E| + |chains|, each edge once, each vertex seen."""
    m, n_chains = len(src), len(offsets) - 1
    if offsets[0] != 0 or offsets[-1] != len(verts) or np.any(np.diff(offsets) < 1):
        raise AssertionError("malformed offsets")
    if len(verts) != m + n_chains:
        raise AssertionError(f"{len(verts)} chain vertices != {m} edges + {n_chains} chains")
    # Consecutive vertices inside a chain are its edges: drop the pairs that straddle chains.
    inside = np.ones(max(len(verts) - 1, 0), dtype=bool)
    inside[offsets[1:-1] - 1] = False
    got = np.sort(verts[:-1][inside] * n + verts[1:][inside])
    want = np.sort(src * n + dst)
    if not np.array_equal(got, want):
        raise AssertionError("chain edges differ from the graph's edges")
    if np.bincount(verts, minlength=n).min(initial=1) < 1:
        raise AssertionError("a vertex is in no chain")


def run_worker(workload: str, n: int, repeat: int) -> dict[str, Any]:
    """Generate one graph, time/measure ``form_chains_indexed`` on it, verify, return figures."""
    form, module_path = load_chain_fn()
    rng = np.random.default_rng([SEED, WORKLOADS.index(workload), n])
    t0 = time.perf_counter()
    src, dst = GENERATORS[workload](n, rng)
    src, dst = np.ascontiguousarray(src, np.int64), np.ascontiguousarray(dst, np.int64)
    gen_s = time.perf_counter() - t0
    if np.bincount(np.concatenate([src, dst]), minlength=n).min(initial=1) < 1:
        raise AssertionError(f"{workload}: a vertex appears in no edge")
    gc.collect()

    # Wall time and peak RSS over the timed runs (peak counter reset after generation).
    base_rss = (_status_kib("VmRSS") or 0) * 1024
    hwm_reset = _reset_peak_rss()
    maxrss_before = _maxrss_bytes()
    times: list[float] = []
    result: tuple[IntArray, IntArray] | None = None
    for _ in range(repeat):
        result = None
        t0 = time.perf_counter()
        result = form(n, src, dst)
        times.append(time.perf_counter() - t0)
    if hwm_reset:
        peak_rss = (_status_kib("VmHWM") or 0) * 1024
        rss_method = "VmHWM reset after generation - VmRSS baseline"
    else:
        peak_rss = _maxrss_bytes()
        base_rss = maxrss_before
        rss_method = "ru_maxrss after - ru_maxrss after generation"
    assert result is not None
    offsets, verts = result
    del result

    # Python-heap peak (numpy buffers included) of one more call, outside the timed runs.
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    traced_base, _ = tracemalloc.get_traced_memory()
    out = form(n, src, dst)
    _, traced_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    del out

    t0 = time.perf_counter()
    verify(n, src, dst, offsets, verts)
    verify_s = time.perf_counter() - t0
    return {
        "workload": workload,
        "n_vertices": n,
        "n_edges": len(src),
        "n_chains": len(offsets) - 1,
        "max_chain_len": int(np.diff(offsets).max()),
        "times_s": times,
        "best_s": min(times),
        "median_s": statistics.median(times),
        "tracemalloc_peak_bytes": traced_peak - traced_base,
        "rss_baseline_bytes": base_rss,
        "rss_peak_bytes": peak_rss,
        "rss_increase_bytes": max(peak_rss - base_rss, 0),
        "rss_method": rss_method,
        "generate_s": gen_s,
        "verify_s": verify_s,
        "verified": True,
        "module": module_path,
    }


# --------------------------------------------------------------------------- parent process


def measure(workload: str, n: int, repeat: int) -> dict[str, Any]:
    """Run one measurement in a fresh interpreter and return its figures."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", workload, str(n)]
    cmd += ["--repeat", str(repeat)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{workload} n={n} failed:\n{proc.stderr}")
    row: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return row


def judge(rows: list[dict[str, Any]]) -> None:
    """Add ``ratio`` (best-time ratio 1M/100k per workload) and PASS/FAIL verdicts to ``rows``."""
    best = {(r["workload"], r["n_vertices"]): r["best_s"] for r in rows}
    for r in rows:
        reasons: list[str] = []
        if r["best_s"] > TARGET_SECONDS:
            reasons.append(f"time > {TARGET_SECONDS:g} s")
        if r["rss_increase_bytes"] > TARGET_BYTES or r["tracemalloc_peak_bytes"] > TARGET_BYTES:
            reasons.append("memory > 1.5 GB")
        r["ratio"] = None
        if r["n_vertices"] == RATIO_BIG and (r["workload"], RATIO_SMALL) in best:
            r["ratio"] = r["best_s"] / best[(r["workload"], RATIO_SMALL)]
            if r["ratio"] > TARGET_RATIO:
                reasons.append(f"ratio > {TARGET_RATIO:g}")
        r["verdict"] = "FAIL: " + ", ".join(reasons) if reasons else "PASS"


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| workload | vertices | edges | chains | best s | median s | tracemalloc peak MiB "
        "| RSS increase MiB | ratio 1M/100k | verdict |"
    )
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.1f}"
        lines.append(
            f"| {r['workload']} | {r['n_vertices']:,} | {r['n_edges']:,} | {r['n_chains']:,} "
            f"| {r['best_s']:.3f} | {r['median_s']:.3f} "
            f"| {r['tracemalloc_peak_bytes'] / MiB:.1f} | {r['rss_increase_bytes'] / MiB:.1f} "
            f"| {ratio} | {r['verdict']} |"
        )
    return "\n".join(lines)


def machine_info() -> dict[str, Any]:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(
                (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu
            )
    except OSError:
        pass
    mem_kib = None
    try:
        with open("/proc/meminfo") as f:
            mem_kib = int(f.readline().split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return {
        "platform": platform.platform(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "mem_total_bytes": mem_kib * 1024 if mem_kib else None,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", default="10000,100000,1000000", help="comma-separated vertex counts")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per measurement")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results", help="results folder")
    p.add_argument("--workloads", default=",".join(WORKLOADS), help="comma-separated subset")
    p.add_argument("--worker", nargs=2, metavar=("WORKLOAD", "N"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error("--repeat must be >= 1")

    if args.worker:
        print(json.dumps(run_worker(args.worker[0], int(args.worker[1]), args.repeat)))
        return 0

    sizes = [int(s.replace("_", "")) for s in args.sizes.split(",") if s]
    workloads = [w for w in args.workloads.split(",") if w]
    if unknown := set(workloads) - set(WORKLOADS):
        p.error(f"unknown workloads: {sorted(unknown)}")
    if any(s < 2 for s in sizes):
        p.error("sizes must be >= 2")

    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    for w in workloads:
        for n in sizes:
            r = measure(w, n, args.repeat)
            print(
                f"  {w:>13} n={n:>9,}: best {r['best_s']:.3f} s, "
                f"RSS +{r['rss_increase_bytes'] / MiB:.0f} MiB",
                file=sys.stderr,
            )
            rows.append(r)
    judge(rows)
    md = table(rows)
    print(md)

    report = {
        "benchmark": "chains",
        "function": "mso.model.chains.form_chains_indexed",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "python": sys.version,
        "numpy": np.__version__,
        "argv": sys.argv[1:],
        "repeat": args.repeat,
        "seed": SEED,
        "targets": {
            "seconds_at_1M": TARGET_SECONDS,
            "bytes_at_1M": TARGET_BYTES,
            "ratio_1M_over_100k": TARGET_RATIO,
            "notes": "time = best of --repeat; memory = max(RSS increase, tracemalloc peak); "
            "ratio = best(1M) / best(100k)",
        },
        "total_wall_s": time.perf_counter() - started,
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "chains.json").write_text(json.dumps(report, indent=2) + "\n")
    meta = (
        f"`form_chains_indexed`, {report['date']}, Python {platform.python_version()}, "
        f"numpy {np.__version__}, {report['machine']['cpu']} ({report['machine']['cpu_count']} "
        f"CPUs), best/median of {args.repeat} runs.\n\n"
    )
    (args.out / "chains.md").write_text("# Chain formation benchmark\n\n" + meta + md + "\n")
    print(f"\nwrote {args.out / 'chains.json'} and {args.out / 'chains.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
