"""What a captured node's false figures steer (issue 27): the rules weigh a move by the
figures each node reports in its beats (battery, drain, load, capacity), and a node's figures
are its own word. Measured in the simulator with the management rules on, the energy case of
tests/test_rules_sim.py: N1 - N2 - N3 - N4, src pinned on N1, a costly ``work`` vertex placed
on the fast N1, which has a tenth of the others' battery, the sink pinned on N4. Honest, the
rules move ``work`` off N1 one hop at a time. Then one node reports false figures in every
beat (its monitor is not asked): ``attract`` (a full battery, no drain, an idle 100x CPU: come
to me) or ``repel`` (an empty battery: keep away), and we see where ``work`` ends, how many
moves the rules made, and what the sink got.

Second table (``outsider``): the energy remap's case, where a draining node picks the join's
new host among every node in view — N1 - N2 - N3 - N4 with the join of ``joined`` on the
small-battery N2, and N5, a neighbour of N2 alone that hosts and relays nothing of the app
(a fifth of the battery: honest, not the place to go), lying ``attract``; each case with the
rules as before (``energy_outsiders=True``: any node in view) and as now (only the app's own
nodes), in one run.

Third (``--lifetime``): the energy study's ``mso-rules`` run under both settings, both
accountings, side by side: what the bound costs honest robots.

Usage: .venv/bin/python bench/false_figures.py [--seconds 120] [--lifetime] [--json FILE]
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

from mso.benchmarks import lifetime as study
from mso.benchmarks.common import provenance, write_results
from mso.management import RuleSettings
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


def follow(
    sim: Simulation, doc: str, vertex: str, liar: str | None, how: str, seconds: float
) -> list[str]:
    """Deploy ``doc`` from N1, have ``liar`` lie from then on, and run ``seconds``: the nodes
    ``vertex`` ran on in turn, as N4 (the sink's node) holds them."""
    app = msgspec.yaml.decode(doc)["name"]
    sim.request("N1", m.DeployRequest(doc, f"{app}.yaml"))
    sim.run_until(1.0)
    if liar is not None:
        lie(sim, liar, how)
    path = [sim.cores["N4"].apps[app].placed[vertex]]
    t = sim.now
    while t < seconds:
        t = min(seconds, t + 1.0)
        sim.run_until(t)
        where = sim.cores["N4"].apps[app].placed[vertex]
        if where != path[-1]:
            path.append(where)
    return path


def run(liar: str | None, how: str, seconds: float) -> dict[str, Any]:
    sim = Simulation(network())
    path = follow(sim, WORK, "work", liar, how, seconds)
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


JOINED = f"""
name: joined
planner: paper
vertices:
  s1: {{code: {V}:CountingSource, pinned: N1, rate: 20, cost: 0.1, output: {V}:Seq}}
  s2: {{code: {V}:CountingSource, pinned: N1, rate: 20, cost: 0.1, output: {V}:Seq}}
  join: {{code: {V}:PassThrough, cost: 10, input: {V}:Seq, output: {V}:Seq}}
  sink: {{code: {V}:GapSink, pinned: N4, cost: 0.1, input: {V}:Seq}}
edges: [[s1, join], [s2, join], [join, sink]]
"""


def outsider_network() -> Network:
    """N1 - N2 - N3 - N4 (N2 a fifth of the others' battery) and N5 off N2 (a fifth too)."""
    small = {"N2", "N5"}
    nodes = [
        NodeSpec(f"N{i}", battery_wh=1.0 if f"N{i}" in small else 5.0, power=POWER)
        for i in range(1, 6)
    ]
    links = [LinkSpec(a, b, delay_ms=1) for a, b in itertools.pairwise(NODES)]
    return Network(nodes, [*links, LinkSpec("N2", "N5", delay_ms=1)])


def run_outsider(liar: str | None, outsiders: bool, seconds: float) -> dict[str, Any]:
    rules = RuleSettings(energy_outsiders=outsiders)
    sim = Simulation(outsider_network(), rules=rules)
    path = follow(sim, JOINED, "join", liar, "attract", seconds)
    sink = sim.cores["N4"].status(sim.now)["apps"]["joined"]["vertices"]["sink"]
    src = sim.cores["N1"].instances("joined")
    left = {n: sim.cores[n].monitor.remaining_j for n in ("N2", "N3")}
    return {
        "liar": liar or "-",
        "rules": "any node in view (before)" if outsiders else "the app's nodes (now)",
        "join_path": path,
        "sent": src["s1"].emitted + src["s2"].emitted,
        "received": int(sink["processed"]),  # (two sources numbered alike: no order to check)
        "j_left": {n: round(j, 1) if j is not None else None for n, j in left.items()},
    }


def lifetime_side_by_side(limit_s: float) -> list[dict[str, Any]]:
    """The energy study's mso-rules under both settings and both accountings."""
    import tempfile

    rows = []
    shipped = study.RULES["mso-rules"]
    try:
        for accounting in study.ACCOUNTINGS:
            for outsiders in (True, False):
                study.RULES["mso-rules"] = RuleSettings(energy_outsiders=outsiders)
                with tempfile.TemporaryDirectory() as tmp:
                    r = study.run(
                        "mso-rules", limit_s, Path(tmp) / "r.sqlite", accounting=accounting
                    )
                rows.append(
                    {
                        "accounting": accounting,
                        "energy_outsiders": outsiders,
                        "leader_lifetime_s": r["leader_lifetime_s"],
                        "network_lifetime_s": r["network_lifetime_s"],
                        "results_stored": r["results_stored"],
                        "energy_per_result_j": r["energy_per_result_j"],
                        "relocations": len(r["relocations"]),
                        "placement_final": r["placement_final"],
                    }
                )
                print(rows[-1], file=sys.stderr)
    finally:
        study.RULES["mso-rules"] = shipped
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--lifetime", action="store_true", help="the energy study side by side")
    ap.add_argument("--limit-s", type=float, default=20_000.0, help="--lifetime's cap (virtual)")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "false_figures.json")
    args = ap.parse_args()
    if not (5.0 <= args.seconds <= 3600.0) or math.isnan(args.seconds):
        ap.error("--seconds: 5..3600")
    if not (60.0 <= args.limit_s <= 100_000.0) or math.isnan(args.limit_s):
        ap.error("--limit-s: 60..100000")
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
    outsider = []
    for liar in (None, "N5"):
        for outsiders in (True, False):
            outsider.append(run_outsider(liar, outsiders, args.seconds))
            print(outsider[-1], file=sys.stderr)
    lines += [
        "",
        f"An outsider's false figures and the energy remap, {args.seconds:g} s simulated "
        "(N1 - N2 - N3 - N4 and N5 off N2; the join on the draining N2; N5 hosts and relays "
        "nothing of the app)",
        "",
        "| liar | energy remap onto | where the join went | N2 J left | N3 J left | sent "
        "| received |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in outsider:
        lines.append(
            f"| {r['liar']} | {r['rules']} | {' -> '.join(r['join_path'])} "
            f"| {r['j_left']['N2']} | {r['j_left']['N3']} | {r['sent']} | {r['received']} |"
        )
    lifetime = lifetime_side_by_side(args.limit_s) if args.lifetime else []
    if lifetime:
        lines += [
            "",
            "The energy study's mso-rules, honest robots, under both settings "
            "(`mso bench lifetime`'s runs, until the leader's battery is empty)",
            "",
            "| accounting | energy remap onto | leader lifetime s | network lifetime s "
            "| results stored | J per result | moves | final join host |",
            "|---|---|---:|---:|---:|---:|---:|---|",
        ]
        for r in lifetime:
            onto = "any node in view" if r["energy_outsiders"] else "the app's nodes"
            lines.append(
                f"| {r['accounting']} | {onto} | {r['leader_lifetime_s']} "
                f"| {r['network_lifetime_s']} | {r['results_stored']} "
                f"| {r['energy_per_result_j']} | {r['relocations']} "
                f"| {r['placement_final'].get('bayes_inference', '?')} |"
            )
    result = {
        "rows": rows,
        "outsider": outsider,
        "lifetime": lifetime,
        "seconds": time.time() - t0,
        **provenance(),
    }
    write_results(args.json, result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
