"""Healed partitions and restarted nodes: a node declared failed comes back as a new
incarnation, the overlay restores what it hosted and unparks what was pinned to it, and no
vertex ends up running twice."""

from __future__ import annotations

from collections import Counter

from mso.model.network import LinkSpec
from mso.sim.runner import Simulation
from mso.statusview import status_text
from test_failure import BRANCH, MESH_LINKS, PIPE, emitted, started, stats, where


def cut(sim: Simulation, links: list[tuple[str, str]]) -> None:
    for a, b in links:
        sim.network.remove_link(a, b)
    sim.update_routes()


def heal(sim: Simulation, links: list[tuple[str, str]]) -> None:
    for a, b in links:
        sim.network.add_link(LinkSpec(a, b, delay_ms=1.0))
    sim.update_routes()


def instances(sim: Simulation, app: str) -> Counter[str]:
    """How many running instances each vertex has over every live node."""
    return Counter(
        v
        for n, c in sim.cores.items()
        if n not in sim.killed and app in c.apps
        for v in c.instances(app)
    )


def test_a_cut_off_sink_node_rejoins_and_its_parked_chain_runs_again() -> None:
    """N5, which runs the sink s2 (pinned there), is cut off for 3 s. Out of reach is not
    failed: re-placing what N5 runs would let nothing flow, so nobody is declared, nobody
    resets, the chain to s2 waits parked with its events kept (store and forward), and on the
    heal s2 gets every one of them, once and in order."""
    sim = started(BRANCH)
    n5 = [(a, b) for a, b in MESH_LINKS if "N5" in (a, b)]
    cut(sim, n5)
    sim.run_until(sim.now + 3.0)
    assert all(not core.failed for core in sim.cores.values())
    parked = sim.cores["N1"].status(sim.now)["apps"]["branch"]["parked"]
    assert "out of reach" in parked["j-c-s2"], parked
    s1_before = stats(sim, "branch", "s1")["count"]

    heal(sim, n5)
    sim.run_until(sim.now + 5.0)
    assert all(not core.failed and core.incarnation == 0 for core in sim.cores.values())
    assert not any(core.membership.failures for core in sim.cores.values())  # nobody declared
    for n, core in sim.cores.items():
        if "branch" not in core.apps:  # (a node that takes no part holds none of it)
            continue
        app = core.status(sim.now)["apps"]["branch"]
        assert app["parked"] == {} and app["placement"]["s2"] == "N5", (n, app)
    assert set(instances(sim, "branch").values()) == {1}  # every vertex runs exactly once
    # the same instance on N5: every event kept while it was away arrives, in order
    s2 = stats(sim, "branch", "s2")
    assert s2["count"] > 150 and s2["repeats"] == 0 and s2["out_of_order"] == 0, s2
    assert s2["next"] == s2["count"], s2  # none skipped: 0, 1, 2, ... with no gap
    s1 = stats(sim, "branch", "s1")
    assert s1["count"] > s1_before + 200 and s1["repeats"] == 0, s1
    text = status_text({n: c.status(sim.now) for n, c in sim.cores.items()})
    assert "rejoined" not in text and "failed nodes" not in text and "parked" not in text


def test_a_healed_even_split_where_neither_side_can_run_the_app_declares_nobody() -> None:
    """An even split {N1, N2, N3} | {N4, N5, N6} with src pinned to N1 and the sink to N6:
    neither side can run the app alone, so neither declares the other (out of reach is not
    failed), nobody resets, and on the heal the sink gets every event kept meanwhile. (Each
    side used to hold the other failed and the side with the higher leader stayed.)"""
    sim = started(PIPE)  # src pinned to N1, sink to N6
    across = [("N3", "N6"), ("N1", "N4"), ("N2", "N5"), ("N3", "N5")]
    cut(sim, across)  # {N1, N2, N3} | {N4, N5, N6}
    sim.run_until(sim.now + 3.0)
    assert all(not core.failed for core in sim.cores.values())

    heal(sim, across)
    sim.run_until(sim.now + 6.0)
    assert all(not core.failed and core.incarnation == 0 for core in sim.cores.values())
    assert instances(sim, "pipe") == Counter({"src": 1, "mid": 1, "sink": 1})
    before = stats(sim, "pipe", "sink")["count"]
    sim.run_until(sim.now + 2.0)
    got = stats(sim, "pipe", "sink")
    assert got["count"] >= before + 150 and got["repeats"] == 0, got
    assert got["out_of_order"] == 0 and got["next"] == got["count"], got  # none lost


def test_a_relay_cut_off_2_s_is_the_only_node_declared_and_is_taken_back_once() -> None:
    """bench/failure.py's partition case in virtual time (beats every 0.1 s, a 0.5 s window):
    N3, which runs mid, loses every link for 2 s. mid can run elsewhere, so its neighbours
    declare N3 and mid is restored; N3 itself holds the others out of reach, alive. On the heal
    N3 alone resets and is taken back, once, at every node. (The nodes that ran nothing and
    held no app read N3's beat, which held them alive, as a sign that they were the ones cut
    off, and reset: each taken for a restart, "declared", by every other node.)"""
    sim = started(PIPE)  # src on N1, mid on N3, sink pinned on N6
    assert where(sim, "pipe", "mid") == "N3"
    links = [(a, b) for a, b in MESH_LINKS if "N3" in (a, b)]
    cut(sim, links)
    sim.run_until(sim.now + 2.0)
    restored = [n for n, c in sim.cores.items() if n != "N3" and "mid" in c.instances("pipe")]
    assert len(restored) == 1  # restored on the larger side (N3's own runs on, out of reach)
    assert not sim.cores["N3"].failed  # out of reach is not failed: N3 declared nobody
    assert all(core.failed == {"N3"} for n, core in sim.cores.items() if n != "N3")

    heal(sim, links)
    sim.run_until(sim.now + 5.0)
    assert {n: c.incarnation for n, c in sim.cores.items()} == {
        n: int(n == "N3") for n in sim.cores
    }  # N3 reset once; nobody else did
    for n, core in sim.cores.items():
        assert not core.failed, (n, core.failed)
        assert {f["node"] for f in core.membership.failures} <= {"N3"}, (n, core.failures)
        if n != "N3":  # taken back exactly once, as its next incarnation
            assert [(r["node"], r["incarnation"]) for r in core.rejoins] == [("N3", 1)], n
    assert instances(sim, "pipe") == Counter({"src": 1, "mid": 1, "sink": 1})
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0, got
    assert sent - 5 <= got["count"] <= sent  # nothing lost across the cut and the heal


def test_a_restarted_node_is_a_new_incarnation_and_gets_its_pinned_vertex_back() -> None:
    sim = started(BRANCH)
    links = [(a, b) for a, b in MESH_LINKS if "N5" in (a, b)]
    sim.kill("N5", convergence_s=0.3)
    sim.run_until(sim.now + 3.0)
    # out of reach, not failed: s2's sink is pinned to N5, re-placing nothing would help
    assert all(not core.failed for n, core in sim.cores.items() if n != "N5")
    heal(sim, links)
    sim.revive("N5")  # a new process: incarnation 1, no apps
    sim.run_until(sim.now + 5.0)
    assert all(not core.failed for core in sim.cores.values())
    assert sim.cores["N5"].incarnation == 1
    assert set(instances(sim, "branch").values()) == {1}
    s2 = stats(sim, "branch", "s2")
    assert s2["count"] > 150 and s2["repeats"] == 0 and s2["out_of_order"] == 1, s2


def test_a_node_told_an_app_again_rearms_its_retransmission() -> None:
    """After a reset a node's old go-back-N timer for the app may have fired while it had no
    app; AppSync must arm it again, or lost frames from this node are never resent."""
    from mso.node.core import NodeCore, SetTimer
    from mso.protocol import messages as m
    from mso.protocol.events import Retransmit

    core = NodeCore("N6")
    placed = {"src": "N1", "mid": "N3", "sink": "N6"}
    effects = core.receive("N1", m.AppSync("pipe", "N1", PIPE, 0, placed, ["sink"]), 5.0)
    dep = core.apps["pipe"]
    assert dep.running and dep.placed == placed and dep.vanished == {"sink"}
    assert not dep.instances  # the sink is restored by the survivors' coordinator, not here
    timers = [e.key for e in effects if isinstance(e, SetTimer)]
    assert Retransmit("pipe") in timers


def test_a_vertex_a_sync_places_on_a_node_that_held_no_app_is_held_vanished_there() -> None:
    """A node reset (or restarted with nothing kept) learns the app from a sync whose sender
    had not heard of it: the vertex the sync places on this node runs nowhere (it went with
    the reset), so the node holds it vanished, for a recovery to restore (seed 122789: held
    running here, the node coordinated a restore of its consumer that waited on it for ever,
    and nobody restored it)."""
    from mso.node.core import NodeCore
    from mso.protocol import messages as m

    core = NodeCore("N3")
    placed = {"src": "N1", "mid": "N3", "sink": "N6"}
    core.receive("N1", m.AppSync("pipe", "N1", PIPE, 0, placed, ["sink"]), 5.0)
    dep = core.apps["pipe"]
    assert dep.placed == placed and not dep.instances
    assert dep.vanished == {"mid", "sink"}


def test_an_app_learnt_again_is_not_passed_on_again_to_a_node_told_it_once() -> None:
    """A node heard back empty lately is told an app this node learns from a sync (it may
    have held none when it heard it: sync.PASS_ON_S) -- once: an app let go and learnt again
    within that time went to it again, and it held the app past the quiet phase, taking no
    part (seed 136149)."""
    from mso.node.core import NodeCore
    from mso.protocol import messages as m
    from mso.protocol.effects import Send

    core = NodeCore("N6")
    core.membership._heard_empty("N5", 4.0)
    placed = {"src": "N1", "mid": "N5", "sink": "N7"}  # (N5 takes part by this view)

    def told(now: float) -> int:
        effects = core.receive("N7", m.AppSync("pipe", "N1", PIPE, 0, placed, []), now)
        return sum(isinstance(e, Send) and e.dst == "N5" for e in effects)

    assert told(4.1) == 1
    del core.apps["pipe"]  # let go (it took no part), then learnt again
    assert told(7.8) == 0


def test_after_a_reset_a_node_still_out_of_reach_is_failed_again_unless_a_route_appears() -> None:
    from mso.protocol.procedures.membership.liveness import Liveness

    live = Liveness(period_s=0.1, dead_after_s=0.5)
    live.set_routes(0.0, {"N2"}, {"N2"})
    live.heard_from("N2", 1.35)  # a neighbour that keeps talking
    live.rejoin("N3", 1.0, reachable=False, route=None)  # held failed, cleared by a reset
    live.rejoin("N4", 1.0, reachable=False, route=None)

    def suspects(now: float) -> list[str]:  # silent watched nodes (neighbours, or out of reach)
        return live.silent(now, set())

    assert suspects(1.4) == []
    live.set_routes(1.3, {"N2", "N4"}, {"N2"})  # N4 comes into reach in time (others watch it)
    assert suspects(1.6) == ["N3"]
    assert live.unreachable(set()) == ["N3"]  # out of reach, declared by nobody (yet)
