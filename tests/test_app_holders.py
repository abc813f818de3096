"""Issue 24.1: an app is held only by the nodes that take part in it -- its origin, its
vertices' nodes, its replicas' -- and any node can still answer for it."""

from __future__ import annotations

import pytest

from mso.model.appfile import with_planner
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.procedures.deploy import holders
from mso.protocol.procedures.lookup import SEARCH_BURST, SEARCH_RATE
from mso.scenario.format import loads_scenario
from mso.scenario.generate import Spec, dumps, generate, pipelines
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app


def _grid(n: int) -> Simulation:
    spec = Spec("grid", n, seed=1, degree=4)
    return Simulation(loads_scenario(dumps(generate(spec), spec), file="grid.yaml").network)


def _deployed(n: int) -> tuple[Simulation, str]:
    sim = _grid(n)
    nodes = sorted(sim.cores)
    (src, doc), = pipelines([nodes[0], nodes[n // 2]], 1, seed=0, rate=20.0)  # fmt: skip
    sim.request(src, m.DeployRequest(with_planner(doc, "paper"), "app.yaml"))
    sim.run_until(3.0)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    return sim, src


@pytest.mark.parametrize("n", [25, 100])
def test_a_node_that_takes_no_part_in_an_app_does_not_hold_it(n: int) -> None:
    sim, origin = _deployed(n)
    dep = sim.cores[origin].apps["app0"]
    taking_part = holders(dep)
    assert origin in taking_part and len(taking_part) < n // 4
    held = {x for x, core in sim.cores.items() if "app0" in core.apps}
    assert held == taking_part, (sorted(held - taking_part), sorted(taking_part - held))


def test_status_from_a_node_that_does_not_hold_the_app_still_reports_it() -> None:
    sim, origin = _deployed(25)
    outsider = max(x for x, core in sim.cores.items() if "app0" not in core.apps)
    sim.request(outsider, m.StatusRequest(req=7, everywhere=True), client=9)
    sim.run_until(sim.now + 2.0)
    (reply,) = [r for _, c, r in sim.replies if c == 9]
    assert isinstance(reply, m.StatusReply)
    assert "app0" not in reply.nodes[outsider]["apps"]
    told = {x for x, st in reply.nodes.items() if "app0" in st["apps"]}
    assert origin in told
    placed = reply.nodes[origin]["apps"]["app0"]["placement"]
    assert set(placed.values()) <= told


def test_a_vertex_whose_host_died_is_recovered_though_few_nodes_hold_the_app() -> None:
    sim, origin = _deployed(25)
    placed = dict(sim.cores[origin].apps["app0"].placed)
    pins = set(sim.cores[origin].apps["app0"].layout.pinned.values())
    victims = sorted({placed[v] for v in placed} - pins - {origin})
    assert victims, placed  # (the paper's split puts a vertex on an interior node)
    before = {x for x, core in sim.cores.items() if "app0" in core.apps}
    sim.kill(victims[0], convergence_s=0.2)
    sim.run_until(sim.now + 6.0)
    after = dict(sim.cores[origin].apps["app0"].placed)
    lost = [v for v, node in placed.items() if node == victims[0]]
    assert all(after[v] not in sim.killed for v in lost), after
    newcomers = {after[v] for v in lost} - before
    for node in {after[v] for v in lost}:
        assert "app0" in sim.cores[node].apps  # the new host was sent the app
        assert all(v in sim.cores[node].apps["app0"].instances for v in lost if after[v] == node)
    assert newcomers or {after[v] for v in lost} <= before


def test_a_restore_whose_app_sync_was_lost_sends_it_again_rather_than_fail() -> None:
    """A restore's target that holds none of the app is sent it (``AppSync``) ahead of the
    ``Prepare``; with that sync lost, the target answers it does not run the app, and the
    coordinator sends the app again with the same ``Prepare``: the restore goes on, and the
    recovery runs once (the restore failed, and the recovery ran a second time, before)."""
    sim, origin = _deployed(25)
    placed = dict(sim.cores[origin].apps["app0"].placed)
    pins = set(sim.cores[origin].apps["app0"].layout.pinned.values())
    victim = min({placed[v] for v in placed} - pins - {origin})
    lost: list[str] = []

    def drop(src: str, dst: str, msg: m.Message) -> bool:
        """The first sync of the app to each node that holds none of it."""
        if isinstance(msg, m.AppSync) and "app0" not in sim.cores[dst].apps and dst not in lost:
            lost.append(dst)
            return True
        return False

    sim.drop = drop
    sim.kill(victim, convergence_s=0.2)
    sim.run_until(sim.now + 6.0)
    after = dict(sim.cores[origin].apps["app0"].placed)
    assert lost and all(after[v] not in sim.killed for v in placed), (lost, after)
    records = [
        r
        for core in sim.cores.values()
        if "app0" in core.apps
        for r in core.status(sim.now)["apps"]["app0"]["recoveries"]
    ]
    assert len(records) == 1 and records[0]["ok"], records
    for v, node in after.items():
        assert v in sim.cores[node].apps["app0"].instances, (v, node)


def test_requests_at_a_node_that_holds_no_app_search_at_a_bounded_rate() -> None:
    """Each request for an app a node holds none of asks every node it reaches: a client
    naming a new app each time would have a node send N messages per request. A node starts
    at most SEARCH_BURST such searches, then SEARCH_RATE a second, whoever asks; the others
    are refused with why, and an honest request later goes through."""
    sim, _ = _deployed(25)
    outsider = max(x for x, core in sim.cores.items() if "app0" not in core.apps)
    asked = sim.census.by_type["PlacementQuery"]
    for k in range(40):  # apps nobody holds: every search asks all 24 others
        sim.request(outsider, m.RelocateRequest(f"nothing{k}", "p1", "upstream"), client=k + 10)
    sim.run_until(sim.now + 0.5)
    searches = (sim.census.by_type["PlacementQuery"] - asked) / (len(sim.cores) - 1)
    assert searches <= SEARCH_BURST + 0.5 * SEARCH_RATE + 1, searches
    refused = [r for _, c, r in sim.replies if c >= 10 and "at most" in getattr(r, "error", "")]
    assert len(refused) >= 40 - SEARCH_BURST - 2, [r for _, c, r in sim.replies if c >= 10]
    assert sim.cores[outsider].refusals["holder_search_over_rate"] == len(refused)
    sim.run_until(sim.now + SEARCH_BURST / SEARCH_RATE)  # the bucket fills again
    sim.request(outsider, m.RelocateRequest("app0", "p1", "upstream"), client=99)
    sim.run_until(sim.now + 2.0)
    (reply,) = [r for _, c, r in sim.replies if c == 99]
    assert isinstance(reply, m.RelocateReply) and "at most" not in reply.error, reply


def test_a_holder_looks_the_placement_up_again_when_a_restart_loses_more_of_it() -> None:
    """A holder that hosts nothing (the origin) looks the placement up before it coordinates
    a recovery, once per set of losses: a restart fails nobody, it only vanishes what its node
    ran, so keyed by the failed nodes alone the lookup made for one restart stood for the next
    ones too. Here mid moves after the holder's lookup for the sink's restart; the next
    restarts lose everything else in its view, and on that view it restored them beside the
    coordinator that knew (fault seed 117806: two instances of a vertex, 31 events lost).

    N1 - N2 - N3 - N4 and N5 on N2; ``pipe`` deployed from N5: src on N1, mid on N3, sink on
    N4."""
    net = Network(
        [NodeSpec(n) for n in ("N1", "N2", "N3", "N4", "N5")],
        [LinkSpec(a, b, delay_ms=1.0) for a, b in (("N1", "N2"), ("N2", "N3"), ("N3", "N4"))]
        + [LinkSpec("N5", "N2", delay_ms=1.0)],
    )
    sim = Simulation(net)
    sim.trace = []
    sim.request("N5", m.DeployRequest(pipe_app(20), "app.yaml"))
    sim.run_until(1.0)
    holder = sim.cores["N5"].apps["pipe"]
    assert holder.placed == {"src": "N1", "mid": "N3", "sink": "N4"}
    assert not holder.hosts_part()
    sim.crash("N4")  # the sink's daemon restarts: the holder looks the placement up
    sim.run_until(1.05)
    sim.revive("N4")
    sim.run_until(3.0)
    sim.request("N3", m.RelocateRequest("pipe", "mid", "", "N2"))  # the holder is not told
    sim.run_until(4.0)
    assert sim.hosts("pipe", "mid") == ["N2"] and holder.placed["mid"] == "N3"
    t0 = sim.now
    for node in ("N1", "N3", "N4"):  # every instance the holder's view names
        sim.crash(node)
    sim.run_until(t0 + 0.05)
    for node in ("N1", "N3", "N4"):
        sim.revive(node)
    sim.run_until(t0 + 4.0)
    coordinators = {src for at, _, src, kind in sim.trace if at > t0 and kind == "Prepare"}
    assert coordinators == {"N2"}  # mid's host, not the holder too
    assert holder.placed["mid"] == "N2"
    for v in ("src", "mid", "sink"):
        assert len(sim.hosts("pipe", v)) == 1, v
