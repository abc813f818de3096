"""What a captured chain end can do with its chain's vertices (issue 27): a chain's head (or
tail) host is warranted to remap the chain (the rules' chain remap), and every other node
takes that warrant for a move of each vertex at most once per ``CHAIN_END_INTERVAL_S``
(10 s), or, with ``--strict-moves``, not at all without an operator's order
(:mod:`mso.protocol.warrant`). Measured in the simulator with operator keys on every node:
the line N1 - N2 - N3 - N4 - N5 runs src -> a -> b -> c -> sink at 100 events/s (src
pinned on N1, the chain's head; the sink pinned on N5, its tail), and the captured N5 asks
its own relocator every ``--every`` seconds to move each of a, b and c somewhere else —
*churn*: round the other nodes, as fast as it may; *pull*: onto itself (it then holds the
chain's state; it sees the chain's output at its tail anyway) — and we count the moves the
other nodes took and refused, and what the sink got: events lost, repeated, out of order,
its longest gap and the chain's delay as the tail measures it. (The tail, not the head: a
captured head hosts the source and can stop the stream at will; and a move onto the head
switches the source's own edge, which then waits for a handover the old host refuses.)

Usage: .venv/bin/python bench/chain_end.py [--seconds 120] [--every 1] [--json FILE]
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
V = "mso.benchmarks.vertices.failure"
APP = f"""
name: chain
planner: paper
vertices:
  src: {{code: {V}:CountingSource, pinned: N1, rate: 100, output: {V}:Seq}}
  a: {{code: {V}:PassThrough, input: {V}:Seq, output: {V}:Seq}}
  b: {{code: {V}:PassThrough, input: {V}:Seq, output: {V}:Seq}}
  c: {{code: {V}:PassThrough, input: {V}:Seq, output: {V}:Seq}}
  sink: {{code: {V}:GapSink, pinned: N5, input: {V}:Seq}}
edges: [[src, a], [a, b], [b, c], [c, sink]]
"""
NODES = ("N1", "N2", "N3", "N4", "N5")
MOVABLE = ("a", "b", "c")
END = "N5"  # the captured chain end: the tail's host


def run(attack: str, strict: bool, seconds: float, every: float) -> dict[str, Any]:
    operator = Signer()
    links = [LinkSpec(x, y, delay_ms=1.0) for x, y in itertools.pairwise(NODES)]
    sim = Simulation(Network([NodeSpec(n) for n in NODES], links))
    for core in sim.cores.values():
        core.authority = Authority.configure([operator.public_text()])
        core.authority.strict_moves = strict
    sim.request("N1", m.DeployRequest(operator.grant(APP, 1000), "app.yaml"))
    sim.run_until(1.0)
    head, tail = sim.cores["N1"], sim.cores[END]
    asked = 0
    turn = itertools.count()
    delays: list[float] = []
    paths = {v: [tail.apps["chain"].placed[v]] for v in MOVABLE}
    t, next_ask = sim.now, sim.now
    end = 1.0 + seconds
    while t < end:
        if attack != "-" and t >= next_ask:
            dep = tail.apps["chain"]
            for v in MOVABLE:
                here = dep.placed[v]
                if attack == "pull":
                    to = END
                else:  # churn: the next node round that is not where it runs
                    others = [n for n in NODES if n != here]
                    to = others[next(turn) % len(others)]
                if to != here:
                    asked += 1
                    tail.relocator.request(None, m.RelocateRequest("chain", v, target=to), t)
            sim.apply(END, tail._run(t))
            next_ask = t + every
        t = min(end, t + min(every, 0.5))
        sim.run_until(t)
        delays += list(tail.status(t)["apps"]["chain"]["chain_delay_ms"].values())
        for v in MOVABLE:
            where = tail.apps["chain"].placed[v]
            if where != paths[v][-1]:
                paths[v].append(where)
    sim.run_until(end + 5.0)  # the stream drains
    sink = tail.status(sim.now)["apps"]["chain"]["vertices"]["sink"]["stats"]
    sent = head.instances("chain")["src"].emitted
    twins = sum(  # (only the app's holders hold it: issue 24.1)
        len(c.apps["chain"].awaiting) for c in sim.cores.values() if "chain" in c.apps
    )
    refused: dict[str, int] = {}
    for core in sim.cores.values():
        for why, k in core.refusals.items():
            if why.startswith("move_"):
                refused[why] = refused.get(why, 0) + k
    return {
        "attack": attack,
        "strict": strict,
        "asked": asked,
        "moves": sum(len(p) - 1 for p in paths.values()),
        "paths": {v: p for v, p in paths.items()},
        "refused": refused,
        "twins_left": twins,
        "sent": sent,
        "received": int(sink["count"]),
        "lost": max(0, sent - int(sink["next"])) + int(sink.get("missing", 0)),
        "repeats": int(sink["repeats"]),
        "out_of_order": int(sink["out_of_order"]),
        "max_gap_ms": round(float(sink["max_gap_ms"]), 1),
        "delay_p50_ms": round(statistics.median(delays), 1) if delays else None,
        "delay_p99_ms": round(_p99(delays), 1) if delays else None,
        "delay_max_ms": round(max(delays), 1) if delays else None,
    }


def _p99(xs: list[float]) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(0.99 * len(s)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--every", type=float, default=1.0, help="how often the head asks (s)")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "chain_end.json")
    args = ap.parse_args()
    if not (5.0 <= args.seconds <= 3600.0) or math.isnan(args.seconds):
        ap.error("--seconds: 5..3600")
    if not (0.1 <= args.every <= 60.0) or math.isnan(args.every):
        ap.error("--every: 0.1..60")
    t0 = time.time()
    cases = [("-", False), ("churn", False), ("pull", False), ("churn", True)]
    rows = []
    for attack, strict in cases:
        rows.append(run(attack, strict, args.seconds, args.every))
        print(rows[-1], file=sys.stderr)
    lines = [
        f"A captured chain end (N5, the tail's host) moving its chain's vertices, asking "
        f"every {args.every:g} s for {args.seconds:g} s simulated (N1 - N2 - N3 - N4 - N5, "
        "100 events/s)",
        "",
        "| attack | strict | asked | moves taken | refused | sent | lost | repeats "
        "| reordered | longest gap ms | delay p50/p99/max ms | twins left |",
        "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        refused = ", ".join(f"{k[5:]} {v}" for k, v in sorted(r["refused"].items())) or "-"
        lines.append(
            f"| {r['attack']} | {'yes' if r['strict'] else 'no'} | {r['asked']} | {r['moves']} "
            f"| {refused} | {r['sent']} | {r['lost']} | {r['repeats']} | {r['out_of_order']} "
            f"| {r['max_gap_ms']} | {r['delay_p50_ms']}/{r['delay_p99_ms']}/{r['delay_max_ms']} "
            f"| {r['twins_left']} |"
        )
    result = {"rows": rows, "seconds": time.time() - t0, **provenance()}
    write_results(args.json, result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
