"""Fail-stop node failures in virtual time: detection by neighbours, one coordinator, remap of
the touched chains, replay from surviving upstreams, parking of chains with a dead pinned end."""

from __future__ import annotations

from typing import Any

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.procedures import placement
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

MESH_LINKS = [
    ("N1", "N2"),
    ("N2", "N3"),
    ("N3", "N6"),
    ("N1", "N4"),
    ("N4", "N5"),
    ("N5", "N6"),
    ("N2", "N5"),
    ("N3", "N5"),
]


def mesh() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 7)]
    return Network(nodes, [LinkSpec(a, b, delay_ms=1.0) for a, b in MESH_LINKS])


def started(doc: str, net: Network | None = None) -> Simulation:
    sim = Simulation(net or mesh())
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(1.0)
    (reply,) = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    assert reply.ok, reply.error
    sim.run_until(2.0)
    return sim


def where(sim: Simulation, app: str, vertex: str) -> str:
    (node,) = [
        n for n, c in sim.cores.items() if n not in sim.killed and vertex in c.instances(app)
    ]
    return node


def stats(sim: Simulation, app: str, vertex: str) -> dict[str, int]:
    core = sim.cores[where(sim, app, vertex)]
    out: dict[str, int] = core.status(sim.now)["apps"][app]["vertices"][vertex]["stats"]
    return out


def emitted(sim: Simulation, app: str, vertex: str) -> int:
    return sim.cores[where(sim, app, vertex)].instances(app)[vertex].emitted


def recoveries(sim: Simulation, app: str) -> list[dict[str, Any]]:
    return [
        r
        for n, c in sim.cores.items()
        if n not in sim.killed and app in c.apps
        for r in c.apps[app].recoveries
    ]


PIPE = pipe_app(100).replace("pinned: N4", "pinned: N6")


def test_interior_node_failure_is_detected_and_recovered_without_loss() -> None:
    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    assert victim not in ("N1", "N6")
    before = stats(sim, "pipe", "sink")["count"]
    sim.kill(victim, convergence_s=0.3)
    sim.run_until(sim.now + 5.0)
    survivors = [n for n in sim.cores if n != victim]
    for n in survivors:  # every survivor knows, whether it detected it or was told
        assert sim.cores[n].failed == {victim}
    detectors = {f["detector"] for n in survivors for f in sim.cores[n].failures}
    assert detectors <= set(sim.network.nodes) - {victim}
    assert where(sim, "pipe", "mid") != victim
    (rec,) = recoveries(sim, "pipe")  # one node coordinated, once
    assert rec["remap"] == "chain" and rec["lost"] == ["mid"] and rec["ok"], rec
    got = stats(sim, "pipe", "sink")
    sent = emitted(sim, "pipe", "src")
    assert got["count"] > before + 300  # it flows again
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent  # nothing from the surviving source was lost


# planner: paper: the scenario needs vertices on interior nodes (it kills them); the default bytes
# split keeps the 64-byte edges on the sources' node
BRANCH = """
name: branch
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, cost: 0.1,
        output: runtime_vertices:Num}
  a: {code: runtime_vertices:Double, output: runtime_vertices:Num, cost: 5}
  j: {code: runtime_vertices:Double, output: runtime_vertices:Num, cost: 20}
  b: {code: runtime_vertices:Double, output: runtime_vertices:Num, cost: 5}
  c: {code: runtime_vertices:Double, output: runtime_vertices:Num, cost: 5}
  s1: {code: runtime_vertices:Recorder, pinned: N6, cost: 0.1}
  s2: {code: runtime_vertices:Recorder, pinned: N5, cost: 0.1}
edges: [[src, a], [a, j], [j, b], [b, s1], [j, c], [c, s2]]
"""


def test_failure_of_a_chain_head_remaps_globally_without_loss() -> None:
    sim = started(BRANCH)
    victim = where(sim, "branch", "j")  # j ends src-a-j and heads j-b-s1 and j-c-s2
    assert victim not in ("N1", "N5", "N6"), victim
    sim.kill(victim, convergence_s=0.3)
    sim.run_until(sim.now + 6.0)
    (rec,) = recoveries(sim, "branch")
    assert rec["remap"] == "global" and rec["ok"], rec
    assert "j" in rec["lost"]
    sent = emitted(sim, "branch", "src")
    for sink in ("s1", "s2"):
        got = stats(sim, "branch", sink)
        assert got["repeats"] == 0 and got["out_of_order"] == 0, (sink, got)
        assert sent - 5 <= got["count"] <= sent, (sink, got, sent)


def test_two_nodes_failing_at_once() -> None:
    sim = started(BRANCH)
    victims = sorted({where(sim, "branch", "j"), where(sim, "branch", "a")} - {"N1", "N5", "N6"})
    others = sorted(set(sim.network.nodes) - {"N1", "N5", "N6", *victims})
    victims = [*victims, *others][:2]  # two interior nodes, at least one hosting a vertex
    hosting = {v for v in victims if sim.cores[v].instances("branch")}
    assert hosting
    for v in victims:
        sim.kill(v, convergence_s=0.3)
    sim.run_until(sim.now + 8.0)
    for n, core in sim.cores.items():
        if n not in victims:  # one that ran nothing is out of reach, not failed: nothing
            assert core.failed == hosting  # of the app needs it declared
            assert set(core.status(sim.now)["unreachable_nodes"]) == set(victims) - hosting
    assert all(r["ok"] for r in recoveries(sim, "branch"))
    sent = emitted(sim, "branch", "src")
    for sink in ("s1", "s2"):
        got = stats(sim, "branch", sink)
        assert got["repeats"] == 0 and got["out_of_order"] == 0, (sink, got)
        assert sent - 5 <= got["count"] <= sent, (sink, got, sent)


def test_a_dead_pinned_sink_parks_its_chain_and_the_rest_runs_on() -> None:
    sim = started(BRANCH)
    before = stats(sim, "branch", "s1")["count"]
    sim.kill("N5", convergence_s=0.3)  # s2 is pinned there
    sim.run_until(sim.now + 4.0)
    for n, core in sim.cores.items():
        if n != "N5":  # out of reach: nothing re-placed would let s2 have its events, so
            st = core.status(sim.now)  # N5 is not declared; its chain waits for it
            assert st["unreachable_nodes"] == ["N5"] and not core.failed
            if "branch" not in st["apps"]:  # (a node that takes no part holds none of it)
                continue
            parked = st["apps"]["branch"]["parked"]
            assert parked == {"j-c-s2": "'s2' is pinned to N5, out of reach"}, parked
    assert stats(sim, "branch", "s1")["count"] > before + 150  # the other branch flows on


def test_a_broken_link_is_not_a_failure() -> None:
    sim = started(PIPE)
    sim.network.remove_link("N1", "N2")
    sim.update_routes()
    sim.run_until(sim.now + 3.0)
    assert all(not core.failed for core in sim.cores.values())
    assert recoveries(sim, "pipe") == []


def test_a_silent_neighbour_is_declared_failed_within_the_deadline() -> None:
    sim = started(PIPE)
    sim.kill("N4", convergence_s=5.0)  # routing is slow: only the heartbeats can tell
    t0 = sim.now
    sim.run_until(t0 + 1.0)
    seen = [f for n, c in sim.cores.items() if n != "N4" for f in c.failures]
    assert seen and all(f["node"] == "N4" for f in seen)
    first = min(f["at"] for f in seen)
    assert 0.5 <= first - t0 <= 0.65  # dead_after_s, plus at most one heartbeat period


def test_status_shows_the_failure_the_recovery_and_parked_chains() -> None:

    from mso.statusview import status_text

    net = mesh()  # two more links, so that losing two nodes does not partition it
    net.add_link(LinkSpec("N1", "N3", delay_ms=1.0))
    net.add_link(LinkSpec("N4", "N6", delay_ms=1.0))
    sim = started(BRANCH, net)
    victim = where(sim, "branch", "j")
    assert victim != "N5"
    sim.kill(victim, convergence_s=0.3)
    sim.kill("N5", convergence_s=0.3)
    sim.run_until(sim.now + 6.0)
    nodes = {n: c.status(sim.now) for n, c in sim.cores.items() if n not in sim.killed}
    text = status_text(nodes)
    assert f"failed nodes: {', '.join(sorted([victim, 'N5']))}" in text
    assert "app branch: chain j-c-s2 parked: 's2' is pinned to failed node N5" in text
    assert "recovered from" in text and "remap of" in text
    assert "end-to-end delay" in text
    got, sent = stats(sim, "branch", "s1"), emitted(sim, "branch", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent, (got, sent)
    edges = [st["apps"]["branch"]["edges"] for st in nodes.values() if "branch" in st["apps"]]
    waiting = [e["j->c"]["waiting"] for e in edges if "j->c" in e]  # (c went with N5)
    assert sum(waiting) > 100, edges
    assert not any(
        st["apps"]["branch"]["given_up"] for st in nodes.values() if "branch" in st["apps"]
    )


def test_a_probe_waits_at_a_hop_whose_routes_still_go_through_the_failed_node() -> None:
    """Routes change a moment apart on different nodes: the recovery's probe must not be sent
    into the dead node by a hop that has not yet learnt the routes around it."""
    from mso.node.core import NodeCore, Send

    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N3": ("N3", 1), "N6": ("N3", 2), "N5": ("N5", 1)}, 1.0)
    core.receive("N1", m.NodeDown("N3", "N1", 0, "N5"), 1.1)  # N5 did not hear it either
    probe = m.Probe("app", -1, 7, "N1", "N6", ["N1"], [1.0])
    sent = [e for e in core.receive("N1", probe, 1.2) if isinstance(e, Send)]
    assert all(e.dst != "N3" for e in sent) and not any(isinstance(e.said, m.Probe) for e in sent)
    effects = core.set_routes({"N1": ("N1", 1), "N6": ("N5", 2), "N5": ("N5", 1)}, 1.3)
    (forwarded,) = [e for e in effects if isinstance(e, Send) and isinstance(e.said, m.Probe)]
    assert forwarded.dst == "N5" and forwarded.msg.nodes == ["N1", "N2"]


def test_a_recovery_that_could_not_complete_waits_for_the_pinned_end_in_reach() -> None:
    """The node hosting mid dies and, before it is declared failed, the sink's node is cut
    off (alive): re-placing mid could not let events flow, so nobody declares its node and
    no recovery starts (one once failed for want of a route to the sink and looped); the
    chain is parked, its sink out of reach. When the sink's node is in reach again, mid's
    node is declared, mid restored, and every event the source emitted arrives once."""
    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    sim.kill(victim, convergence_s=0.0)
    sim.run_until(sim.now + 0.3)
    links = [LinkSpec(n, "N6", delay_ms=1.0) for n in sim.network.neighbours("N6")]
    for link in links:
        sim.network.remove_link(link.a, link.b)  # cut off the sink's node, not dead
    sim.update_routes()
    sim.run_until(sim.now + 3.0)
    core = sim.cores["N1"]
    st = core.status(sim.now)
    assert core.failed == set() and st["unreachable_nodes"] == sorted([victim, "N6"])
    assert recoveries(sim, "pipe") == []
    assert st["apps"]["pipe"]["parked"] == {"src-mid-sink": "'sink' is pinned to N6, out of reach"}
    for link in links:
        sim.network.add_link(link)
    sim.update_routes()
    sim.run_until(sim.now + 3.0)
    assert core.failed == {victim} and core.status(sim.now)["apps"]["pipe"]["parked"] == {}
    (rec,) = recoveries(sim, "pipe")
    assert rec["ok"] and rec["lost"] == ["mid"] and where(sim, "pipe", "mid") != victim
    got = stats(sim, "pipe", "sink")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert got["count"] == got["next"] == emitted(sim, "pipe", "src"), got


def test_a_daemon_crashed_on_a_live_router_is_recovered_without_routes_around_it() -> None:
    """mid's node loses its daemon but its machine routes on (babeld keeps its routes, the
    kernel forwards), so no routing view ever goes around it. The recovery waits for routes
    to settle only ``ROUTES_SETTLE_S``, and probes skip the hop with no daemon; mid runs
    elsewhere and nothing from the source is lost or repeated."""
    from mso.protocol.procedures.remap import ROUTES_SETTLE_S

    sim = started(PIPE)
    victim = where(sim, "pipe", "mid")
    assert victim not in ("N1", "N6")
    sim.crash(victim)
    sim.run_until(sim.now + 1.0)
    survivors = [n for n in sim.cores if n != victim]
    assert all(victim in sim.cores[n].routes for n in survivors)  # routed to, for ever
    assert all(sim.cores[n].failed == {victim} for n in survivors)
    sim.run_until(sim.now + ROUTES_SETTLE_S + 3.0)
    assert where(sim, "pipe", "mid") != victim
    (rec,) = recoveries(sim, "pipe")
    assert rec["ok"] and rec["lost"] == ["mid"], rec
    got = stats(sim, "pipe", "sink")
    sent = emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent


def test_a_probe_held_for_routes_that_never_change_skips_the_failed_hop() -> None:
    """N3's daemon crashed but its router lives on: N2's route to N6 goes through N3 for
    ever. The held probe waits ``PROBE_HOLD_S`` for routes around it, then goes straight to
    its target (the transport gets it there through N3's router); N3, with no daemon, is
    not on its path of candidate hosts."""
    from mso.node.core import NodeCore, Send, SetTimer
    from mso.protocol.events import HeldProbesDue
    from mso.protocol.procedures.deploy import PROBE_HOLD_S

    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N3": ("N3", 1), "N6": ("N3", 2)}, 1.0)
    core.receive("N1", m.NodeDown("N3", "N1", 0, "N5"), 1.1)
    probe = m.Probe("app", -1, 7, "N1", "N6", ["N1"], [1.0])
    effects = core.receive("N1", probe, 1.2)
    assert not any(isinstance(e, Send) and isinstance(e.said, m.Probe) for e in effects)
    (timer,) = [e for e in effects if isinstance(e, SetTimer) and isinstance(e.key, HeldProbesDue)]
    assert timer.at == 1.2 + PROBE_HOLD_S
    effects = core.on_timer(timer.key, timer.at)
    (sent,) = [e for e in effects if isinstance(e, Send) and isinstance(e.said, m.Probe)]
    assert sent.dst == "N6" and sent.msg.nodes == ["N1", "N2"]


def test_a_consumer_drops_frames_from_an_instance_of_its_producer_a_restore_replaced() -> None:
    """A producer restored elsewhere while its node was cut off and held failed still runs
    there until that node resets; back in reach, its frames are numbered in its own run, and
    taken they put another event at a number the replacement sends next, then dropped as had
    (fault seed 162674: 1 event lost). Its consumer, told by the restore's rewire, drops them;
    a node it neither places the producer on nor holds replaced -- a move's old host sending
    its last frames before the switch -- is heard, and the node placed there again is too."""
    sim = started(PIPE)
    host, node = where(sim, "pipe", "mid"), where(sim, "pipe", "sink")
    core, dep = sim.cores[node], sim.cores[node].apps["pipe"]
    other = next(n for n in sorted(sim.cores) if n not in (host, node, "N1"))
    inc, version = dep.inc[1], dep.versions.get("mid", 0)  # (mid -> sink)
    placement.learn(dep, "mid", other, version + 1, sim.now)  # a move's word, its old host
    at = inc.expected  # sending on
    sim.run_until(sim.now + 0.5)
    assert inc.expected > at  # taken
    placement.learn(dep, "mid", host, version + 2, sim.now)
    sim.run_until(sim.now + 0.5)
    rewire = m.Rewire("pipe", 1, other, 1234, False)  # a restore's: mid runs there now
    sim.apply(node, core.receive("N1", rewire, sim.now))
    assert dep.placed["mid"] == other and dep.view.replaced("mid", host)
    at, dropped = inc.expected, core.dropped_messages
    sim.run_until(sim.now + 1.0)
    assert inc.expected == at and core.dropped_messages > dropped  # the old instance's
    placement.learn(dep, "mid", host, version + 3, sim.now)  # placed there again: heard
    assert not dep.view.replaced("mid", host) and dep.view.gone is None
    sim.run_until(sim.now + 3.0)  # (its window again, after a retransmission's wait)
    assert inc.expected > at
