"""A source whose daemon restarted numbers its edge on from the bound its last process saved,
past numbers its consumer never got; the positions of that process's last ack may be gone with
it (its ack lost). The consumer's answer to the source's restore says where its outputs stand
(exact: it has processed everything before), and the edge keeps them at its new start: a later
replacement of the consumer, fed the replay from there, numbers what it makes as the lost
instance did (fault seed 202193: with none, a chain's replacement numbered the replay to a sink
from where the sink stood, and 6 events reached it twice). Likewise a replacement's output
numbered on a guess, once a consumer takes it: the producer is told where it starts (seed
309522).

N1 - N2 - N3 - N4, ``pipe`` deployed: src on N1, mid on N3, sink on N4."""

from __future__ import annotations

import pytest

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.channel import InChannel, OutChannel
from mso.protocol.procedures.instance import H
from mso.protocol.state import AppState, Restoring
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app


def line_of_four() -> Network:
    """N1 - N2 - N3 - N4, 1 ms a hop: ``pipe``'s source on N1, its sink pinned on N4."""
    return Network(
        [NodeSpec(n) for n in ("N1", "N2", "N3", "N4")],
        [LinkSpec(a, b, delay_ms=1.0) for a, b in (("N1", "N2"), ("N2", "N3"), ("N3", "N4"))],
    )


def test_a_restarted_sources_edge_keeps_its_consumers_positions_at_its_new_start() -> None:
    sim = Simulation(line_of_four())
    sim.request("N1", m.DeployRequest(pipe_app(20), "app.yaml"))
    sim.run_until(1.5)
    assert sim.hosts("pipe", "mid") == ["N3"]
    # the source's node hears no ack from here on: its last saved positions fall behind
    sim.drop = lambda src, dst, msg: dst == "N1" and isinstance(msg, m.Ack)
    sim.run_until(2.0)
    sim.crash("N1")
    sim.run_until(2.05)
    sim.revive("N1")
    sim.run_until(2.5)
    edge = sim.cores["N1"].apps["pipe"].out[0]  # src -> mid, restored
    mid = sim.cores["N3"].apps["pipe"]
    assert edge.acked < edge.next_seq == mid.inc[0].expected  # mid took the new numbers
    assert 1 in edge.positions, edge.positions  # where mid's output stood at the edge's start
    made = mid.inc[0].expected - edge.acked  # mid makes one event of each (Double)
    assert edge.positions[1] + made == mid.out[1].next_seq


def replacement(sim: Simulation, node: str, vertex: str, restoring: Restoring) -> AppState:
    """``vertex``'s instance on ``node`` turned into a replacement awaiting its restore."""
    dep = sim.cores[node].apps["pipe"]
    h = dep.instances.pop(vertex)
    dep.gates.pop(vertex, None)  # (the lost instance's checkpoints went with it)
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting[vertex] = h
    dep.restoring[vertex] = restoring
    return dep


def guessed_mid() -> tuple[Simulation, OutChannel, AppState]:
    """``pipe`` on a line, the sink's acks lost (nothing is acknowledged upstream: a cut
    further down), and mid on N3 replaced with its consumer lost too: its output is a guess.
    The source's edge, and mid's."""
    sim = Simulation(line_of_four())
    sim.drop = lambda src, dst, msg: src == "N4" and isinstance(msg, m.Ack)
    sim.request("N1", m.DeployRequest(pipe_app(20), "app.yaml"))
    sim.run_until(1.0)
    assert sim.hosts("pipe", "mid") == ["N3"]
    edge = sim.cores["N1"].apps["pipe"].out[0]  # src -> mid
    assert not edge.positions
    mid = replacement(sim, "N3", "mid", Restoring(98, "N2", set(), resumed={0}, fetched=True))
    mid.inc[0] = InChannel.starting_at(edge.acked, True)
    sim.cores["N3"].restorer.activate(mid, "mid")
    assert mid.out[1].guessed and mid.out[1].gen
    assert not edge.positions  # (a guess no consumer took: not told)
    return sim, edge, mid


def test_a_guessed_numbering_its_consumer_takes_is_told_to_the_producer_at_its_start() -> None:
    """A replacement whose consumer was lost too numbers its output on a guess (no ack's
    positions, no consumer's word); the consumer's replacement takes it. The producer is told
    where the guess starts, with an ack at the input's start: lost again before its consumer
    acknowledged anything (the chained acks held further down), the next replacement numbers
    the replay as the guess did, and the consumer drops what it has. Told nothing, it
    numbered the replay from where the consumer stood, past what it had, and the consumer
    took it all again (fault seed 309522: a restored source's first 3 events twice at the
    sink, through a merge restored on the other side of a cut)."""
    sim, edge, mid = guessed_mid()
    start, guess = edge.acked, mid.out[1]
    # the sink's replacement takes it (the restore's rewire of mid's output, answered)
    sink = replacement(sim, "N4", "sink", Restoring(99, "N2", {(1, True)}, fetched=True))
    del sink.inc[1]
    rewire = m.Rewire("pipe", 1, "N4", 99, True)
    sim.apply("N3", sim.cores["N3"].receive("N2", rewire, sim.now))
    sim.run_until(sim.now + 0.05)
    assert "sink" in sink.instances and sink.inc[1].gen == guess.gen
    assert edge.acked == edge.positions_at == start  # an ack at the input's start
    assert edge.positions == {1: guess.origin} and edge.gens == {1: guess.gen}
    # mid lost again: its next replacement numbers the replay as the guess did, not from
    # where the sink stands
    at = sink.inc[1].expected
    assert at > guess.origin
    again = Restoring(
        97, "N2", set(), resumed={0}, positions=dict(edge.positions), gens=dict(edge.gens),
        consumer_start={1: at}, consumer_gen={1: guess.gen}, fetched=True,
    )  # fmt: skip
    mid = replacement(sim, "N3", "mid", again)
    mid.inc[0] = InChannel.starting_at(start, True)
    sim.cores["N3"].restorer.activate(mid, "mid")
    assert mid.out[1].origin == guess.origin and mid.out[1].gen == guess.gen


def test_a_told_guess_that_its_consumer_did_not_take_is_told_again_in_the_consumers_terms() -> None:
    """A restore's rewire confirmed the guess, but the consumer runs (another coordinator
    restored it first: restart seed 138982) and stands in its own numbering: the output takes
    that numbering (``Restorer._renumber``), and the producer is told again where the input's
    start stands in it. Left with the guess's position, the next replacement would number
    the replay in a numbering the consumer never took, from below where it stands."""
    sim, edge, mid = guessed_mid()
    start, guess = edge.acked, mid.out[1]
    sink = sim.cores["N4"].apps["pipe"]
    at = sink.inc[1].expected
    rewire = m.Rewire("pipe", 1, "N4", 99, True)  # (as of a sink restored there)
    sim.apply("N3", sim.cores["N3"].receive("N2", rewire, sim.now))
    sim.run_until(sim.now + 0.05)
    assert mid.out[1] is not guess and mid.out[1].origin == at and mid.out[1].gen == 0
    assert edge.acked == edge.positions_at == start
    assert edge.positions == {1: at} and not edge.gens


def test_a_replacement_below_its_consumers_unheld_start_says_so_with_no_positions(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fork's replacement started its input past one consumer's marks (``unheld``: its
    producer was lost too, and its other consumer, lost too, lacks what lies below them). The
    producer's replacement numbers its output from its acks' positions, below that start, and
    knows no positions further down (a restarted source's edge knows its own only): it says
    where it starts all the same, so that the fork takes the replay from there. Said only with
    positions, the fork kept its start and its other consumer never got the events below the
    marks (fault seed 340535: 6 of a source's events never reached one sink)."""
    sim = Simulation(line_of_four())
    sim.request("N1", m.DeployRequest(pipe_app(20), "app.yaml"))
    sim.run_until(1.0)
    assert sim.hosts("pipe", "mid") == ["N3"] and sim.hosts("pipe", "sink") == ["N4"]
    core = sim.cores["N3"]
    edge = sim.cores["N1"].apps["pipe"].out[0]  # src -> mid
    at = core.apps["pipe"].out[1].next_seq  # where mid's output stands: its replay's start
    restoring = Restoring(
        96, "N2", set(), resumed={0}, positions={1: at}, consumer_start={1: at + 6},
        consumer_gen={1: 0}, unheld={1}, fetched=True,
    )  # fmt: skip
    mid = replacement(sim, "N3", "mid", restoring)
    mid.inc[0] = InChannel.starting_at(edge.acked, True)
    sent: list[tuple[str, m.Message]] = []
    send = core.send
    monkeypatch.setattr(core, "send", lambda dst, msg: (sent.append((dst, msg)), send(dst, msg)))
    core.restorer.activate(mid, "mid")
    said = [msg for dst, msg in sent if dst == "N4" and isinstance(msg, m.Resume)]
    assert [(r.edge, r.producer, r.start, r.positions) for r in said] == [(1, True, at, {})]


def test_a_survivor_past_the_acks_positions_in_another_numbering_numbers_the_output() -> None:
    """The producer's acks say where a replacement's output stood in a numbering a twin of
    its consumer took (restored across a cut, lost since), and the consumer that answers the
    rewire survived the cut: it stands past those positions in its own numbering, which it
    never left. Its word wins, and the producer is told where the input's start stands in
    it. Numbered from the acks' positions, what the replacement made took numbers below where
    the consumer stood, and it dropped them as had (fault seed 327842: a restarted source's
    first 8 events)."""
    sim, edge, mid = guessed_mid()
    start, guess = edge.acked, mid.out[1]
    sink = sim.cores["N4"].apps["pipe"]
    at = sink.inc[1].expected  # the sink, running in the first numbering all along
    assert at > 5 and sink.inc[1].gen == 0 and guess.gen
    again = Restoring(
        97, "N2", set(), resumed={0}, positions={1: at - 5}, gens={1: guess.gen},
        consumer_start={1: at}, consumer_gen={1: 0}, fetched=True,
    )  # fmt: skip
    mid = replacement(sim, "N3", "mid", again)
    mid.inc[0] = InChannel.starting_at(start, True)
    sim.cores["N3"].restorer.activate(mid, "mid")
    assert mid.out[1].origin == at and mid.out[1].gen == 0 and not mid.out[1].guessed
    sim.run_until(sim.now + 0.05)
    assert edge.acked == edge.positions_at == start
    assert edge.positions == {1: at} and not edge.gens
