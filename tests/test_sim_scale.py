"""What keeps the simulator linear in N: a node's retransmit timer runs only while it has
something unacknowledged, and a link change reaches only the nodes whose routes it changes."""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Callable
from typing import Any

import pytest

from mso.model.appfile import with_planner
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore, Send
from mso.protocol import messages as m
from mso.protocol.events import Retransmit
from mso.protocol.procedures.membership.peers import Membership
from mso.scenario.generate import pipelines
from mso.sim.runner import Simulation


def _line(n: int) -> Network:
    ids = [f"N{i}" for i in range(1, n + 1)]
    return Network([NodeSpec(i) for i in ids], [LinkSpec(a, b) for a, b in itertools.pairwise(ids)])


def _armed(sim: Simulation) -> set[str]:
    return {node for (node, key) in sim._timers if isinstance(key, Retransmit)}


def test_the_retransmit_timer_runs_only_where_events_wait_for_an_ack() -> None:
    sim = Simulation(_line(8), manage=False)
    (src, doc), = pipelines(["N1", "N3"], 1, seed=0, rate=20.0)  # fmt: skip
    sim.request(src, m.DeployRequest(doc, "app.yaml"))
    sim.run_until(3.0)
    hosts = {sim.placement("N1", "app0")[v] for v in ("src", "p1", "p2", "sink")}
    assert hosts <= {"N1", "N2", "N3"}
    producers = {sim.placement("N1", "app0")[v] for v in ("src", "p1", "p2")}
    # the producers' timers come and go with their events in flight; nodes that only know
    # of the app (they were told of it at deployment) have none at all
    assert _armed(sim) <= producers
    assert not _armed(sim) & {"N4", "N5", "N6", "N7", "N8"}
    seen = set()
    for k in range(1, 40):
        sim.run_until(3.0 + k * 0.05)
        seen |= _armed(sim)
    assert seen & producers  # (while events were unacknowledged, they were armed)


def test_a_link_change_reaches_only_the_nodes_whose_routes_it_changes() -> None:
    sim = Simulation(_line(6), manage=False, wire=False)
    called: list[str] = []
    for n, core in sim.cores.items():
        original = core.change_routes

        def spy(delta, now=0.0, n=n, original=original):  # type: ignore[no-untyped-def]
            called.append(n)
            return original(delta, now)

        core.change_routes = spy  # type: ignore[method-assign]
    sim.network.add_link(LinkSpec("N5", "N6", delay_ms=3.0))  # attributes only: nothing
    sim.links_changed()
    assert called == []
    sim.network.add_link(LinkSpec("N4", "N6"))  # a shortcut at the end of the line
    sim.links_changed()
    assert sorted(called) == ["N1", "N2", "N3", "N4", "N6"]  # N5's routes stay as they were
    assert sim.cores["N1"].routes["N6"] == ("N2", 4)


def _grid_run(
    quiet: bool,
    monkeypatch: pytest.MonkeyPatch,
    cast: bool = True,
    each: Callable[[Simulation], None] | None = None,
    restart: bool = False,
) -> tuple[Simulation, int]:
    """A 4x4 grid, one app; its interior host killed at 3 s and revived at 6 s: with beats
    that carry no news taken by the quiet path (``quiet``) or weighed whole; a message to
    several nodes delivered as one broadcast (``cast``) or as sends of their own; ``each``
    looks at the simulation every 50 ms. With ``restart``, deployed at N13 (an origin that
    hosts none of it), and at 10 s the host of ``p2`` restarts its daemon at once (its
    instances go before anyone holds it failed; ``each`` looks every 0.5 ms for 0.1 s then);
    the run goes on to 14 s."""

    def run_until(t: float, step: float = 0.05) -> None:
        while each is not None and sim.now + step < t:
            sim.run_until(sim.now + step)
            each(sim)
        sim.run_until(t)

    monkeypatch.setattr(NodeCore, "quiet_beats", quiet)
    if not cast:

        def one_by_one(self: Simulation, node: str, sends: list[Send]) -> None:
            for eff in sends:
                if not self._send(node, eff.dst, eff.msg):
                    self.waiting[node].hold(eff.dst, (eff.dst, eff.msg), 0, self.now)

        monkeypatch.setattr(Simulation, "_cast", one_by_one)
    pushed: Counter[str] = Counter()
    original_push = Simulation._push

    def push(self: Simulation, at: float, kind: str, node: str, payload: Any) -> None:
        pushed[kind] += 1
        original_push(self, at, kind, node, payload)

    monkeypatch.setattr(Simulation, "_push", push)
    taken = [0]
    original = Membership.quiet_beat

    def counted(self: Membership, src: str, msg: m.Heartbeat, now: float) -> bool:
        ok = original(self, src, msg, now)
        taken[0] += ok
        return ok

    monkeypatch.setattr(Membership, "quiet_beat", counted)
    ids = [f"N{i}" for i in range(1, 17)]
    links = [LinkSpec(ids[i], ids[i + 1]) for i in range(16) if i % 4 != 3]
    links += [LinkSpec(ids[i], ids[i + 4]) for i in range(12)]
    sim = Simulation(Network([NodeSpec(i) for i in ids], links), manage=False)
    sim.trace = []
    (src, doc), = pipelines(["N1", "N16"], 1, seed=0, rate=20.0)  # fmt: skip
    # the paper's split puts p1 on an interior node, the victim (bytes: beside a pinned end)
    origin = "N13" if restart else src  # (with restart: an origin that hosts none of it)
    sim.request(origin, m.DeployRequest(with_planner(doc, "paper"), "app.yaml"))
    run_until(3.0)
    victim = sim.placement("N1", "app0")["p1"]
    assert victim not in ("N1", "N16")
    sim.kill(victim, convergence_s=0.2)
    run_until(6.0)
    for n in sim.network.nodes:  # its links back, then the daemon restarts
        if n != victim and ids.index(n) in _grid_neighbours(ids.index(victim)):
            sim.network.add_link(LinkSpec(victim, n))
    sim.revive(victim)
    run_until(10.0)
    if restart:
        host = sim.placement("N1", "app0")["p2"]
        assert host not in ("N1", "N16")
        sim.crash(host)
        sim.revive(host)
        run_until(10.1, step=0.0005)  # (its hello makes the holders restore it at once)
        run_until(14.0)
    sim.pushed = pushed  # type: ignore[attr-defined]
    return sim, taken[0]


def _grid_neighbours(i: int) -> set[int]:
    out = {i - 4, i + 4} | ({i - 1} if i % 4 else set()) | ({i + 1} if i % 4 != 3 else set())
    return {j for j in out if 0 <= j < 16}


def test_a_beat_with_no_news_taken_quietly_changes_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The quiet path for beats (Membership.quiet_beat) is an optimisation only: a run with
    a failure and a restart goes message for message as when every beat is weighed whole."""
    whole, none_taken = _grid_run(False, monkeypatch)
    quiet, taken = _grid_run(True, monkeypatch)
    # most beats carry no news (the rest follow the failure, or are hellos)
    assert none_taken == 0 and taken > quiet.census.by_type["Heartbeat"] // 2
    assert quiet.trace == whole.trace
    assert quiet.census.by_type == whole.census.by_type
    assert quiet.replies == whole.replies
    assert quiet.delivered == whole.delivered
    for n, core in quiet.cores.items():
        other = whole.cores[n]
        assert core.failed == other.failed
        assert core.placement("app0") == other.placement("app0")
        assert core.membership.liveness.last_heard == other.membership.liveness.last_heard
        assert core.membership.liveness.heard == other.membership.liveness.heard  # figures
        gaps, other_gaps = core.membership.liveness.gaps, other.membership.liveness.gaps
        assert {k: (g.count, g.recent) for k, g in gaps.items()} == {
            k: (g.count, g.recent) for k, g in other_gaps.items()
        }
        assert core.membership.heard_of() == other.membership.heard_of()  # hellos taken quietly
        assert core.failures == other.failures and core.rejoins == other.rejoins


def test_a_beat_to_every_neighbour_is_one_broadcast_that_changes_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A beat goes to every neighbour as one scheduled event (a radio's local broadcast),
    yet each copy is counted, measured and delivered in the order its own send would have
    had: the run with a failure and a restart goes message for message as with a send per
    neighbour."""
    apart, _ = _grid_run(True, monkeypatch, cast=False)
    cast, _ = _grid_run(True, monkeypatch, cast=True)
    assert cast.trace == apart.trace
    assert cast.census.by_type == apart.census.by_type
    assert cast.census.control == apart.census.control
    assert cast.bytes == apart.bytes
    assert cast.replies == apart.replies
    assert cast.delivered == apart.delivered
    for n, core in cast.cores.items():
        assert core.failed == apart.cores[n].failed
        assert core.membership.liveness.last_heard == apart.cores[n].membership.liveness.last_heard
    scheduled = apart.pushed["msg"]  # type: ignore[attr-defined]
    fewer = scheduled - cast.pushed["msg"] - cast.pushed["cast"]  # type: ignore[attr-defined]
    # the grid's 16 nodes have 2-4 neighbours: a beat is 1 event, not 2-4
    assert fewer > cast.census.by_type["Heartbeat"] // 2
    assert apart.pushed["cast"] == 0  # type: ignore[attr-defined]


def test_a_beat_reads_only_the_apps_engaged_here_and_misses_none(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A node may hold apps it runs no part of (the origin's, a replica's), but a beat counts
    instances and looks for vanished vertices (and a monitor period for chain delays to
    report) only in the apps engaged here (Apps.engaged): through a deployment, a failure,
    a daemon restart that leaves vertices vanished at the nodes that hold the app and their
    restore, that is every app with any, at every moment, on every node."""
    seen = {"hosting": 0, "vanished": 0}

    def check(sim: Simulation) -> None:
        for n, core in sim.cores.items():
            if n in sim.killed:
                continue
            apps = core.apps
            full = {
                a
                for a, dep in apps.items()
                if dep.instances or dep.vanished or dep.delays or n in dep.placed.values()
            }
            assert {dep.app.name for dep in apps.engaged_apps()} == full, (sim.now, n)
            hosting = sum(len(dep.instances) for dep in apps.values())
            assert core.membership._hosting() == hosting
            seen["hosting"] += hosting > 0
            seen["vanished"] += any(dep.vanished for dep in apps.values())

    _grid_run(True, monkeypatch, each=check, restart=True)
    # (both were there to be missed: the restart's vanished vertex, at the app's holders)
    assert seen["hosting"] and seen["vanished"], seen


def test_an_app_notes_itself_engaged_however_it_gains_an_instance_or_a_vertex_here() -> None:
    sim = Simulation(_line(2), manage=False)
    (_, doc), = pipelines(["N1", "N2"], 1, seed=0, rate=20.0)  # fmt: skip
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(1.0)
    apps = sim.cores[sim.placement("N1", "app0")["sink"]].apps
    dep = apps["app0"]
    held = dict(dep.instances)
    assert dep.delays  # (the sink ends the app's one chain here)
    dep.instances.clear()
    assert apps.engaged_apps() == [dep]  # its delays are still reported from here
    dep.delays.clear()
    placed = dict(dep.placed)
    dep.placed.update((v, "elsewhere") for v in placed)
    assert apps.engaged_apps() == [] and not apps.engaged
    grow: list[Callable[[], object]] = [
        lambda: dep.instances.__setitem__("x", next(iter(held.values()))),
        lambda: dep.instances.setdefault("x", next(iter(held.values()))),
        lambda: dep.instances.update(held),
        lambda: dep.instances.__ior__(held),
        lambda: dep.vanished.add("p1"),
        lambda: dep.vanished.update({"p1"}),
        lambda: dep.vanished.__ior__({"p1"}),
        lambda: dep.vanished.__ixor__({"p1"}),
        lambda: dep.vanished.replace({"p1"}),
        lambda: dep.placed.__setitem__("p1", apps.node),
        lambda: dep.placed.update(placed),
        lambda: dep.placed.__ior__({"sink": apps.node}),
    ]
    for way in grow:
        way()
        assert apps.engaged_apps() == [dep]
        dep.instances.clear()
        dep.vanished.clear()
        dep.placed.update((v, "elsewhere") for v in placed)
        assert apps.engaged_apps() == []
    dep.vanished.add("p1")  # a new record for the app (a sync) in place of the old one
    apps["app0"] = replaced = type(dep)(dep.app, dep.layout, dep.origin, {})
    assert apps.engaged_apps() == []
    replaced.vanished.add("p2")
    assert apps.engaged_apps() == [replaced]


def test_a_broadcast_copy_is_seen_and_lost_one_receiver_at_a_time() -> None:
    """A test's taps see every copy of a broadcast and ``drop`` loses one receiver's copy,
    not the others'."""
    sim = Simulation(_line(3), manage=False)
    seen: list[tuple[str, str]] = []
    sim.taps.append(lambda a, b, msg: seen.append((a, b)) if a == "N2" else None)
    sim.drop = lambda a, b, msg: a == "N2" and b == "N3"
    sim.run_until(0.35)
    assert seen.count(("N2", "N1")) == seen.count(("N2", "N3")) > 0
    n1 = sim.cores["N1"].membership.liveness.last_heard["N2"]
    assert n1 > 0.2
    assert sim.cores["N3"].membership.liveness.last_heard.get("N2", 0.0) < 0.1


def test_a_first_start_says_hello_to_neighbours_and_a_deployment_carries_incarnations() -> None:
    # N² hellos at t=0 were most of a 1,000-node start-up: a node in its first incarnation
    # tells only its neighbours; the nodes of an app learn each other's incarnations from
    # its start (StartApp), so a restart of a host far away is still known as one
    sim = Simulation(_line(8), manage=False)
    assert sim.census.by_type["Heartbeat"] == 2 * 7  # each way over each link (was 8 x 7)
    app = pipelines(["N1", "N7"], 1, seed=0, rate=20.0)[0][1]
    sim.request("N1", m.DeployRequest(app, "app.yaml"))
    sim.run_until(3.0)
    hosts = set(sim.placement("N1", "app0").values())
    assert {"N1", "N7"} <= hosts
    for n in hosts:
        known = sim.cores[n].membership
        assert all(known.incarnation_of(h, -1) == 0 for h in hosts - {n}), (n, hosts)
    ran = {v for v, n in sim.placement("N1", "app0").items() if n == "N7"}
    sim.crash("N7")  # its daemon alone: routes stay, the sink pinned to it is restored
    sim.run_until(3.2)
    sim.revive("N7")  # a new incarnation: N1 never had a beat from it, yet knows a restart
    sim.run_until(6.0)
    assert [j["node"] for j in sim.cores["N1"].membership.rejoins] == ["N7"]
    assert ran and ran <= set(sim.cores["N7"].instances("app0"))


def test_every_copy_counts_its_frame_at_its_encoded_size_at_every_hop() -> None:
    """A message to many is encoded once; each copy's frame size is worked out from its two
    names, not encoded again: every node's byte counters come out as if each copy had been
    encoded, with names of different lengths and routes of several hops, taps on or off."""
    ids = [f"N{i}" for i in range(1, 13)]  # names of 2 and 3 bytes

    def run(tapped: bool) -> tuple[Simulation, dict[str, list[int]]]:
        sim = Simulation(_line(12), manage=False)
        # what each node counted once started, and then each copy's frame encoded when sent
        want = {n: list(c) for n, c in sim.bytes.items()}
        hops = [0]

        def tap(a: str, b: str, msg: m.Message) -> None:
            size, route = len(m.wrap(a, b, msg)), sim.network.route(a, b)
            assert route is not None
            hops[0] = max(hops[0], len(route) - 1)
            for x in route[:-1]:
                want[x][0] += size
            for x in route[1:]:
                want[x][1] += size

        if tapped:
            sim.taps.append(tap)
        (src, doc), = pipelines([ids[0], ids[-1]], 1, seed=0, rate=20.0)  # fmt: skip
        sim.request(src, m.DeployRequest(doc, "app.yaml"))
        sim.run_until(2.0)
        assert hops[0] > 1 or not tapped  # (routes of several hops among them)
        return sim, want

    tapped, want = run(True)
    plain, _ = run(False)
    assert tapped.bytes == want
    assert plain.bytes == want


def _idle_footprint(n: int) -> tuple[int, int]:
    """The bytes an interior node of an N-node grid holds, apart from its routing table, 2
    simulated seconds after start (no apps): its degree and the bytes."""
    from mso.benchmarks.footprint import Walker, by_component
    from mso.scenario.format import loads_scenario
    from mso.scenario.generate import Spec, dumps, generate

    spec = Spec("grid", n, seed=1, degree=6)
    sim = Simulation(loads_scenario(dumps(generate(spec), spec), file="grid.yaml").network)
    sim.run_until(2.0)
    core = max(sim.cores.values(), key=lambda c: (len(c.membership.liveness.neighbours), c.id))
    walker = Walker([sim, sim.network, *sim.cores.values()])
    walker.size(core.routes)  # the routing view's own N entries: not counted
    return len(core.membership.liveness.neighbours), sum(by_component(walker, core).values())


def test_a_node_hosting_nothing_holds_no_table_of_every_node_besides_its_routes() -> None:
    """Issue 24: per-node memory independent of N beyond the node's apps. The monitor kept a
    copy of every route's next hop and liveness a set of every reachable node (about 77 bytes
    a node of the network at an interior node); they keep the core's table instead."""
    (deg_a, small), (deg_b, large) = _idle_footprint(25), _idle_footprint(100)
    assert deg_a == deg_b == 6
    assert (large - small) / (100 - 25) < 20, (small, large)


def test_route_values_are_shared_not_one_per_destination() -> None:
    core = NodeCore("N0")
    routes = {f"N{i}": (f"N{i % 3 + 1}", 1 + i // 100) for i in range(1, 1000)}
    core.set_routes({d: (h, k) for d, (h, k) in routes.items()}, 0.0)
    assert core.routes == routes
    assert len({id(r) for r in core.routes.values()}) <= 3 * 10
    core.change_routes({"N5": ("N2", 4), "N6": None}, 1.0)
    assert core.routes["N5"] == ("N2", 4) and "N6" not in core.routes
    assert len({id(r) for r in core.routes.values()}) <= 3 * 10 + 1


def test_a_node_that_takes_no_part_in_an_app_holds_none_of_it() -> None:
    """Only the nodes that take part in an app hold it (issue 24.1): its origin and its
    vertices' nodes (and replicas'); an app costs the others nothing (it cost each of them
    5.5 KB, paid N/20 times per node at scale, when every node held every app)."""
    from mso.scenario.format import loads_scenario
    from mso.scenario.generate import Spec, dumps, generate

    spec = Spec("grid", 25, seed=1, degree=6)
    sim = Simulation(loads_scenario(dumps(generate(spec), spec), file="grid.yaml").network)
    ((src, doc),) = pipelines(list(sim.cores), 1, seed=1)
    sim.request(src, m.DeployRequest(doc, "app.yaml"))
    sim.run_until(3.0)
    held = {x for x, core in sim.cores.items() if core.apps}
    (dep,) = sim.cores[src].apps.values()
    assert dep.running and held == {dep.origin, *dep.placed.values()}, held
    assert len(sim.cores) - len(held) >= 18
