"""A captured member's "yes, I hear it" (issue 27): a node that lost its route to a node asks a
few members whether they hear it (a ``Suspect``), and a ``Hears`` yes kept the node from being
declared. A captured member answering yes for a dead node kept it alive for ever at every node
that asked it — apps it hosts nothing of stopped for good. Now one member's uncorroborated yes
keeps a suspect alive for at most ``LONE_YES_WINDOWS`` liveness windows (until this node hears
the node itself); two members that hear it, or the only member there is to ask, still keep it
alive as long as they hear it (a routing view that lags, as babeld's did for 12 s) — for at
most ``MEMBERS_YES_WINDOWS`` windows (20 s): two captured members kept a dead node alive for
ever.

In the simulator, whose sources are proven as with node identities."""

from __future__ import annotations

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import Effect
from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.protocol.procedures.membership.claims import (
    LONE_YES_WINDOWS,
    MEMBERS_YES_WINDOWS,
    Vouchers,
)
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app
from test_failure import emitted, recoveries, started, stats, where

# src on N1, mid on N3 (re-placeable: N1 - N2 - N5 - N4 avoids it), sink pinned on N4; N6 is a
# neighbour of N3 and of N1 that hosts nothing of the app and relays none of its edges
LINKS = [("N1", "N2"), ("N2", "N3"), ("N3", "N4"), ("N2", "N5"), ("N5", "N4")]
LINKS += [("N1", "N6"), ("N6", "N3")]
DEAD_AFTER_S = 0.5


def overlay() -> Simulation:
    net = Network([NodeSpec(f"N{i}") for i in range(1, 7)], [LinkSpec(a, b, 1.0) for a, b in LINKS])
    sim = started(pipe_app(100), net)
    assert {v: where(sim, "pipe", v) for v in ("src", "mid", "sink")} == {
        "src": "N1",
        "mid": "N3",
        "sink": "N4",
    }
    assert not sim.cores["N6"].apps["pipe"].instances
    return sim


def captured(sim: Simulation, node: str, about: str) -> list[int]:
    """``node`` answers every ``Suspect`` about ``about`` with yes, heard just now; returns the
    list its answers are counted in."""
    core, told = sim.cores[node], []
    receive = core.receive

    def lying(src: str, msg: m.Message, now: float) -> list[Effect]:
        if isinstance(msg, m.Suspect) and msg.node == about:
            told.append(msg.rid)
            return [Send(src, m.Hears(about, msg.rid, True, 0))]
        return receive(src, msg, now)

    core.receive = lying  # type: ignore[method-assign]
    return told


def refused(sim: Simulation, reason: str) -> int:
    return sum(int(c.status(sim.now)["refusals"].get(reason, 0)) for c in sim.cores.values())


def test_a_captured_members_yes_does_not_keep_a_dead_node_from_being_declared() -> None:
    sim = overlay()
    told = captured(sim, "N6", "N3")
    t0 = sim.now
    sim.kill("N3", convergence_s=0.3)
    sim.run_until(t0 + 10.0)
    assert told, "N6 was never asked: the attack did not happen"
    survivors = [n for n in sim.cores if n != "N3"]
    for n in survivors:
        assert sim.cores[n].failed == {"N3"}, (n, sim.cores[n].failed)
    declared = min(f["at"] for n in survivors for f in sim.cores[n].failures) - t0
    # the lone yes bought at most its windows, then the next suspicion: about 2.9 s, not never
    assert declared <= (LONE_YES_WINDOWS + 2) * DEAD_AFTER_S + 0.5, declared
    assert refused(sim, "hears_uncorroborated") >= 1
    (rec,) = recoveries(sim, "pipe")
    assert rec["ok"] and rec["lost"] == ["mid"], rec
    assert where(sim, "pipe", "mid") not in ("N3", "N6")
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent  # the app N6 hosts nothing of recovered whole


def test_members_that_hear_a_node_keep_it_alive_however_long_a_route_is_missing() -> None:
    """N1 needs N3 (it runs mid) and has no route to it for 6 s while N2, N4 and N6 hear it:
    two yeses each time, so N1 never declares it, however long babeld takes."""
    sim = overlay()
    instance = sim.cores["N3"].instances("pipe")["mid"].instance
    sim.lose_route("N1", "N3")
    sim.lose_route("N3", "N1")
    sim.run_until(sim.now + 6.0)
    for n, core in sim.cores.items():
        assert core.failed == set(), (n, core.failed)
    sim.lose_route("N1", "N3", lost=False)  # babeld converges: nothing was disturbed
    sim.lose_route("N3", "N1", lost=False)
    sim.run_until(sim.now + 2.0)
    for n, core in sim.cores.items():
        assert core.failed == set(), (n, core.failed)
    assert refused(sim, "hears_uncorroborated") == 0
    assert sim.cores["N3"].instances("pipe")["mid"].instance == instance
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0 and sent - 5 <= got["count"]


def test_a_lone_yes_counts_for_its_windows_until_the_node_is_heard_itself() -> None:
    v, grace = Vouchers(), LONE_YES_WINDOWS * DEAD_AFTER_S
    assert v.counts("S", {"X"}, 3, now=10.0, grace_s=grace)  # one of three: for a while
    assert v.counts("S", {"X"}, 3, now=10.0 + grace, grace_s=grace)
    assert not v.counts("S", {"X"}, 3, now=10.1 + grace, grace_s=grace)  # then no more
    assert v.counts("S", {"X"}, 1, now=99.0, grace_s=grace)  # the only one asked: its word
    assert v.counts("S", {"X", "Y"}, 3, now=99.0, grace_s=grace)  # two: corroborated ...
    assert v.counts("S", {"X"}, 3, now=99.0, grace_s=grace)  # ... and the clock starts again
    v.heard("S")  # heard itself: a later lone yes has its windows again
    assert v.counts("S", {"X"}, 3, now=200.0, grace_s=grace)
    assert v.lone == {"S": 200.0}


def test_two_captured_members_keep_a_dead_node_alive_only_for_their_windows() -> None:
    """N2 and N6, both neighbours of N3, answer yes for it after it died (and claim nothing):
    two members' word. It used to keep N3 alive for ever (the sink stopped at 200 of 3,200
    events in 30 s); now for at most ``MEMBERS_YES_WINDOWS`` windows, then N3 is declared and
    mid restored, the app whole."""
    sim = overlay()
    told = [captured(sim, n, "N3") for n in ("N2", "N6")]
    t0 = sim.now
    sim.kill("N3", convergence_s=0.3)
    sim.run_until(t0 + 23.0)
    assert all(told), "the liars were never asked: the attack did not happen"
    survivors = [n for n in sim.cores if n != "N3"]
    declared = min(f["at"] for n in survivors for f in sim.cores[n].failures) - t0
    bound = MEMBERS_YES_WINDOWS * DEAD_AFTER_S
    assert bound - 1.0 <= declared <= bound + 2 * DEAD_AFTER_S, declared
    assert refused(sim, "hears_uncorroborated") >= 1
    sim.run_until(t0 + 26.0)
    assert where(sim, "pipe", "mid") not in ("N3", "N2", "N6")
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent


def test_members_yes_counts_for_their_windows_until_the_node_is_heard_itself() -> None:
    v, bound, grace = Vouchers(), MEMBERS_YES_WINDOWS * DEAD_AFTER_S, 2.0

    def episode(start: float) -> float:
        """Two members' yes every second from ``start`` while it counts; when it stopped."""
        t = start
        while v.counts("S", {"X", "Y"}, 3, now=t, grace_s=grace, bound_s=bound):
            t += 1.0
        return t - start

    assert episode(10.0) == bound + 1.0  # counted for its windows, then no more
    assert not v.counts("S", {"X"}, 1, now=10.0 + bound + 1.5, grace_s=grace, bound_s=bound)
    v.heard("S")  # heard itself: members' word has its windows again
    assert episode(100.0) == bound + 1.0
    # an episode that ended (no yes for longer than grace_s), the node never heard directly
    # since (one this node hears only through others): the next one has its windows too
    assert episode(500.0) == bound + 1.0
