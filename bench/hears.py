"""How long a captured member's "I hear it" keeps a dead node from being declared (issue 27).

The simulator's overlay of tests/test_security_hears.py: a pipe src (N1) -> mid (N3) -> sink
(N4) at 100 events/s over N1 - N2 - N3 - N4, N2 - N5 - N4 and N1 - N6 - N3; N6 hosts and relays
nothing of the pipe. N3 dies; the liars (captured members, with their own node identities)
answer every ``Suspect`` about N3 with yes, echoing the asker's challenge with the best proof
they have — N3's real answer to an earlier question (kept from a route missing a moment while
N3 lived), else made-up bytes. Cases: nobody lies; N6 lies; N6 lies and is the only member
every asker can ask (the suspect's one neighbour it reaches); N2 and N6 lie. Each with the
rules of a member's word alone (*windows*: one member's yes for 4 liveness windows, members'
for 40 — what a node without identities has) and with the suspect's own signed word required
(*proofs*: a yes counts only with N3's answer to the asker's fresh challenge), in one run.

Usage: .venv/bin/python bench/hears.py [--json FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import Effect
from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.protocol.procedures.membership import suspicion
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
V = "mso.benchmarks.vertices.failure"
PIPE = f"""
name: pipe
planner: paper
vertices:
  src: {{code: {V}:CountingSource, pinned: N1, rate: 100, output: {V}:Seq}}
  mid: {{code: {V}:PassThrough, input: {V}:Seq, output: {V}:Seq}}
  sink: {{code: {V}:GapSink, pinned: N4, input: {V}:Seq}}
edges: [[src, mid], [mid, sink]]
"""
LINKS = [("N1", "N2"), ("N2", "N3"), ("N3", "N4"), ("N2", "N5"), ("N5", "N4")]
LINKS += [("N1", "N6"), ("N6", "N3")]
HORIZON_S = 30.0  # simulated after N3 dies: past the 20 s of members' windows
CASES: list[tuple[str, list[str], bool]] = [
    ("nobody", [], False),
    ("one member (N6)", ["N6"], False),
    ("the only member asked (N6)", ["N6"], True),
    ("two members (N2, N6)", ["N2", "N6"], False),
]


def liar(sim: Simulation, node: str, about: str) -> list[int]:
    """``node`` answers every ``Suspect`` about ``about`` yes, with the best proof it has."""
    core, told, proofs = sim.cores[node], [], [os.urandom(64)]
    receive = core.receive

    def lying(src: str, msg: m.Message, now: float) -> list[Effect]:
        if isinstance(msg, m.Hears) and msg.node == about and msg.proof:
            proofs.append(msg.proof)
        if isinstance(msg, m.Suspect) and msg.node == about:
            told.append(msg.rid)
            return [Send(src, m.Hears(about, msg.rid, True, 0, msg.nonce, proofs[-1]))]
        return receive(src, msg, now)

    core.receive = lying  # type: ignore[method-assign]
    return told


def only_asked(member: str, about: str) -> Callable[[], None]:
    """Every node but ``member`` can ask only ``member`` about ``about``; returns the undo."""
    ask_whom = suspicion.ask_whom

    def only(suspect: str, me: str, *args: Any, **kw: Any) -> list[str]:
        return [member] if suspect == about and me != member else ask_whom(suspect, me, *args, **kw)

    suspicion.ask_whom = only

    def undo() -> None:
        suspicion.ask_whom = ask_whom

    return undo


def run(liars: list[str], only: bool, proofs: bool) -> dict[str, Any]:
    net = Network([NodeSpec(f"N{i}") for i in range(1, 7)], [LinkSpec(a, b, 1.0) for a, b in LINKS])
    sim = Simulation(net, proofs=proofs)
    sim.request("N1", m.DeployRequest(PIPE, "pipe.yaml"))
    sim.run_until(2.0)
    placed = dict(sim.cores["N1"].apps["pipe"].placed)
    assert placed["mid"] == "N3", placed
    told = [liar(sim, n, "N3") for n in liars]
    sim.lose_route("N1", "N3")  # a route missing a moment while N3 lives (a proof to replay)
    sim.run_until(sim.now + 1.0)
    sim.lose_route("N1", "N3", lost=False)
    sim.run_until(sim.now + 1.0)
    t0 = sim.now
    undo = only_asked("N6", "N3") if only else (lambda: None)
    still, last, since = 0.0, -1, t0  # the longest the sink's count stood still
    try:
        sim.kill("N3", convergence_s=0.3)
        while sim.now < t0 + HORIZON_S:
            sim.run_until(sim.now + 0.1)
            count = int(sim.instance("N4", "pipe", "sink").stats()["count"])
            if count != last:
                last, since = count, sim.now
            still = max(still, sim.now - since)
    finally:
        undo()
    survivors = [n for n in sim.cores if n != "N3"]
    at = [f["at"] for n in survivors for f in sim.cores[n].failures if f["node"] == "N3"]
    (sink,) = [c for n, c in sim.cores.items() if n != "N3" and "sink" in c.instances("pipe")]
    got = sink.status(sim.now)["apps"]["pipe"]["vertices"]["sink"]
    refusals: dict[str, int] = {}
    for n in survivors:
        for k, v in sim.cores[n].status(sim.now)["refusals"].items():
            if k.startswith("hears_"):
                refusals[k] = refusals.get(k, 0) + int(v)
    return {
        "liars": liars,
        "only_member_asked": only,
        "rules": "proofs" if proofs else "windows",
        "asked_liars": sum(len(t) for t in told),
        "declared_after_s": round(min(at) - t0, 2) if at else None,
        "sent": sim.cores["N1"].instances("pipe")["src"].emitted,
        "received": int(got["processed"]),
        "repeats": int(got["stats"].get("repeats", 0)),
        "out_of_order": int(got["stats"].get("out_of_order", 0)),
        "stood_still_s": round(still, 1),
        "refusals": refusals,
        "proofs_stripped": sim.proofs_refused,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, default=HERE / "results" / "hears.json")
    args = ap.parse_args()
    t0 = time.time()
    rows = []
    for name, liars, only in CASES:
        for proofs in (False, True):
            rows.append({"case": name, **run(liars, only, proofs)})
            print(rows[-1], file=sys.stderr)
    lines = [
        f"N3 (mid's host) dies; the liars answer yes for it; {HORIZON_S:g} s simulated after, "
        "liveness window 0.5 s; windows = a member's word (no identities), proofs = the "
        "suspect's own signed answer required (node identities)",
        "",
        "| liars | rules | declared after s | stream stood still s | liars asked | sent "
        "| received | repeats | reordered | set aside | proofs stripped |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        aside = ", ".join(f"{k} {v}" for k, v in sorted(r["refusals"].items())) or "-"
        lines.append(
            f"| {r['case']} | {r['rules']} | {r['declared_after_s']} | {r['stood_still_s']} "
            f"| {r['asked_liars']} | {r['sent']} | {r['received']} | {r['repeats']} "
            f"| {r['out_of_order']} | {aside} | {r['proofs_stripped']} |"
        )
    result = {"rows": rows, "seconds": time.time() - t0, **provenance()}
    write_results(args.json, result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
