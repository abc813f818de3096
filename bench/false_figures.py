"""What a captured node's false figures steer (issue 27): the rules weigh a move by the
figures each node reports in its beats (battery, drain, load, capacity), and a node's figures
are its own word. Measured in the simulator with the management rules on, the energy case of
tests/test_rules_sim.py: N1 - N2 - N3 - N4, src pinned on N1, a costly ``work`` vertex placed
on the fast N1, which has a tenth of the others' battery, the sink pinned on N4. Honest, the
rules move ``work`` off N1 one hop at a time. Then one node reports false figures in every
beat (its monitor is not asked): ``attract`` (a full battery, no drain, an idle 100x CPU: come
to me) or ``repel`` (an empty battery: keep away), and we see where ``work`` ends, how many
moves the rules made, and what the sink got.

Usage: .venv/bin/python bench/false_figures.py [--seconds 120] [--json FILE]
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from pathlib import Path
from typing import Any

import msgspec

from mso.benchmarks.common import provenance, write_results
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.protocol import messages as m
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
POWER = PowerModel(idle_w=1.0, cpu_w=6.0)
V = "mso.benchmarks.vertices.failure"
WORK = f"""
name: work
vertices:
  src: {{code: {V}:CountingSource, pinned: N1, rate: 50, cost: 0.1, output: {V}:Seq}}
  work: {{code: {V}:PassThrough, cost: 20, input: {V}:Seq, output: {V}:Seq}}
  sink: {{code: {V}:GapSink, pinned: N4, cost: 0.1, input: {V}:Seq}}
edges: [[src, work], [work, sink]]
"""
NODES = ("N1", "N2", "N3", "N4")


def network() -> Network:
    nodes = [NodeSpec("N1", cpu=4.0, battery_wh=0.5, power=POWER)]
    nodes += [NodeSpec(n, battery_wh=5.0, power=POWER) for n in NODES[1:]]
    links = [LinkSpec(a, b, delay_ms=1) for a, b in itertools.pairwise(NODES)]
    return Network(nodes, links)


def lie(sim: Simulation, node: str, how: str) -> None:
    """``node`` reports made-up figures in every beat from now on."""
    core = sim.cores[node]
    honest = core.figures

    def figures() -> m.Figures:
        f = honest()
        if how == "attract":
            return msgspec.structs.replace(
                f, cpu=100.0, load=0.0, drain_w=0.01, remaining_j=1e9, lifetime_s=1e9
            )
        return msgspec.structs.replace(f, remaining_j=0.0, lifetime_s=0.0, drain_w=50.0)

    core.figures = figures  # type: ignore[method-assign]


def run(liar: str | None, how: str, seconds: float) -> dict[str, Any]:
    sim = Simulation(network())
    sim.request("N1", m.DeployRequest(WORK, "work.yaml"))
    sim.run_until(1.0)
    if liar is not None:
        lie(sim, liar, how)
    path = [sim.cores["N4"].apps["work"].placed["work"]]
    t = sim.now
    while t < seconds:
        t = min(seconds, t + 1.0)
        sim.run_until(t)
        where = sim.cores["N4"].apps["work"].placed["work"]
        if where != path[-1]:
            path.append(where)
    sink = sim.cores["N4"].status(sim.now)["apps"]["work"]["vertices"]["sink"]
    sent = sim.cores["N1"].instances("work")["src"].emitted
    left = sim.cores["N1"].monitor.remaining_j
    return {
        "liar": liar or "-",
        "lie": how if liar else "-",
        "work_path": path,
        "moves": len(path) - 1,
        "sent": sent,
        "received": int(sink["processed"]),
        "repeats": int(sink["stats"].get("repeats", 0)),
        "n1_battery_left_j": round(left, 1) if left is not None else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "false_figures.json")
    args = ap.parse_args()
    if not (5.0 <= args.seconds <= 3600.0) or math.isnan(args.seconds):
        ap.error("--seconds: 5..3600")
    t0 = time.time()
    cases = [(None, "-")] + [(n, h) for h in ("attract", "repel") for n in ("N2", "N3", "N4")]
    rows = []
    for liar, how in cases:
        rows.append(run(liar, how, args.seconds))
        print(rows[-1], file=sys.stderr)
    lines = [
        f"False figures in one node's beats, {args.seconds:g} s simulated "
        "(N1 - N2 - N3 - N4; work starts on N1, which has a tenth of the others' battery)",
        "",
        "| liar | lie | where work went | moves | N1 J left | sent | received | repeats |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['liar']} | {r['lie']} | {' -> '.join(r['work_path'])} | {r['moves']} "
            f"| {r['n1_battery_left_j']} | {r['sent']} | {r['received']} | {r['repeats']} |"
        )
    result = {"rows": rows, "seconds": time.time() - t0, **provenance()}
    write_results(args.json, result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
