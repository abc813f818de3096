"""A node that learnt an app from syncs does not act on a placement it holds on hearsay alone
(issue 27): with operator keys, where a vertex runs is taken on a sync's word as a vote (one
a sender; :mod:`mso.protocol.procedures.membership.sync`), and on a tie — a captured member
and one honest member, each saying it runs the vertex itself, the case of a two-member app —
the captured member's first word used to stand: the node's events for that vertex went to
it. Now the vertex's events wait at the node (store and forward, as for a consumer out of
reach) until two senders agree or the node named says so itself and no sender names
another (:meth:`mso.protocol.state.AppState.unconfirmed`).

The simulator's line N1 - N2 - N3 - N4 - N5 runs src -> a -> b -> c -> sink, one vertex a
node; N6, linked to N5, restarts hosting nothing; the captured N2 syncs it first."""

from __future__ import annotations

from mso.model.network import LinkSpec
from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.protocol.state import AppState
from mso.sim.runner import Simulation
from test_captured_robot import robot, signed
from test_security_steps import line, sync

B_TO_C = 2  # the edge b -> c


def restarted() -> Simulation:
    sim = line(n6=("N5",))
    sim.kill("N6")
    sim.run_until(sim.now + 2.0)
    sim.network.add_link(LinkSpec("N5", "N6", delay_ms=5.0))
    sim.revive("N6")
    sim.update_routes()
    signed(sim, "N6")
    return sim


def sent(sim: Simulation, dep: AppState, at: float) -> list[tuple[str, list[bytes]]]:
    """Where N6 sends b's events on edge b -> c now (as if it hosted b), and what."""
    core = sim.cores["N6"]
    core.dataplane.send_events(dep, [B_TO_C], [b"e1", b"e2"], at, dep.layout.edge_chain[B_TO_C])
    return data(core._run(at))


def data(effects: list[object]) -> list[tuple[str, list[bytes]]]:
    return [
        (e.dst, e.said.events)
        for e in effects
        if isinstance(e, Send) and isinstance(e.said, m.Data) and e.said.edge == B_TO_C
    ]


def test_events_for_a_vertex_placed_on_a_tie_wait_for_a_second_word() -> None:
    """N2 says c runs on N2; c's host N4 says it runs on N4: a tie. N6 sends nothing of
    b's output to either (it used to send it to N2, the first word); the events wait. A
    second member's sync agrees with N4: c is placed on N4 and what waited goes there."""
    sim = restarted()
    robot(sim, "N6", sync(sim, {"c": "N2"}), src="N2")
    dep = sim.cores["N6"].apps["line"]
    assert not dep.unconfirmed("c")  # N2's own word, uncontested so far
    assert dep.unconfirmed("b")  # N2's word about N3: b's host has not spoken
    robot(sim, "N6", sync(sim, {}), src="N4")  # c's host: the truth, and a tie
    assert dep.placed["c"] == "N2" and dep.unconfirmed("c")
    assert not dep.unconfirmed("b")  # (two senders agree: N2 and N4)
    assert sent(sim, dep, sim.now) == []  # not to N2: held
    assert dep.out[B_TO_C].out_of_reach
    robot(sim, "N6", sync(sim, {}), src="N1")
    assert dep.placed["c"] == "N4" and not dep.hearsay
    sim.cores["N6"].dataplane.sf.retransmit("line", sim.now + 0.5)
    assert data(sim.cores["N6"]._run(sim.now + 0.5)) == [("N4", [b"e1", b"e2"])]


def test_a_hosts_own_uncontested_word_is_acted_on_at_once() -> None:
    """The honest case of a two-member app: c's host N4 syncs N6 first, alone: c is placed
    on N4 on its own word and b's events go there without waiting for a second sync."""
    sim = restarted()
    robot(sim, "N6", sync(sim, {}), src="N4")
    dep = sim.cores["N6"].apps["line"]
    assert dep.placed["c"] == "N4" and "c" in dep.hearsay and not dep.unconfirmed("c")
    assert sent(sim, dep, sim.now) == [("N4", [b"e1", b"e2"])]
