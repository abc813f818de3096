"""Every table a member can make a node fill is bounded (issue 27, item 4): messages held for
apps not yet announced, and the failure maps that heartbeats carry. In the simulator, with a
captured member speaking as a neighbour (``core.receive`` in its name)."""

from __future__ import annotations

from mso.node.early import EARLY_S
from mso.protocol import messages as m
from mso.sim.runner import Simulation
from test_failure import mesh


def flood_early(sim: Simulation, node: str, src: str, n: int, size: int) -> None:
    """``n`` ChainPlaced of ``size`` bytes each, for apps nobody ever announces."""
    core = sim.cores[node]
    filler = {f"v{i}": "x" * 64 for i in range(size // 70)}
    for i in range(n):
        sim.apply(node, core.receive(src, m.ChainPlaced(f"ghost{i % 50}", i, filler), sim.now))


def test_early_messages_are_bounded_per_peer_in_bytes_and_time_and_go_with_their_peer() -> None:
    sim = Simulation(mesh())
    sim.run_until(1.0)
    core = sim.cores["N1"]
    lim = core.early.limits
    flood_early(sim, "N1", "N2", 2_000, 64 * 1024)  # 128 MiB offered by one member
    count, held = core.early.peer("N2")
    assert held <= lim.per_peer_bytes and count <= lim.per_peer
    assert count < 2_000 and core.early.bytes <= lim.total_bytes
    assert core.refusals["early_over_peer_bound"] == 2_000 - count
    flood_early(sim, "N1", "N4", 5_000, 100)  # many small ones: the count bound holds
    assert core.early.peer("N4")[0] == lim.per_peer
    # another peer's message still gets its share: one member cannot take all of it
    sim.apply("N1", core.receive("N5", m.ChainPlaced("real", 0, {"a": "N5"}), sim.now))
    assert core.early.peer("N5")[0] == 1
    assert len(core.early) <= lim.total
    # the flooding member is declared failed (its daemon dies, its router lives on: silent
    # with a route, not only out of reach): what it had held goes with it
    sim.crash("N2")
    sim.run_until(sim.now + 2.0)
    assert "N2" in core.failed
    assert core.early.peer("N2") == (0, 0)
    assert core.refusals["early_peer_failed"] == count
    # past the deadline, the rest expires (an announcement that late is not coming)
    sim.run_until(sim.now + EARLY_S + 2.0)
    assert len(core.early) == 0 and core.early.bytes == 0
    assert core.refusals["early_expired"] == lim.per_peer + 1
    assert core.status(sim.now)["refusals"]["early_expired"] == lim.per_peer + 1


def test_invented_failures_cannot_grow_the_failure_maps_or_the_heartbeats() -> None:
    """50,000 ``NodeDown``s about invented nodes, beats from 50,000 invented senders and a beat
    holding 50,000 nodes failed: no table of N1 grows past its bound, its beats stay small,
    and the overlay runs on with nobody held failed."""
    sim = Simulation(mesh())
    sim.run_until(1.0)
    core, mem = sim.cores["N1"], sim.cores["N1"].membership
    bound = mem.known_bound()
    assert bound < 50_000
    before = (len(mem._failed_incarnation), len(mem.peers), len(mem._incarnations))
    for i in range(50_000):
        sim.apply("N1", core.receive("N2", m.NodeDown(f"ghost{i}", "N2", 1), sim.now))
    assert core.refusals["node_down_unknown"] == 50_000
    assert (len(mem._failed_incarnation), len(mem.peers), len(mem._incarnations)) == before
    assert core.failed == set() and mem.beat().failed == {}
    for i in range(50_000):  # beats in invented names (a member can give any name)
        sim.apply("N1", core.receive(f"ghost{i}", m.Heartbeat(f"ghost{i}", 1), sim.now))
    assert len(mem._incarnations) <= bound and len(mem.liveness.last_heard) <= bound
    assert core.refusals["unknown_node_over_bound"] >= 50_000 - bound
    # a beat of a real neighbour holding 50,000 nodes failed is refused whole
    huge = {f"ghost{i}": 1 for i in range(50_000)}
    incarnations = dict(mem._incarnations)
    sim.apply("N1", core.receive("N2", m.Heartbeat("N2", 0, huge), sim.now))
    assert core.refusals["heartbeat_failed_map_over_bound"] == 1
    assert mem._incarnations == incarnations
    # a NodeDown now names one of the invented nodes N1 has heard of: its maps stay bounded
    for i in range(50_000):
        sim.apply("N1", core.receive("N2", m.NodeDown(f"ghost{i}", "N2", 1), sim.now))
    assert len(mem._failed_incarnation) <= bound and len(mem.beat().failed) <= bound
    assert len(core.failures) <= 50
    sim.run_until(sim.now + 2.0)
    for n, c in sim.cores.items():
        assert not (c.failed & set(sim.cores)), (n, c.failed)


def test_status_requests_share_one_fan_out_however_many_come() -> None:
    """20 clients asking for everyone's status 20 times a second while the others were slow
    kept 1,200 fan-outs in flight, each with this node's whole status (171 MB, never given
    back). Now one fan-out gathers at a time, the requests meanwhile join it (up to 256;
    past them a client gets this node's status alone) and each is answered once."""
    from mso.node.core import NodeCore
    from mso.protocol.effects import Reply, SetTimer
    from mso.protocol.procedures.status import MAX_WAITERS, StatusFanout

    core = NodeCore("N1")
    core.set_routes({"N2": ("N2", 1), "N3": ("N2", 2)}, 0.0)
    asks, timers, alone = [], [], []
    for client in range(1, 1001):
        effects = core.request(client, m.StatusRequest(everywhere=True), 0.001 * client)
        timers += [e for e in effects if isinstance(e, SetTimer)]
        alone += [e.client for e in effects if isinstance(e, Reply)]
        asks += [e for e in effects if not isinstance(e, Reply | SetTimer)]
    assert alone == list(range(MAX_WAITERS + 1, 1001))  # answered at once, with N1 alone
    fanouts = [p for p in core.procedures.values() if isinstance(p, StatusFanout)]
    assert len(fanouts) == 1 and len(fanouts[0].clients) == MAX_WAITERS
    assert len(asks) == 2  # N2 and N3 asked once, not a thousand times
    deadline = next(t for t in timers if t.key.pid == fanouts[0].pid)
    replies = [e for e in core.on_timer(deadline.key, deadline.at) if isinstance(e, Reply)]
    assert sorted(r.client for r in replies) == list(range(1, MAX_WAITERS + 1))
    assert not [p for p in core.procedures.values() if isinstance(p, StatusFanout)]
    core.request(2000, m.StatusRequest(everywhere=True), deadline.at)
    assert [p for p in core.procedures.values() if isinstance(p, StatusFanout)]  # a new one
