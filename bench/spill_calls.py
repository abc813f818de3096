"""How long the daemon's spill store holds the node's loop: every call timed over a long cut.

The node calls its spill store (``mso.daemon.spill.SqliteSpill``) on its asyncio loop, so a
call that takes long stops everything else on that node, beats included: giving back a drained
300 MB in one call took 3.6-5.7 s and its peer declared the node failed. Here, on an asyncio
loop with ``keep_tidy`` beside it as the daemon runs it, a source's edge fills the store as a
cut of ``--mb`` MB would (50 KB events, a turn of the loop between them), then drains as acks
come (up to a window of what the store's reader thread read ahead, as a node's drain takes it
with ``ready``, then acks of 8 events), and the drained file's pages go back. Per kind
of call: the wall and CPU time of each (p50, p99, max) and how many took over 50 ms; and the
loop's largest stall, from a 10 ms ticker's lateness (what a beat would have waited). Then
the same with every page given back in one call, as the store did before (the same run's
figures to compare). Wall times on a loaded machine include waits for a core; CPU times not.

Usage: .venv/bin/python bench/spill_calls.py [--mb 300] [--json FILE]
Writes bench/results/spill_calls.json and spill_calls.md.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.daemon.spill import VACUUM_PAGES, SqliteSpill, keep_tidy

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SIZE = 50_000
WINDOW = 80  # events read at once (4 MB: the heal's drain keeps about that unacknowledged)
ACK = 8  # events per ack
TICK_S = 0.01
AT_ONCE = 1 << 30  # pages a step may give back: all of them, as the store did before


async def measure(mb: int, tmp: Path, pages: int) -> dict[str, Any]:
    store = SqliteSpill(tmp)
    calls: dict[str, list[tuple[float, float]]] = {}
    stalls: list[float] = []
    done = asyncio.Event()

    def timed(name: str, call: Callable[..., Any], *args: Any) -> Any:
        t0, c0 = time.perf_counter(), time.thread_time()
        out = call(*args)
        calls.setdefault(name, []).append((time.perf_counter() - t0, time.thread_time() - c0))
        return out

    async def ticker() -> None:
        loop = asyncio.get_running_loop()
        while not done.is_set():
            due = loop.time() + TICK_S
            await asyncio.sleep(TICK_S)
            stalls.append(loop.time() - due)

    step = store.tidy

    def timed_step(pages: int = pages) -> bool:
        return bool(timed("tidy", step, pages))

    store.tidy = timed_step  # type: ignore[method-assign]  # (each step keep_tidy takes)
    tidy = asyncio.create_task(keep_tidy(store))
    tick = asyncio.create_task(ticker())
    key, n = "app/1/0", mb * 1_000_000 // SIZE
    peak = 0
    try:
        for i in range(n):
            timed("append", store.append, key, i, [bytes(SIZE)])
            if i % 1024 == 0:
                timed("save_position", store.save_position, key, i + 1024)
            peak = max(peak, store.disk_bytes())
            await asyncio.sleep(0)
        timed("span", store.span, key)
        more = asyncio.Event()
        store.read_apart(asyncio.get_running_loop().call_soon_threadsafe, lambda k: more.set())
        pos = 0
        while pos < n:  # (what the reader thread read ahead: a drain's ``ready``)
            got = timed("ready", store.ready, key, pos, WINDOW)
            if not got:
                more.clear()
                await asyncio.wait_for(more.wait(), 60)
                continue
            end = pos + len(got)
            while pos < end:
                pos = min(end, pos + ACK)
                timed("trim", store.trim, key, pos)
                await asyncio.sleep(0)
        drained = time.perf_counter()
        while store.owed or store.disk_bytes() > 1 << 20:
            await asyncio.sleep(0.05)
            if time.perf_counter() - drained > 120:
                break
        given_back_s = time.perf_counter() - drained
    finally:
        done.set()
        tidy.cancel()
        await tick
        store.close()
    rows = {}
    for name, xs in calls.items():
        wall = sorted(x[0] * 1e3 for x in xs)
        cpu = sorted(x[1] * 1e3 for x in xs)
        rows[name] = {
            "calls": len(xs),
            "wall_p50_ms": round(pct(wall, 50), 3),
            "wall_p99_ms": round(pct(wall, 99), 3),
            "wall_max_ms": round(wall[-1], 1),
            "cpu_max_ms": round(cpu[-1], 1),
            "over_50ms": sum(w > 50 for w in wall),
        }
    stalls.sort()
    return {
        "calls": rows,
        "loop_stall_p99_ms": round(pct(stalls, 99) * 1e3, 1),
        "loop_stall_max_ms": round(stalls[-1] * 1e3, 1) if stalls else 0.0,
        "disk_peak_mb": round(peak / 1e6, 1),
        "pages_back_s": round(given_back_s, 2),
        "reads_apart": store.reads_apart,
    }


def pct(xs: list[float], p: float) -> float:
    return xs[min(len(xs) - 1, max(0, round(p / 100 * (len(xs) - 1))))] if xs else float("nan")


def render(result: dict[str, Any]) -> str:
    lines = []
    for r in result["runs"]:
        how = (
            f"{r['pages']} pages a step, a step per loop turn"
            if r["pages"] != AT_ONCE
            else "all pages in one call, as before"
        )
        lines += [
            f"### The spill store's calls on the node's loop ({result['mb']} MB of 50 KB events "
            f"held, then drained; keep_tidy beside, {how})",
            "",
            "| call | calls | wall p50 ms | wall p99 ms | wall max ms | CPU max ms | over 50 ms |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for name, c in r["calls"].items():
            lines.append(
                f"| {name} | {c['calls']:,} | {c['wall_p50_ms']} | {c['wall_p99_ms']} | "
                f"{c['wall_max_ms']} | {c['cpu_max_ms']} | {c['over_50ms']} |"
            )
        lines += [
            "",
            f"Load average {r['load'][0]:.1f} (wall times include waits for a core). The "
            f"loop's largest stall (a 10 ms ticker's lateness): {r['loop_stall_max_ms']} ms "
            f"(p99 {r['loop_stall_p99_ms']} ms); the file's peak {r['disk_peak_mb']} MB; the "
            f"drained file's pages back in {r['pages_back_s']} s. The drain's events read on "
            f"the reader thread ({r['reads_apart']} reads of up to 4 MB): `ready` takes them "
            "from memory.",
            "",
        ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mb", type=int, default=300)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not 1 <= args.mb <= 2000:
        ap.error("--mb: 1..2000")
    out: Path = args.json or RESULTS / "spill_calls.json"
    started = time.monotonic()
    result: dict[str, Any] = {"benchmark": "spill_calls", "mb": args.mb, "runs": []}
    for pages in (VACUUM_PAGES, AT_ONCE):  # as the store does it, and as it did (one call)
        with tempfile.TemporaryDirectory(prefix="mso-bench-spill-") as tmp:
            run = asyncio.run(measure(args.mb, Path(tmp), pages))
        result["runs"].append({"pages": pages, "load": os.getloadavg()} | run)
    result["seconds"] = time.monotonic() - started
    write_results(out, result | provenance(), render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
