"""A failure declared on one node's missing route must be confirmed by the nodes it still
reaches: a node the others still hear is not declared failed (and reset) on one node's word,
while a node that every node has lost is still declared failed, about as fast as before.

Seen on the netns mesh: after a relay died, babeld left N4 with no route to N6 for over 12 s
while N3 still heard N6; N4 declared N6 failed every 3 s and N6 reset, dropping its sink."""

from __future__ import annotations

from mso.node.core import Effect, NodeCore, Send
from mso.protocol import messages as m
from mso.protocol.events import HeartbeatTick
from mso.sim.runner import Simulation
from test_failure import PIPE, emitted, recoveries, started, stats, where


def sink_instance(sim: Simulation) -> int:
    return sim.cores["N6"].instances("pipe")["sink"].instance


def assert_nobody_held_failed_but(sim: Simulation, dead: set[str]) -> None:
    for n, core in sim.cores.items():
        if n not in sim.killed:
            assert core.failed == dead, (n, core.failed)
            assert {f["node"] for f in core.failures} <= dead, (n, core.failures)


def test_a_node_that_loses_its_route_to_a_node_others_hear_does_not_declare_it() -> None:
    sim = started(PIPE)  # src on N1, mid on N3, sink pinned on N6
    assert where(sim, "pipe", "mid") == "N3"
    incarnation, instance = sim.cores["N6"].incarnation, sink_instance(sim)
    before = stats(sim, "pipe", "sink")["count"]
    sim.lose_route("N4", "N6")  # the others still route to N6; N3 and N5 are its neighbours
    sim.lose_route("N6", "N4")
    sim.run_until(sim.now + 6.0)  # twelve liveness windows with no route between N4 and N6
    assert_nobody_held_failed_but(sim, set())
    assert sim.cores["N6"].incarnation == incarnation  # N6 never reset ...
    assert sink_instance(sim) == instance  # ... so its sink is the same instance
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["count"] > before + 500  # it kept receiving
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent
    sim.lose_route("N4", "N6", lost=False)  # babeld converges: nothing was disturbed
    sim.lose_route("N6", "N4", lost=False)
    sim.run_until(sim.now + 2.0)
    assert_nobody_held_failed_but(sim, set())
    assert not sim.cores["N4"].procedures  # no suspicion left open


def test_a_killed_relay_is_recovered_while_one_survivor_has_no_route_to_the_sink() -> None:
    """The netns mesh's flaky run, in virtual time: the relay that runs ``mid`` dies, and one
    survivor is left with no route to the sink's node for seconds."""
    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    assert victim == "N3"
    incarnation, instance = sim.cores["N6"].incarnation, sink_instance(sim)
    sim.lose_route("N4", "N6")
    sim.lose_route("N6", "N4")
    sim.kill(victim, convergence_s=0.3)
    sim.run_until(sim.now + 6.0)
    assert_nobody_held_failed_but(sim, {victim})  # the relay, and only it
    assert where(sim, "pipe", "mid") != victim
    (rec,) = recoveries(sim, "pipe")
    assert rec["ok"] and rec["lost"] == ["mid"], rec
    assert sim.cores["N6"].incarnation == incarnation and sink_instance(sim) == instance
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent  # nothing from the source lost, nothing twice


def first_declared(sim: Simulation, victim: str, t0: float) -> tuple[float, float]:
    """When the first and the last survivor held ``victim`` failed, after ``t0``."""
    at = [
        min(f["at"] for f in c.failures if f["node"] == victim) - t0
        for n, c in sim.cores.items()
        if n != victim
    ]
    return min(at), max(at)


def test_a_node_every_node_loses_is_still_declared_failed_about_as_fast() -> None:
    """Every survivor's routes drop the dead node (it runs mid, which can be re-placed) at
    once (no neighbour is left to time its silence): they ask each other, nobody hears it,
    and it is declared. Before confirmation every survivor declared it at 0.5 s
    (dead_after_s); now one round trip later."""
    sim = started(PIPE)
    t0 = sim.now
    assert where(sim, "pipe", "mid") == "N3"
    sim.kill("N3", convergence_s=0.0)
    sim.run_until(t0 + 3.0)
    assert_nobody_held_failed_but(sim, {"N3"})
    first, last = first_declared(sim, "N3", t0)
    dead_after, period = 0.5, 0.1
    assert dead_after <= first and last <= dead_after + period + 0.02, (first, last)
    assert all(not c.procedures or c.id == "N3" for c in sim.cores.values())


def test_a_silent_neighbour_is_declared_after_asking_a_few_not_everyone() -> None:
    """The routing view still lists the dead node as a neighbour (its routing daemon is heard)
    while it stopped beating: its watchers ask a few of its other neighbours (SWIM's k), who
    answer at once from their own clock, and declare it within a period of the window."""
    sim = started(PIPE)
    sim.trace = []
    t0 = sim.now
    sim.kill("N4", convergence_s=5.0)
    sim.run_until(t0 + 1.0)
    first, last = first_declared(sim, "N4", t0)
    assert 0.5 <= first <= 0.6 and last <= 0.75, (first, last)
    asked = [t for t in sim.trace if t[3] in ("Suspect", "Hears")]
    watchers = 2  # N1 and N5, each asks the other
    assert 0 < len(asked) <= 2 * 3 * watchers, asked


def test_a_partition_that_cuts_off_a_pinned_end_declares_nobody() -> None:
    """A clean cut leaves N6, which runs the sink pinned there, alone. Its neighbours no
    longer hear it, but re-placing what it runs would let nothing flow: nobody declares it,
    every node holds it unreachable, and N6 holds the others unreachable (it cannot run the
    app alone). (The watchers used to declare it, and it them: a reset on every heal.)"""
    from test_rejoin import cut

    sim = started(PIPE)
    t0 = sim.now
    cut(sim, [("N3", "N6"), ("N5", "N6")])  # N6 alone
    sim.run_until(t0 + 0.8)
    assert_nobody_held_failed_but(sim, set())
    for n, core in sim.cores.items():
        want = sorted(set(sim.cores) - {"N6"}) if n == "N6" else ["N6"]
        assert core.status(sim.now)["unreachable_nodes"] == want, n
    assert [r for r in sim.replies if isinstance(r[2], m.Refused)] == []


# -- one core, by hand: the suspicion's answers, its deadline, what ends it -------------------
FIGS = m.Figures(1.0, 0.0, 0.0, None, None, (1.0, 4.0, 2.0, 1.0), {"N1": 1, "N3": 1})


def suspecting(now: float = 1.0) -> tuple[NodeCore, list[Effect]]:
    """N1's neighbours are N2 and N4; N4 (whose last figures name N3 a neighbour of its) beat
    last at time 0 and then fell silent, its route kept."""
    core = NodeCore("N1")
    core.set_routes({"N2": ("N2", 1), "N3": ("N2", 2), "N4": ("N4", 1)}, -1.0)
    core.receive("N4", m.Heartbeat("N4", 0, figures=FIGS), 0.0)
    core.receive("N2", m.Heartbeat("N2", 0), now - 0.05)
    return core, core.on_timer(HeartbeatTick(), now)


def asked(effects: list[Effect]) -> dict[str, m.Suspect]:
    return {e.dst: e.said for e in effects if isinstance(e, Send) and isinstance(e.said, m.Suspect)}


def test_a_silent_node_is_asked_about_its_neighbours_not_declared() -> None:
    core, effects = suspecting()
    queries = asked(effects)
    assert sorted(queries) == ["N3"] and queries["N3"].node == "N4"  # N4's neighbour only
    assert core.failed == set() and core.status(1.0)["suspected_nodes"] == ["N4"]
    core.receive("N3", m.Hears("N4", queries["N3"].rid, True, 100), 1.02)  # heard at 0.92
    assert core.failed == set() and core.procedures == {}
    assert core.peer_state("N4") == "ALIVE"
    core.receive("N2", m.Heartbeat("N2", 0), 1.35)
    assert asked(core.on_timer(HeartbeatTick(), 1.4)) == {}  # its clock runs from 0.92,
    core.receive("N2", m.Heartbeat("N2", 0), 1.45)
    assert sorted(asked(core.on_timer(HeartbeatTick(), 1.5))) == ["N3"]  # not from the answer


def test_a_node_nobody_hears_is_declared_with_its_witness_and_the_news_rides_on_beats() -> None:
    core, effects = suspecting()
    (rid,) = {q.rid for q in asked(effects).values()}
    core.receive("N3", m.Hears("N4", rid, False), 1.02)
    assert core.failed == {"N4"} and core.failures[-1]["detector"] == "N1"
    assert core.procedures == {}
    beats = [e.said for e in core.on_timer(HeartbeatTick(), 1.1) if isinstance(e, Send)]
    assert beats and all(isinstance(b, m.Heartbeat) for b in beats)
    assert beats[0].news == [m.NodeDown("N4", "N1", 0, "N3")]  # piggybacked, not a message


def test_a_suspicion_nobody_answers_is_asked_again_until_the_routes_settle() -> None:
    """Nobody answering is no evidence while the routing view may still be converging: the
    asker's own route may be what broke (babeld forwards into a broken link for 1.3-2.1 s),
    so it asks again each window. Once the view has had ROUTES_SETTLE_S since the node was
    last heard, a node asked may have died too: the silence holds, and it is declared."""
    from mso.protocol.events import Deadline
    from mso.protocol.procedures.remap import ROUTES_SETTLE_S

    core, effects = suspecting()
    (rid,) = {q.rid for q in asked(effects).values()}
    assert core.procedures[rid].deadline == 1.0 + core.liveness.dead_after_s
    core.on_timer(Deadline(rid), 1.0 + core.liveness.dead_after_s)
    assert core.failed == set() and core.peer_state("N4") == "ALIVE"
    settled = core.liveness.dead_after_s + ROUTES_SETTLE_S  # N4 was last heard at 0
    t, rounds = 1.5, 0
    while not core.failed and t < 10.0:
        t = round(t + 0.1, 3)
        core.receive("N2", m.Heartbeat("N2", 0), t - 0.01)
        rounds += bool(asked(core.on_timer(HeartbeatTick(), t)))
        for pid, proc in list(core.procedures.items()):
            if proc.deadline is not None and proc.deadline <= t:
                core.on_timer(Deadline(pid), t)
        assert core.failed == set() or t >= settled, t
    assert core.failed == {"N4"} and core.procedures == {}
    assert t < settled + 2 * core.liveness.dead_after_s and rounds >= 2  # asked twice more


def test_a_suspicion_ends_when_the_node_is_heard_or_another_detector_is_corroborated() -> None:
    core, _ = suspecting()
    core.set_routes({"N2": ("N2", 1), "N3": ("N2", 2)}, 1.1)  # a withdrawal: only a hint
    assert core.procedures != {} and core.peer_state("N4") == "SUSPECT"
    core, _ = suspecting()
    core.receive("N4", m.ChainDelay("nothing", 0, 1.0), 1.1)  # N4 reaches us: it lives
    assert core.procedures == {} and core.peer_state("N4") == "ALIVE"
    core, _ = suspecting()
    core.receive("N3", m.NodeDown("N4", "N3", 0, "N5"), 1.1)  # another detector, a witness
    assert core.procedures == {} and core.failed == {"N4"}


def test_a_node_with_nobody_else_to_ask_declares_a_silent_neighbour_without_asking() -> None:
    """N2, N1's only neighbour, fell silent with its route kept (a crashed daemon on a live
    router): nobody else is there to ask."""
    core = NodeCore("N1")
    core.set_routes({"N2": ("N2", 1)}, -1.0)
    core.receive("N2", m.Heartbeat("N2", 0), -0.9)
    effects = core.on_timer(HeartbeatTick(), 1.0)
    assert asked(effects) == {} and core.failed == {"N2"}


def test_a_node_out_of_reach_that_runs_nothing_needed_is_not_asked_about() -> None:
    """N2's route is gone and no app needs what it runs: it is unreachable, not suspected."""
    core = NodeCore("N1")
    core.set_routes({"N2": ("N2", 1)}, -1.0)
    core.set_routes({}, 0.0)
    effects = core.on_timer(HeartbeatTick(), 1.0)
    assert asked(effects) == {} and core.failed == set()
    assert core.status(1.0)["unreachable_nodes"] == ["N2"]


def test_a_node_says_it_hears_a_node_only_when_it_heard_it_lately() -> None:
    """Lately: within half the window (a live node beats every period; a dead one was last
    heard about a window ago by all its watchers). (One it reaches but is not a neighbour of
    it asks: the test below.)"""
    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N4": ("N4", 1)}, 0.0)
    core.receive("N4", core.membership.beat(), 1.0)

    def answer(about: str, now: float) -> m.Hears:
        (e,) = [e for e in core.receive("N1", m.Suspect(about, 7), now) if isinstance(e, Send)]
        assert isinstance(e.said, m.Hears) and e.dst == "N1" and e.said.rid == 7
        return e.said

    assert answer("N4", 1.2) == m.Hears("N4", 7, True, 200)  # heard 0.2 s ago
    assert answer("N4", 1.4) == m.Hears("N4", 7, False, 400)  # its neighbour, not lately
    assert not answer("N9", 1.0).yes  # never heard of it, out of reach
    assert answer("N2", 1.0).yes  # itself: alive
    core.receive("N1", m.NodeDown("N4", "N1", 0, "N5"), 1.4)
    assert not answer("N4", 1.4).yes  # held failed


def test_a_node_reaching_none_of_the_suspects_neighbours_learns_it_lives_through_others() -> None:
    """N4 keeps routes only to N1 and N2: it watched N5, now out of its reach and silent to
    it. N4 runs nothing, and N5 nothing an app needs re-placed: N5 is only unreachable to N4,
    nobody is asked about it and nobody is declared. (N4 used to ask N5's neighbour it still
    reached, N2, which heard it.)"""
    sim = started(PIPE)
    incarnation = sim.cores["N6"].incarnation
    sim.trace = []
    for a, b in (("N4", "N6"), ("N4", "N3"), ("N4", "N5")):
        sim.lose_route(a, b)
        sim.lose_route(b, a)
    sim.run_until(sim.now + 4.0)
    assert_nobody_held_failed_but(sim, set())
    assert sim.cores["N6"].incarnation == incarnation
    pinged = {(dst, src) for _, dst, src, kind in sim.trace if kind == "Suspect"}
    assert not any(src == "N4" for _, src in pinged), pinged
    assert {src for _, src in pinged} <= {"N5", "N6", "N3"}  # those that lost routes
    assert "N5" in sim.cores["N4"].status(sim.now)["unreachable_nodes"]
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and sent - 5 <= got["count"] <= sent


def test_a_node_asked_about_one_it_reaches_but_does_not_hear_asks_it() -> None:
    from mso.protocol.events import Deadline

    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N3": ("N3", 1), "N6": ("N3", 2)}, 0.0)
    (ping,) = [e for e in core.receive("N1", m.Suspect("N6", 41), 1.0) if isinstance(e, Send)]
    assert ping.dst == "N6" and isinstance(ping.msg, m.Suspect) and ping.msg.node == "N6"
    assert [e for e in core.receive("N4", m.Suspect("N6", 42), 1.01) if isinstance(e, Send)] == []
    answer = m.Hears("N6", ping.msg.rid, True)
    (yes, yes4) = [e for e in core.receive("N6", answer, 1.02) if isinstance(e, Send)]
    assert (yes.dst, yes.msg) == ("N1", m.Hears("N6", 41, True, 0))
    assert (yes4.dst, yes4.msg) == ("N4", m.Hears("N6", 42, True, 0))
    assert core.procedures == {}
    (ping,) = [e for e in core.receive("N1", m.Suspect("N6", 43), 2.0) if isinstance(e, Send)]
    (no,) = [e for e in core.on_timer(Deadline(ping.msg.rid), 2.2) if isinstance(e, Send)]
    assert (no.dst, no.msg) == ("N1", m.Hears("N6", 43, False))
    assert core.procedures == {}


def _beat_holding_failed(sim: Simulation, sender: str, failed: list[str]) -> m.Heartbeat:
    """``sender``'s beat (it runs something) holding ``failed`` failed in their incarnations."""
    dead = {n: sim.cores[n].incarnation for n in failed}
    core = sim.cores[sender]
    return m.Heartbeat(sender, core.incarnation, dead, sender, 1)


def test_a_beat_from_a_node_that_held_most_of_us_failed_does_not_reset_the_larger_side() -> None:
    """N6 was cut off from everyone, held them all failed, and came back before N1 finished
    confirming it (others had): N1 holds N6 failed too, and the rank resets N6, not N1."""
    sim = started(PIPE)
    n1 = sim.cores["N1"]
    incarnation = n1.incarnation
    beat = _beat_holding_failed(sim, "N6", ["N1", "N2", "N3", "N4", "N5"])
    n1.receive("N6", beat, sim.now)
    assert n1.incarnation == incarnation and "pipe" in n1.apps  # N1 did not reset
    assert "N6" in n1.failed


def test_a_beat_from_a_node_that_alone_missed_us_still_resets_us() -> None:
    """N6 held only N1 failed (N1 stalled, say, and N6 declared it): N1 yields, as before."""
    sim = started(PIPE)
    n1 = sim.cores["N1"]
    incarnation = n1.incarnation
    n1.receive("N6", _beat_holding_failed(sim, "N6", ["N1"]), sim.now)
    assert n1.incarnation == incarnation + 1  # reset: a new incarnation
    assert "N6" not in n1.failed
