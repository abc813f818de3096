"""Taps (mso echo / hz / record) in the simulator, on the virtual clock: a client's tap is served
by the consumer's node (or relayed by the node asked), copies come bounded by the rate asked,
the edge itself loses nothing to a tap, a tap follows its consumer when it moves, and a tap
nobody renews ends."""

from __future__ import annotations

import msgspec
import pytest

from mso.api import TapCounts
from mso.model.appfile import loads_app
from mso.protocol import messages as m
from mso.protocol.taps import FLUSH_S, MAX_SERVED, find_edge
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app
from test_failure import PIPE, started, where
from test_runtime_sim import deploy, line, sink_stats

CLIENT = 7


def taps(sim: Simulation, since: int = 0, client: int = CLIENT) -> list[m.TapEvents]:
    return [r for _, c, r in sim.replies[since:] if c == client and isinstance(r, m.TapEvents)]


def keep(sim: Simulation, node: str, tap: m.Tap, seconds: float, client: int = CLIENT) -> None:
    """Run ``seconds``, asking again every second as a client does."""
    end = sim.now + seconds
    while sim.now < end:
        sim.request(node, tap, client=client)
        sim.run_until(min(end, sim.now + 1.0))


def copies(replies: list[m.TapEvents]) -> list[int]:
    return [s for r in replies for s in r.seqs]


def test_edge_names_resolve_or_say_what_there_is() -> None:
    app = loads_app(pipe_app(10), file="pipe.yaml")
    assert find_edge(app, "src->mid") == 0
    assert find_edge(app, "mid:sink") == 1
    assert find_edge(app, "mid") == 1  # a vertex with one output edge
    assert "has no output edge" in str(find_edge(app, "sink"))
    assert "no edge 'src->sink' (edges: src->mid, mid->sink)" in str(find_edge(app, "src->sink"))
    assert "no vertex or edge 'nope'" in str(find_edge(app, "nope"))


def test_a_tap_relayed_by_the_node_asked_copies_at_most_the_rate_and_costs_the_edge_nothing() -> (
    None
):
    sim = Simulation(line(4))
    assert deploy(sim, pipe_app(100)).ok
    host = sim.cores["N4"]  # the sink's node serves a tap of mid->sink
    n = len(sim.replies)
    keep(sim, "N1", m.Tap("pipe", "mid->sink", 10.0, 3.0), 4.0)
    got = taps(sim, n)
    assert got and all(r.node == "N4" and not r.ended for r in got), got[:2]
    seqs = copies(got)
    assert 30 <= len(seqs) <= 45, len(seqs)  # 10 a second for ~4 s (and a first burst)
    assert seqs == sorted(set(seqs)), "copies in the edge's order, none twice"
    assert got[-1].seen >= 350, got[-1].seen  # every event counted, 100 a second
    assert got[-1].dropped == got[-1].seen - len(seqs)
    assert all(0 < d < 100 for r in got for d in r.delays_ms)
    event = msgspec.msgpack.decode(got[-1].events[-1])
    assert got[-1].format == "runtime_vertices:Num" and event["seq"] == seqs[-1]
    # the edge itself: nothing lost, nothing out of order
    stats = sink_stats(sim, "pipe", "sink")
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0 and stats["count"] > 500
    assert host.dataplane.taps.served and sim.cores["N1"].dataplane.taps.relays


def test_counts_only_and_an_unrenewed_tap_ends_everywhere() -> None:
    sim = Simulation(line(4))
    assert deploy(sim, pipe_app(50)).ok
    n = len(sim.replies)
    sim.request("N4", m.Tap("pipe", "mid", 0.0, 1.0), client=CLIENT)  # served where asked
    sim.run_until(sim.now + 0.9)
    got = taps(sim, n)
    assert got and not copies(got) and got[-1].seen >= 35
    sim.run_until(sim.now + 1.0)  # not asked again: the lease ran out
    assert not sim.cores["N4"].dataplane.taps.served
    quiet = len(sim.replies)
    sim.run_until(sim.now + 2.0)
    assert not taps(sim, quiet), "nothing more after the lease"
    sim.request("N2", m.Tap("pipe", "mid", 0.0, 1.0), client=CLIENT)
    sim.run_until(sim.now + 3.0)
    assert not sim.cores["N2"].dataplane.taps.relays
    assert not sim.cores["N4"].dataplane.taps.served


def test_bad_requests_end_at_once_with_why() -> None:
    sim = Simulation(line(2))
    assert deploy(sim, pipe_app(10).replace("N4", "N2")).ok
    for tap, why in (
        (m.Tap("nope", "a->b", 1.0, 3.0), "no running app named 'nope'"),
        (m.Tap("pipe", "sink->src", 1.0, 3.0), "no edge 'sink->src'"),
        (m.Tap("pipe", "mid", -1.0, 3.0), "rate: expected"),
        (m.Tap("pipe", "mid", float("nan"), 3.0), "rate: expected"),
    ):
        n = len(sim.replies)
        sim.request("N1", tap, client=CLIENT)
        sim.run_until(sim.now + 0.1)  # (an app N1 holds none of is looked for first)
        (reply,) = taps(sim, n)
        assert why in reply.ended, reply.ended
    for client in range(MAX_SERVED + 1):  # bounded: the next one is refused, with why
        sim.request("N2", m.Tap("pipe", "mid", 1.0, 3.0), client=100 + client)
    refused = taps(sim, 0, client=100 + MAX_SERVED)
    assert refused and "serves 16 taps already" in refused[-1].ended


def test_a_tap_follows_its_consumer_when_it_moves() -> None:
    sim = Simulation(line(4))
    assert deploy(sim, pipe_app(100)).ok
    mid_at = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    n = len(sim.replies)
    tap = m.Tap("pipe", "src->mid", 20.0, 3.0)
    keep(sim, "N1", tap, 1.5)
    target = "N3" if mid_at != "N3" else "N2"
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    keep(sim, "N1", tap, 2.5)
    got = taps(sim, n)
    assert not any(r.ended for r in got), [r.ended for r in got if r.ended]
    assert {r.node for r in got} == {mid_at, target}, {r.node for r in got}
    after = [s for r in got if r.node == target for s in r.seqs]
    assert after and min(after) > max(s for r in got if r.node == mid_at for s in r.seqs)
    counts = TapCounts()  # what a client shows: counts since the tap opened, across the move
    seen = [counts.carry(r).seen for r in got]
    assert seen == sorted(seen), seen
    before = max(r.seen for r in got if r.node == mid_at)
    assert seen[-1] > before + 100, (before, seen[-1])  # the new host's on top of the old's
    assert FLUSH_S < 1.0


@pytest.mark.parametrize(
    ("edge", "asked"),
    [
        ("src->mid", "elsewhere"),
        ("src->mid", "old host"),
        ("src->mid", "new host"),
        ("mid->sink", "elsewhere"),  # its producer moves
    ],
)
def test_a_tap_misses_no_event_when_the_edge_moves(edge: str, asked: str) -> None:
    """Every copy at a rate above the edge's: the copies go on across the move of the
    edge's consumer (or producer) with no seq left out and none twice, whichever node the
    client asks (a relay, the consumer's old host, its new host)."""
    sim = Simulation(line(4))
    assert deploy(sim, pipe_app(100)).ok
    mid_at = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    target = "N3" if mid_at != "N3" else "N2"
    node = {"elsewhere": "N1", "old host": mid_at, "new host": target}[asked]
    n = len(sim.replies)
    tap = m.Tap("pipe", edge, 1000.0, 3.0)
    keep(sim, node, tap, 1.5)
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    keep(sim, node, tap, 2.5)
    assert "mid" in sim.cores[target].instances("pipe")
    got = taps(sim, n)
    assert not any(r.ended for r in got), [r.ended for r in got if r.ended]
    hosts = {mid_at, target} if edge == "src->mid" else {"N4"}
    assert {r.node for r in got} == hosts, {r.node for r in got}
    seqs = copies(got)
    assert len(seqs) > 300, len(seqs)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "a gap or a repeat at the move"
    counts = TapCounts()
    last = [counts.carry(r) for r in got][-1]
    assert (last.seen, last.dropped) == (len(seqs), 0)


def test_a_tap_goes_on_after_its_consumers_node_fails() -> None:
    """The consumer's host dies and the vertex is restored elsewhere: the node relaying the
    tap learns where from the restore and asks there at the client's next renewal."""
    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    n = len(sim.replies)
    tap = m.Tap("pipe", "src->mid", 20.0, 3.0)
    keep(sim, "N1", tap, 1.5)
    sim.kill(victim, convergence_s=0.3)
    keep(sim, "N1", tap, 5.0)
    now_at = where(sim, "pipe", "mid")
    got = taps(sim, n)
    assert not any(r.ended for r in got), [r.ended for r in got if r.ended]
    assert now_at != victim and got[-1].node == now_at, (now_at, [r.node for r in got][-3:])
    assert copies([r for r in got if r.node == now_at]), "no copies from the new host"
