"""Healed partitions and restarted nodes: a node declared failed comes back as a new
incarnation, the overlay restores what it hosted and unparks what was pinned to it, and no
vertex ends up running twice."""

from __future__ import annotations

from collections import Counter

from mso.model.network import LinkSpec
from mso.sim.runner import Simulation
from mso.statusview import status_text
from test_failure import BRANCH, MESH_LINKS, PIPE, started, stats


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
    sim = started(BRANCH)
    n5 = [(a, b) for a, b in MESH_LINKS if "N5" in (a, b)]
    cut(sim, n5)
    sim.run_until(sim.now + 3.0)
    for n, core in sim.cores.items():
        # N5 declares the neighbours it watched, and N1 (beyond them) which runs the source
        assert core.failed == ({"N5"} if n != "N5" else set(sim.network.nodes) - {"N5"}), n
    assert "j-c-s2" in sim.cores["N1"].status(sim.now)["apps"]["branch"]["parked"]
    s1_before = stats(sim, "branch", "s1")["count"]
    hosting = {n for n, c in sim.cores.items() if n != "N5" and c.instances("branch")}

    heal(sim, n5)
    sim.run_until(sim.now + 5.0)
    assert all(not core.failed for core in sim.cores.values())
    # N5 lost the tie-break (it counted everyone else failed) and rejoined as incarnation 1;
    # every node of the larger side kept its own, those that ran nothing too (they waited for
    # N5 to reset rather than yield to it), so nobody but N5 was ever declared failed
    assert sim.cores["N5"].incarnation == 1
    others = set(sim.cores) - {"N5"}
    assert hosting and {n: sim.cores[n].incarnation for n in others} == dict.fromkeys(others, 0)
    declared = {f["node"] for n in others for f in sim.cores[n].membership.failures}
    assert declared == {"N5"}
    for n, core in sim.cores.items():
        app = core.status(sim.now)["apps"]["branch"]
        assert app["parked"] == {} and app["placement"]["s2"] == "N5", (n, app)
    assert set(instances(sim, "branch").values()) == {1}  # every vertex runs exactly once
    # a fresh instance on N5: its first event skips what the parked chain dropped, then
    # every event follows the one before
    s2 = stats(sim, "branch", "s2")
    assert s2["count"] > 150 and s2["repeats"] == 0 and s2["out_of_order"] == 1, s2
    s1 = stats(sim, "branch", "s1")
    assert s1["count"] > s1_before + 200 and s1["repeats"] == 0, s1
    text = status_text({n: c.status(sim.now) for n, c in sim.cores.items()})
    (line,) = [ln for ln in text.splitlines() if ln.startswith("rejoined (restarted")]
    assert "N5 (1)" in line  # (nodes that ran nothing may have yielded too)
    assert "failed nodes" not in text and "parked" not in text


def test_a_healed_even_split_rejoins_the_side_with_the_higher_leader() -> None:
    sim = started(PIPE)  # src pinned to N1, sink to N6
    across = [("N3", "N6"), ("N1", "N4"), ("N2", "N5"), ("N3", "N5")]
    cut(sim, across)  # {N1, N2, N3} | {N4, N5, N6}
    sim.run_until(sim.now + 3.0)
    assert sim.cores["N1"].failed == {"N4", "N5", "N6"}
    assert sim.cores["N6"].failed == {"N1", "N2", "N3"}

    heal(sim, across)
    sim.run_until(sim.now + 6.0)
    assert all(not core.failed for core in sim.cores.values())
    # three failed nodes each side: the side led by N1 stays (N1 runs src), the other
    # resets and rejoins (N6 ran the sink); nodes that ran nothing may yield either way
    assert sim.cores["N1"].incarnation == 0 and sim.cores["N6"].incarnation == 1
    assert instances(sim, "pipe") == Counter({"src": 1, "mid": 1, "sink": 1})
    before = stats(sim, "pipe", "sink")["count"]
    sim.run_until(sim.now + 2.0)
    got = stats(sim, "pipe", "sink")
    assert got["count"] >= before + 150 and got["repeats"] == 0, got


def test_a_restarted_node_is_a_new_incarnation_and_gets_its_pinned_vertex_back() -> None:
    sim = started(BRANCH)
    links = [(a, b) for a, b in MESH_LINKS if "N5" in (a, b)]
    sim.kill("N5", convergence_s=0.3)
    sim.run_until(sim.now + 3.0)
    assert all(core.failed == {"N5"} for n, core in sim.cores.items() if n != "N5")
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
