"""The floor of a heartbeat in Python (issue 24): what 10 Hz beats to every neighbour would cost
with nothing but the event loop and the liveness clock, to set the simulator's per-node CPU
against.

N nodes on a random graph of mean degree D; each node's tick is popped from a heap every 0.1
simulated seconds, makes a beat and pushes one heap entry for its broadcast; each copy is one
method call that checks the sender's incarnation and writes its liveness clock. Figures: CPU
microseconds per copy and milliseconds per node per simulated second (the simulator's target
is 1 ms with the node's real code).

Usage: .venv/bin/python bench/beat_floor.py [--nodes 1000] [--degree 6] [--seconds 10]
Writes bench/results/beat_floor.json and beat_floor.md.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import random
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results

RESULTS = Path(__file__).resolve().parent / "results"


class _Node:
    __slots__ = ("incarnations", "last_heard")

    def __init__(self) -> None:
        self.incarnations: dict[int, int] = {}
        self.last_heard: dict[int, float] = {}

    def receive(self, src: int, incarnation: int, now: float) -> bool:
        if self.incarnations.get(src, incarnation) != incarnation:
            return False
        self.last_heard[src] = now
        return True


def _graph(n: int, degree: float, seed: int) -> list[list[int]]:
    rng = random.Random(seed)
    near: list[set[int]] = [set() for _ in range(n)]
    while sum(map(len, near)) < n * degree:
        a, b = rng.randrange(n), rng.randrange(n)
        if a != b:
            near[a].add(b)
            near[b].add(a)
    return [sorted(x) for x in near]


def run(n: int, degree: float, seconds: float, seed: int = 1) -> dict[str, Any]:
    near = _graph(n, degree, seed)
    nodes = [_Node() for _ in range(n)]
    rng = random.Random(seed)
    heap: list[tuple[float, int, int, int]] = []  # (at, seq, kind 0 tick / 1 cast, node)
    seq = itertools.count()
    for i in range(n):
        heapq.heappush(heap, (rng.random() * 0.1, next(seq), 0, i))
    copies = 0
    c0 = time.process_time()
    while heap and heap[0][0] <= seconds:
        at, _, kind, i = heapq.heappop(heap)
        if kind == 0:
            heapq.heappush(heap, (at + 0.001, next(seq), 1, i))  # the broadcast, 1 ms away
            heapq.heappush(heap, (at + 0.1, next(seq), 0, i))
        else:
            for d in near[i]:
                nodes[d].receive(i, 0, at)
                copies += 1
    cpu = time.process_time() - c0
    return {
        "nodes": n,
        "mean_degree": round(sum(map(len, near)) / n, 2),
        "seconds": seconds,
        "copies": copies,
        "us_per_copy": round(cpu / copies * 1e6, 3),
        "ms_per_node_per_sim_s": round(cpu / seconds / n * 1e3, 4),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=1000)
    ap.add_argument("--degree", type=float, default=6.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args(argv)
    if args.nodes < 2 or not 0 < args.degree < args.nodes or not 0 < args.seconds <= 3600:
        print("error: --nodes >= 2, 0 < --degree < nodes, 0 < --seconds <= 3600", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    r = run(args.nodes, args.degree, args.seconds)
    result = {"floor": r, **provenance(), "seconds": time.perf_counter() - t0}
    table = (
        "### The floor of a heartbeat in Python\n\n"
        "| N | mean degree | simulated s | copies | µs per copy | ms per node per simulated s |\n"
        "|---:|---:|---:|---:|---:|---:|\n"
        f"| {r['nodes']} | {r['mean_degree']} | {r['seconds']:g} | {r['copies']:,} |"
        f" {r['us_per_copy']} | {r['ms_per_node_per_sim_s']} |\n"
    )
    write_results(RESULTS / "beat_floor.json", result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
