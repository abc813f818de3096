"""Membership that is local, fast and honest: liveness from mso's own beats whatever the routing
view does, unreachable apart from failed, O(N) messages per failure, beats whose size does not
grow with N, and failure claims that need corroboration. Simulator, virtual clock."""

from __future__ import annotations

import sys
from itertools import pairwise
from pathlib import Path

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore
from mso.protocol import messages as m
from mso.protocol.events import HeartbeatTick
from runtime_vertices import pipe_app
from test_failure import PIPE, emitted, started, stats, where

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
import membership as bench


def test_a_dead_relay_whose_routes_are_withdrawn_is_declared_from_its_last_beat() -> None:
    """The routing view withdraws the dead node's routes 0.3 s after it died: the silence
    clock keeps running from its last beat (it once restarted at the withdrawal: 0.9 s)."""
    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    t0 = sim.now
    sim.kill(victim, convergence_s=0.3)
    sim.run_until(t0 + 2.0)
    first = min(
        f["at"]
        for n, c in sim.cores.items()
        if n != victim
        for f in c.failures
        if f["node"] == victim
    )
    assert 0.5 <= first - t0 <= 0.65, first - t0
    assert where(sim, "pipe", "mid") != victim


def test_a_live_node_whose_route_is_withdrawn_is_unreachable_then_alive_nothing_lost() -> None:
    """N1 (the source) loses its route to N6 (the sink) while both run and the others hear
    N6: N1 holds it unreachable, asks N6's neighbours, who hear it; on heal it is simply
    reachable again — no reset, the same sink instance, nothing lost or repeated."""
    sim = started(PIPE)
    n6 = sim.cores["N6"]
    incarnation, instance = n6.incarnation, n6.instances("pipe")["sink"].instance
    sim.lose_route("N1", "N6")
    sim.lose_route("N6", "N1")
    sim.run_until(sim.now + 2.0)
    st = sim.cores["N1"].status(sim.now)
    assert st["unreachable_nodes"] == ["N6"] and st["failed_nodes"] == []
    sim.lose_route("N1", "N6", lost=False)
    sim.lose_route("N6", "N1", lost=False)
    sim.run_until(sim.now + 2.0)
    assert all(not c.failed for c in sim.cores.values())
    assert sim.cores["N1"].status(sim.now)["unreachable_nodes"] == []
    assert n6.incarnation == incarnation
    assert n6.instances("pipe")["sink"].instance == instance
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0 and sent - 5 <= got["count"] <= sent


def test_control_messages_for_one_failure_grow_no_faster_than_the_nodes() -> None:
    """One interior node killed on a 5x5 and a 10x10 grid: the control messages from the kill
    to quiescence (not data, acks or beats) grow at most linearly (4x the nodes), no node
    handles more than O(N), and detection and recovery stay near the window."""
    small, large = bench.failure(5, 0.0), bench.failure(10, 0.0)
    assert small["control_messages"] > 0
    ratio = large["control_messages"] / small["control_messages"]
    assert ratio <= 4.0 * 1.25, (small, large)
    assert large["control_messages"] <= 10 * large["nodes"], large
    assert "Suspect" not in large["by_type"] or large["by_type"]["Suspect"] <= 3 * 8, large
    for r in (small, large):
        assert r["detection_s"] is not None and r["detection_s"] <= 0.65, r
        assert r["recovery_s"] is not None and r["lost"] == 0, r


def test_a_beats_size_does_not_grow_with_the_network() -> None:
    small, large = bench.failure(5, 0.0), bench.failure(10, 0.0)
    per_beat = [r["heartbeat_bytes_per_node_s"] for r in (small, large)]
    assert per_beat[1] <= per_beat[0] * 1.2, per_beat


def core_with_victim() -> NodeCore:
    """N1 reaches N2 (a neighbour) and N3 through it; it has heard N3's incarnation 5."""
    core = NodeCore("N1")
    core.set_routes({"N2": ("N2", 1), "N3": ("N2", 2)}, 0.0)
    core.receive("N3", m.Heartbeat("N3", 5), 0.5)
    core.receive("N2", m.Heartbeat("N2", 0), 0.9)
    return core


def test_a_claim_with_an_implausible_incarnation_does_not_fail_its_victim() -> None:
    core = core_with_victim()
    core.receive("N2", m.NodeDown("N3", "N2", 5 + 86_000_000, "N4"), 1.0)
    assert core.failed == set() and core.refusals["node_down_implausible_incarnation"] == 1


def test_an_uncorroborated_claim_waits_for_our_own_probe_and_a_live_victim_refutes_it() -> None:
    core = core_with_victim()
    out = core.receive("N2", m.NodeDown("N3", "N2", 5), 1.0)  # no witness, one detector
    assert core.failed == set()
    probes = [e for e in out if getattr(e, "dst", "") == "N3" and isinstance(e.said, m.Suspect)]
    assert probes, out  # we ask the victim itself
    core.receive("N3", m.Hears("N3", 0, True, 0), 1.05)  # it answers: it lives
    core.on_timer(HeartbeatTick(), 1.3)
    assert core.failed == set() and core.refusals["node_down_refuted"] == 1
    core.receive("N2", m.NodeDown("N3", "N2", 5), 2.0)  # unanswered, it is believed
    core.on_timer(HeartbeatTick(), 2.3)
    assert core.failed == {"N3"}


def test_two_detectors_corroborate_each_other() -> None:
    core = core_with_victim()
    core.receive("N2", m.NodeDown("N3", "N2", 5), 1.0)
    assert core.failed == set()
    core.receive("N4", m.NodeDown("N3", "N4", 5), 1.01)
    assert core.failed == {"N3"}


def test_a_node_that_hears_the_victim_refuses_the_claim() -> None:
    core = core_with_victim()
    core.receive("N3", m.Heartbeat("N3", 5), 1.0)
    core.receive("N2", m.NodeDown("N3", "N2", 5, "N4"), 1.05)
    assert core.failed == set() and core.refusals["node_down_heard"] == 1


def test_status_and_the_dashboard_show_an_unreachable_node_apart_from_the_failed() -> None:
    """N6 out of N1's reach (and N1 of N6's) while both run: `mso status` and the dashboard
    say unreachable, from whom, and never failed; once the routes are back, neither says it."""
    from mso.dashboard.view import Tracker
    from mso.statusview import status_text

    sim = started(PIPE)
    sim.lose_route("N1", "N6")
    sim.lose_route("N6", "N1")
    sim.run_until(sim.now + 2.0)
    nodes = {n: c.status(sim.now) for n, c in sim.cores.items()}
    text = status_text(nodes)
    assert "failed nodes" not in text
    (line,) = [ln for ln in text.splitlines() if ln.startswith("unreachable nodes")]
    assert line.endswith(": N1 (from N6), N6 (from N1)"), line
    view = Tracker(t0=0.0).update(nodes, 1.0)
    assert view["failed"] == [] and view["unreachable"] == ["N1", "N6"]
    assert [n["id"] for n in view["nodes"] if n["unreachable"]] == ["N1", "N6"]
    sim.lose_route("N1", "N6", lost=False)
    sim.lose_route("N6", "N1", lost=False)
    sim.run_until(sim.now + 1.0)
    text = status_text({n: c.status(sim.now) for n, c in sim.cores.items()})
    assert "unreachable" not in text and "failed nodes" not in text


def test_the_checker_catches_a_node_held_failed_while_it_is_heard() -> None:
    """The fault runs' invariant "no node held failed while it is heard": N1 made to hold N6
    failed, with N6's beats to N1 lost so that nothing corrects it, is caught once the two
    have reached each other for longer than the grace; a node out of reach is not."""
    from mso.protocol.procedures.membership.detector import PeerEvent
    from mso.sim.invariants import HEARD_GRACE_S, HeldFailed

    sim = started(PIPE)
    held = HeldFailed()
    sim.drop = lambda src, dst, msg: src == "N6" and dst == "N1"
    sim.cores["N1"].membership._move("N6", PeerEvent.CONFIRMED)  # a hand-broken table
    assert held.check(sim) == []
    sim.run_until(sim.now + HEARD_GRACE_S / 2)
    assert held.check(sim) == []
    sim.run_until(sim.now + HEARD_GRACE_S)
    (v,) = held.check(sim)
    assert v.invariant == "held-failed" and v.detail.startswith("N1 holds N6 failed"), v
    sim.lose_route("N1", "N6")  # out of reach: unreachable may be held failed (not heard)
    assert held.check(sim) == []


def test_a_rejoin_is_announced_to_the_apps_hosts_and_neighbours_not_to_every_node() -> None:
    """The end of a 10-node line restarts: its neighbour announces it to its own neighbours
    and the app's hosts, not to all ten (under mobility every node told every node was half of
    all membership traffic); the others learn from their rejoin rounds, and all hold it alive."""
    import itertools

    from mso.model.network import LinkSpec, Network, NodeSpec
    from mso.sim.runner import Simulation

    ids = [f"N{i}" for i in range(1, 11)]
    net = Network([NodeSpec(i) for i in ids], [LinkSpec(a, b) for a, b in itertools.pairwise(ids)])
    sim = Simulation(net)
    sim.run_until(1.0)
    sim.kill("N10", convergence_s=3.0)  # routes outlive it: silent with a route, declared
    sim.run_until(3.5)  # (withdrawn at once, it would be unreachable, not failed: no app
    assert all("N10" in sim.cores[n].failed for n in ids[:-1])  # needs what it ran)
    ups: list[tuple[str, str]] = []
    sim.taps.append(
        lambda src, dst, msg: (
            ups.append((src, dst)) if isinstance(m.carried(msg), m.NodeUp) else None
        )
    )
    sim.network.add_link(LinkSpec("N9", "N10"))
    sim.revive("N10")
    sim.update_routes()
    sim.run_until(sim.now + 3.0)
    assert all("N10" not in sim.cores[n].failed for n in ids[:-1])
    assert ups and len(ups) <= 2 * len(ids), ups  # was one per node per announcing node
    assert ("N9", "N1") not in ups  # not to the far end of the line


def test_a_vertex_fed_from_a_node_out_of_reach_is_not_moved_until_it_is_back() -> None:
    """A move waits for a marker from every producer: with the producer's node out of reach
    (held unreachable, not failed) it would wait past its commit for one that cannot come
    (fault seeds 5449, 8978: the producers that had switched placed the vertex where no
    instance ran). Refused, saying why; done once the route is back."""
    sim = started(PIPE)
    host = where(sim, "pipe", "mid")
    target = next(n for n in sorted(sim.cores) if n not in (host, "N1", "N6"))
    sim.lose_route(host, "N1")
    sim.request(host, m.RelocateRequest("pipe", "mid", target=target))
    sim.run_until(sim.now + 0.2)
    (refused,) = [r for _, _, r in sim.replies if isinstance(r, m.RelocateReply)]
    assert not refused.ok and "'mid' takes events from 'src' on N1, out of reach" in refused.error
    assert where(sim, "pipe", "mid") == host
    sim.lose_route(host, "N1", lost=False)
    sim.run_until(sim.now + 0.5)
    sim.request(host, m.RelocateRequest("pipe", "mid", target=target))
    sim.run_until(sim.now + 1.0)
    moved = [r for _, _, r in sim.replies if isinstance(r, m.RelocateReply)][-1]
    assert moved.ok, moved.error
    assert where(sim, "pipe", "mid") == target
    got, sent = stats(sim, "pipe", "sink"), emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0 and sent - 5 <= got["count"] <= sent


def test_a_restarts_control_messages_do_not_grow_with_the_network() -> None:
    """The app's interior node killed, recovered from, then back 3 s later on a 5x5 and a
    10x10 grid: its return is told to its neighbours and the app's nodes, not by every node
    that heard its hello (NodeUp to theirs, the app from each: 175 then 755 messages); every
    node takes it back all the same. Its vertex was recovered elsewhere meanwhile, so it
    takes no part in the app and is not given it (issue 24.1: only the nodes that take part
    hold an app)."""
    small, large = bench.restart(5), bench.restart(10)
    for r in (small, large):
        assert not r["synced"] and r["held_failed_after"] == 0, r
        assert r["taken_back_by"] == r["nodes"] - 1, r
        assert r["by_type"].get("NodeUp", 0) >= 1, r
    assert small["control_messages"] > 0
    assert large["control_messages"] <= 1.2 * small["control_messages"], (small, large)
    assert large["nodes_involved"] <= small["nodes_involved"] + 2, (small, large)


def test_a_restarted_node_whose_apps_have_no_other_host_is_sent_them() -> None:
    """Fault seed 866: on the line N1 - N2 - N3 the app runs on N1 alone; N2 and N1 crash,
    then come back. N1's only neighbour is N2, back empty too, and N3 hosts nothing: before,
    nobody sent N1 the app (a restart is synced by its neighbours and the app's hosts), and
    no node ran it again. Every node that holds an app with no other host left sends it."""
    from mso.sim.faults import Settings, run

    result = run(866, Settings(start_s=1, faults_s=3, quiet_s=4, rate=10, restarts=False))
    assert result.topology == "line" and result.faults["crash"] == 2
    assert not result.violations, "\n".join(map(str, result.violations))


SQUARE_LINKS = [("N1", "N2"), ("N2", "N4"), ("N1", "N3"), ("N3", "N4")]


def test_a_link_break_whose_routes_converge_after_the_window_declares_nobody() -> None:
    """The netns square N1-N2-N4 / N1-N3-N4 as babeld runs it: the link N1 routes to N4 by
    breaks, and for 1 s (babeld's re-route, hellos every 0.5 s) every node's routes still go
    over it, so whatever they send that way is lost -- N1's beats to that neighbour and its
    questions about it alike. Beats every 0.1 s, declared after 0.5 s: the silent neighbour
    is suspected, but a suspicion that nobody answers is no evidence (the asker's own routes
    are what failed); it waits for the routing view to settle, then the nodes hear each other
    over the other path. Before, both ends were declared failed by everyone, reset, and the
    source's node's reset repeated events at the sink."""
    net = Network(
        [NodeSpec(f"N{i}") for i in range(1, 5)],
        [LinkSpec(a, b, delay_ms=1.0) for a, b in SQUARE_LINKS],
    )
    sim = started(pipe_app(100), net)
    via = sim.cores["N1"].routes["N4"][0]
    assert via in ("N2", "N3")
    old = {(a, b): net.route(a, b) for a in net.nodes for b in net.nodes if a != b}
    incarnations = {n: c.incarnation for n, c in sim.cores.items()}
    hole_ends = sim.now + 1.0

    def over_the_broken_link(src: str, dst: str, msg: m.Message) -> bool:
        route = old.get((src, dst)) or []
        hops = set(pairwise(route))
        return sim.now < hole_ends and bool(hops & {("N1", via), (via, "N1")})

    sim.drop = over_the_broken_link
    sim.network.remove_link("N1", via)
    sim.links_changed(convergence_s=1.0)
    sim.run_until(sim.now + 4.0)
    sim.drop = None
    sim.run_until(sim.now + 2.0)
    assert all(not c.failures for c in sim.cores.values()), {
        n: c.failures for n, c in sim.cores.items()
    }
    assert {n: c.incarnation for n, c in sim.cores.items()} == incarnations
    assert sim.cores["N1"].routes["N4"][0] != via
    got = stats(sim, "pipe", "sink")
    assert got["repeats"] == 0, got
