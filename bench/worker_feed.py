"""CPU of the vertex worker per event: ``VertexWorker.feed`` on batches of 64 small events.

A 1:1 vertex with one input against the same vertex as a merge (two inputs), whose worker also
records which event of the batch each output came from (mso.protocol.provenance): what the
provenance costs on the hot path, and that a one-input vertex pays nothing for it. Thread CPU
time, best and median of 7 repetitions of 2,000 batches each, in one process.

Usage: .venv/bin/python bench/worker_feed.py [--json bench/results/worker_feed.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import msgspec

from mso.benchmarks.common import provenance, write_results
from mso.model.app import Vertex
from mso.protocol import effects as fx
from mso.runtime.worker import VertexWorker

RESULTS = Path(__file__).resolve().parent / "results"
BATCH, BATCHES, REPS = 64, 2000, 7


class Num(msgspec.Struct, frozen=True):
    seq: int
    pad: bytes = b""


def double(e: Num) -> Num:
    return Num(e.seq * 2, e.pad)


def ns_per_event(inputs: int) -> tuple[float, float]:
    """(best, median) ns of thread CPU per event for a vertex with ``inputs`` input edges."""
    start = fx.StartVertex(1, "app", Vertex(id="v", code=double), "operator",
                           inputs={i: Num for i in range(inputs)}, outputs={9: Num})  # fmt: skip
    worker = VertexWorker(start)
    assert worker.open().error == ""
    batch = [msgspec.msgpack.encode(Num(i, b"x" * 16)) for i in range(BATCH)]
    feed = fx.FeedVertex(1, 0, batch, 0.0)
    runs = []
    for _ in range(REPS):
        t0 = time.thread_time()
        for _ in range(BATCHES):
            worker.feed(feed)
        runs.append((time.thread_time() - t0) / (BATCHES * BATCH) * 1e9)
    runs.sort()
    return runs[0], runs[REPS // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=RESULTS / "worker_feed.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = {}
    for name, inputs in (("one input", 1), ("merge (two inputs)", 2)):
        best, median = ns_per_event(inputs)
        rows[name] = {"best_ns": round(best, 1), "median_ns": round(median, 1)}
    table = "### VertexWorker.feed, thread CPU per event (batches of 64, 1:1 vertex)\n\n"
    table += "| vertex | best ns/event | median ns/event |\n|---|---:|---:|\n"
    for name, r in rows.items():
        table += f"| {name} | {r['best_ns']:,.0f} | {r['median_ns']:,.0f} |\n"
    result = {"benchmark": "worker_feed", "rows": rows, **provenance()}
    result["seconds"] = time.perf_counter() - t0
    write_results(args.json, result, table)


if __name__ == "__main__":
    main()
