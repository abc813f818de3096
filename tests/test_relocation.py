"""Intra-chain relocation (§3.4.1) under load: no event lost, repeated or reordered, and the
state of a stateful vertex moves with it."""

from __future__ import annotations

import pytest

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.net.forwarding import ROUTE_WAIT_S
from mso.protocol import messages as m
from mso.protocol.events import PeerFailed, PeerRejoined
from mso.protocol.procedures.relocation import Relocation
from mso.sim.runner import Simulation
from test_runtime_sim import data_frames, lose_first

# planner: paper: the scenario needs its vertices spread over N2 and N3 (they are moved from
# there); the default bytes split keeps these 64-byte edges on the sources' node
APP = """
name: pipe
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 500,
        output: runtime_vertices:Num}
  a: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  counter: {code: runtime_vertices:Counter, output: runtime_vertices:Num}
  b: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N4}
edges: [[src, a], [a, counter], [counter, b], [b, sink]]
"""


def line4() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 5)]
    return Network(nodes, [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1.0) for i in range(1, 4)])


def started() -> Simulation:
    sim = Simulation(line4())
    sim.request("N1", m.DeployRequest(APP, "pipe.yaml"))
    sim.run_until(1.0)
    assert isinstance(sim.replies[-1][2], m.DeployReply) and sim.replies[-1][2].ok
    return sim


def relocate(sim: Simulation, via: str, **kw: str) -> m.RelocateReply:
    n = len(sim.replies)
    sim.request(via, m.RelocateRequest("pipe", **kw))
    sim.run_until(sim.now + 0.2)
    (reply,) = [r for _, _, r in sim.replies[n:]]
    assert isinstance(reply, m.RelocateReply)
    return reply


def where(sim: Simulation, vertex: str) -> set[str]:
    return {n for n, c in sim.cores.items() if vertex in c.instances("pipe")}


def counts_on(sim: Simulation) -> None:
    """The sink gets over 400 events in the next second (the source's 500/s), none twice and
    none out of order."""
    before = sink_stats(sim)
    sim.run_until(sim.now + 1.0)
    after = sink_stats(sim)
    assert after["count"] > before["count"] + 400
    assert after["repeats"] == 0 and after["out_of_order"] == 0, after


def sink_stats(sim: Simulation) -> dict[str, int]:
    stats: dict[str, int] = sim.cores["N4"].status(sim.now)["apps"]["pipe"]["vertices"]["sink"][
        "stats"
    ]
    return stats


def test_upstream_and_downstream_moves_lose_nothing_and_keep_state() -> None:
    sim = started()
    start = where(sim, "counter")
    assert len(start) == 1
    moves = 0
    for k in range(8):
        direction = "downstream" if k % 2 == 0 else "upstream"
        via = f"N{1 + k % 4}"  # any node can ask
        reply = relocate(sim, via, vertex="counter", direction=direction)
        if not reply.ok:
            assert "already runs" in reply.error  # at an end of the line: refused, unchanged
            continue
        moves += 1
        assert where(sim, "counter") == {reply.node}
        # every node learned the new place
        assert all(c.placement("pipe")["counter"] == reply.node for c in sim.cores.values())
    assert moves >= 4
    # an upstream move never made the new instance drop events as a gap (no go-back-N stall)
    gaps = sum(ch.gaps for c in sim.cores.values() for ch in c.apps["pipe"].inc.values())
    assert gaps == 0
    sim.run_until(sim.now + 1.0)
    stats = sink_stats(sim)
    emitted = sim.cores["N1"].instances("pipe")["src"].emitted
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0
    assert emitted - 10 <= stats["count"] <= emitted
    counter_node = next(iter(where(sim, "counter")))
    state = sim.instance(counter_node, "pipe", "counter").count
    assert state == stats["next"] or state - stats["next"] <= 10  # state moved, never reset


@pytest.mark.parametrize(
    ("kw", "error"),
    [
        ({"vertex": "src", "direction": "downstream"}, "end of chain"),
        ({"vertex": "sink", "direction": "upstream"}, "end of chain"),
        ({"vertex": "nope", "direction": "upstream"}, "unknown vertex"),
        ({"vertex": "counter", "target": "N9"}, "not reachable"),
        ({"vertex": "counter", "direction": "sideways"}, "expected direction"),
    ],
)
def test_refusals_leave_the_overlay_as_it_was(kw: dict[str, str], error: str) -> None:
    sim = started()
    before = {n: dict(c.placement("pipe")) for n, c in sim.cores.items()}
    reply = relocate(sim, "N2", **kw)
    assert not reply.ok and error in reply.error
    assert {n: dict(c.placement("pipe")) for n, c in sim.cores.items()} == before


def test_a_move_asked_on_a_view_from_before_the_vertex_came_to_its_target_is_refused() -> None:
    """A node whose view places the counter where it ran before (it learnt the app from a
    node behind) asks to move it to the node that runs it now. Before, the target prepared,
    the move committed and waited for a handover from a node that ran no counter: open for
    the switch's 60 s, with the app held (fault seed 79022). Refused now, and the asker is
    told where the counter runs."""
    sim = started()
    (host,) = where(sim, "counter")
    dep = sim.cores["N1"].apps["pipe"]
    dep.placed["counter"] = next(n for n in ("N2", "N3") if n != host)
    reply = relocate(sim, "N1", vertex="counter", target=host)
    assert not reply.ok and f"runs on {host} already" in reply.error, reply
    assert not sim.cores["N1"].procedures and dep.placed["counter"] == host
    before = sink_stats(sim)["count"]
    sim.run_until(sim.now + 1.0)
    assert where(sim, "counter") == {host} and sink_stats(sim)["count"] > before + 400


# planner: paper: the moves below start from the paper's split (left and right apart)
FORK = """
name: pipe
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 500,
        output: runtime_vertices:Num}
  left: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  right: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  lsink: {code: runtime_vertices:Recorder, pinned: N4}
  rsink: {code: runtime_vertices:Recorder, pinned: N4}
edges: [[src, left], [left, lsink], [src, right], [right, rsink]]
"""


def test_moves_in_and_out_of_a_folded_fork_lose_nothing() -> None:
    """src's two consumers join on one node (their batches share a frame), part, and join
    again on another: each sink still gets every event once and in order."""
    sim = Simulation(line4())
    sent = data_frames(sim)

    def folded() -> int:
        return sum(1 for _, _, d in sent if d.also)

    sim.request("N1", m.DeployRequest(FORK, "pipe.yaml"))
    sim.run_until(1.0)
    assert isinstance(sim.replies[-1][2], m.DeployReply) and sim.replies[-1][2].ok
    seen, together = [], []
    moves = [("left", "N2"), ("right", "N3"), ("right", "N2"), ("left", "N3"), ("right", "N3")]
    for vertex, target in moves:
        if where(sim, vertex) != {target}:
            reply = relocate(sim, "N1", vertex=vertex, target=target)
            assert reply.ok, reply.error
        sim.run_until(sim.now + 0.2)
        before = folded()
        sim.run_until(sim.now + 0.2)
        seen.append(folded() > before)
        together.append(where(sim, "left") == where(sim, "right"))
    assert seen == together == [False, False, True, False, True]  # folded while together
    sim.run_until(sim.now + 1.0)
    emitted = sim.cores["N1"].instances("pipe")["src"].emitted
    for sink in ("lsink", "rsink"):
        stats = sim.cores["N4"].status(sim.now)["apps"]["pipe"]["vertices"][sink]["stats"]
        assert stats["repeats"] == 0 and stats["out_of_order"] == 0
        assert emitted - 10 <= stats["count"] <= emitted


SNAPSHOTTING = """
name: pipe
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 20,
        output: runtime_vertices:Num}
  counter: {code: runtime_vertices:Counter, cost: 40, snapshot_events: 5,
            output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N3}
edges: [[src, counter], [counter, sink]]
"""


@pytest.mark.parametrize("at", [2.0, 2.1, 2.2])
def test_a_move_whose_marker_waits_behind_a_replication_snapshot_finishes(
    at: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A replicated vertex's snapshot takes a while on a device (it waits for the call in
    progress); a marker that arrives meanwhile must be reached once the snapshot is in, though
    no event comes after it to move the instance's queue (its producers switched)."""
    from mso.protocol import effects as fx
    from mso.sim.executor import SimExecutor

    submit = SimExecutor.submit

    def slow_snapshots(self: SimExecutor, eff: fx.VertexEffect, now: float) -> None:
        if isinstance(eff, fx.SnapshotVertex) and eff.instance in self.workers:
            busy = self._busy_until.get(eff.instance, now)
            self._busy_until[eff.instance] = max(now, busy) + 0.25
        submit(self, eff, now)

    monkeypatch.setattr(SimExecutor, "submit", slow_snapshots)
    net = Network(
        [NodeSpec(f"N{i}") for i in range(1, 4)],
        [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1.0) for i in range(1, 3)],
    )
    sim = Simulation(net, model_time=True)
    sim.request("N1", m.DeployRequest(SNAPSHOTTING, "pipe.yaml"))
    sim.run_until(at)
    n = len(sim.replies)
    sim.request("N1", m.RelocateRequest("pipe", vertex="counter", direction="downstream"))
    sim.run_until(at + 5.0)  # the move takes about 1 s (its coordinator would wait 60)
    (reply,) = [r for _, _, r in sim.replies[n:]]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert where(sim, "counter") == {"N3"}
    sink = sim.cores["N3"].status(sim.now)["apps"]["pipe"]["vertices"]["sink"]
    moved = sink["stats"]["count"]
    sim.run_until(sim.now + 2.0)  # (the counter lags behind its source: 40 ms an event)
    stats = sim.cores["N3"].status(sim.now)["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0
    assert stats["count"] == stats["next"] > moved + 20  # nothing lost, and it flows on


def test_a_moved_vertex_never_shows_the_stats_of_its_empty_start() -> None:
    """Stats come with an instance's results, and the handover's restore returns none: the
    moved counter showed the count it started with (0) until its next event, in status read
    right after a move (test_isolation's loaded run did, 600 events in)."""
    sim = Simulation(line4())
    sim.request("N1", m.DeployRequest(APP.replace(":Counter,", ":PidCounter,"), "pipe.yaml"))
    sim.run_until(1.0)
    (home,) = where(sim, "counter")

    def shown() -> list[int]:
        out = []
        for n in where(sim, "counter"):
            st = sim.cores[n].status(sim.now)["apps"]["pipe"]["vertices"]["counter"]["stats"]
            if st is not None:
                out.append(st["count"])
        return out

    (before,) = shown()
    assert before > 100
    sim.request("N1", m.RelocateRequest("pipe", "counter", direction="downstream"))
    seen = []
    for _ in range(2000):  # the move, a tenth of a millisecond at a time
        sim.run_until(sim.now + 0.0001)
        seen += shown()
    assert where(sim, "counter") != {home}
    assert min(seen) >= before, seen


def test_a_move_whose_switch_was_lost_is_switched_again_and_finishes() -> None:
    """The move's target is prepared and the coordinator tells the producer to switch; that
    Switch is lost (its node went out of reach as the target answered). The coordinator
    sends it again a second on, and the move finishes; before, it waited for the producer's
    marker the switch's 60 s, its target holding the app (restart seed 100429). A Switch
    that comes twice is taken once: one marker, nothing lost or repeated."""
    sim = started()
    (host,) = where(sim, "counter")
    (producer,) = where(sim, "a")
    rel = sim.cores[producer].relocator
    lost: list[m.Switch] = []
    take = rel.on_switch

    def once_lost(src: str, msg: m.Switch) -> None:
        if not lost:
            lost.append(msg)
            return
        take(src, msg)
        take(src, msg)  # (and the same Switch again: dropped)

    rel.on_switch = once_lost  # type: ignore[method-assign]
    target = next(n for n in ("N2", "N3") if n != host)
    sim.request("N1", m.RelocateRequest("pipe", "counter", target=target))
    sim.run_until(sim.now + 0.5)
    assert lost and where(sim, "counter") == {host}  # committed, waiting for the marker
    sim.run_until(sim.now + 1.5)
    assert where(sim, "counter") == {target} and not sim.cores["N1"].procedures
    counts_on(sim)


def test_a_move_whose_marker_was_lost_is_marked_again_and_finishes() -> None:
    """The producer switches and its marker is lost on the way to the old host (markers go
    unsequenced, in order with the events: a route missing past its wait, a relay dying).
    The coordinator sends its Switch again a second on; the producer, switched already,
    sends the same marker again, and the move finishes. Before, the Switch sent again was
    dropped, and the move waited for the marker the switch's 60 s, its target holding the
    app (control loss seed 134). Nothing lost or repeated."""
    sim = started()
    (host,) = where(sim, "counter")
    (producer,) = where(sim, "a")
    assert producer != host  # (the marker goes over the network)
    lost: list[m.Message] = []
    sim.drop = lose_first(m.Marker, lost)
    target = next(n for n in ("N2", "N3") if n != host)
    sim.request("N1", m.RelocateRequest("pipe", "counter", target=target))
    sim.run_until(sim.now + 0.5)
    assert lost and where(sim, "counter") == {host} and sim.cores["N1"].procedures
    sim.run_until(sim.now + 1.5)
    assert where(sim, "counter") == {target} and not sim.cores["N1"].procedures


def test_a_restarted_target_refuses_the_switch_its_last_process_was_sent() -> None:
    """An upstream move of ``counter`` onto N2, which runs its producer ``a``: N2 is prepared
    and the coordinator's Switch is held on the way while N2 restarts. Its new process,
    which prepared nothing, is then sent the Switch (a control stream sends a frame again
    when a route appears, before its sender hears of the restart). It refuses it: the
    counter stays on N3, and ``a`` is restored on N2. Before, it marked the edge, N3 handed
    the counter over to no instance, and neither ran anywhere (fault seed 314611)."""
    sim = started()
    assert where(sim, "counter") == {"N3"} and where(sim, "a") == {"N2"}
    held: list[tuple[str, m.Message]] = []

    def hold(src: str, dst: str, msg: m.Message) -> bool:
        if isinstance(msg, m.Switch) and dst == "N2":
            held.append((src, msg))
            return True
        return False

    sim.drop = hold
    sim.request("N1", m.RelocateRequest("pipe", "counter", target="N2"))
    sim.run_until(sim.now + 0.05)
    assert held and "counter" in sim.cores["N2"].apps["pipe"].awaiting
    sim.drop = None
    sim.crash("N2")
    sim.run_until(sim.now + 0.05)
    sim.revive("N2")
    core = sim.cores["N2"]
    while "pipe" not in core.apps:  # (the app comes back with the rejoin's sync)
        sim.run_until(sim.now + 0.001)
    sim.apply("N2", core.receive(*held[0], sim.now))
    assert core.refusals.get("switch_to_no_prepared_instance") == 1
    sim.run_until(sim.now + 3.0)
    assert where(sim, "counter") == {"N3"} and where(sim, "a") == {"N2"}
    counts_on(sim)


def test_a_marker_given_up_in_a_cut_as_its_producer_switched_goes_again_after_it() -> None:
    """The vertex moves onto its producer's node, and the producer loses its route to the old
    host as it switches, for longer than the route wait: the marker is given up (a marker
    rides no control stream). The coordinator's Switch that comes again once the route is
    back sends it again, and the move finishes, nothing lost or repeated. Before, the
    producer dropped that Switch as taken: the old host ran the vertex waiting for a marker,
    the producer placed it on itself, the sink stalled (restart seed 310539)."""
    sim = started()
    (host,) = where(sim, "counter")
    (producer,) = where(sim, "a")
    assert producer != host
    rel = sim.cores[producer].relocator
    take = rel.on_switch
    cut: list[float] = []

    def cut_as_it_switches(src: str, msg: m.Switch) -> None:
        if not cut:
            cut.append(sim.now)
            sim.lose_route(producer, host)
        take(src, msg)

    rel.on_switch = cut_as_it_switches  # type: ignore[method-assign]
    sim.request("N1", m.RelocateRequest("pipe", "counter", target=producer))
    sim.run_until(sim.now + ROUTE_WAIT_S + 0.5)
    assert cut and where(sim, "counter") == {host} and sim.cores["N1"].procedures
    sim.lose_route(producer, host, lost=False)
    sim.run_until(sim.now + 1.5)
    assert where(sim, "counter") == {producer} and not sim.cores["N1"].procedures
    counts_on(sim)


def test_a_move_failed_with_its_target_held_failed_unprepares_it_when_it_answers() -> None:
    """The coordinator sees the move's target restart (held failed for a moment) before its
    Prepare is taken: the move fails, with no Unprepare (the target is held failed). The
    Prepare reaches the target's new process after all, which prepares the vertex: its
    Prepared gets an Unprepare now. Before, it held the instance, and the app, for the
    switch's 60 s (restart seed 100772)."""
    sim = started()
    (host,) = where(sim, "counter")
    target = next(n for n in ("N2", "N3") if n != host)
    rel = sim.cores[target].relocator
    held: list[tuple[str, m.Prepare]] = []
    take = rel.on_prepare
    rel.on_prepare = lambda src, msg: held.append((src, msg))  # type: ignore[method-assign]
    sim.request("N1", m.RelocateRequest("pipe", "counter", target=target))
    sim.run_until(sim.now + 0.05)
    assert held and sim.cores["N1"].procedures
    coordinator = sim.cores["N1"]
    coordinator.failed.add(target)  # (its restart seen: the move needs it)
    coordinator.relocator.on_peer_failed(PeerFailed(target))
    coordinator.failed.discard(target)  # (and taken back at once, as a rejoin does)
    assert not coordinator.procedures
    rel.on_prepare = take  # type: ignore[method-assign]
    sim.apply(target, sim.cores[target].receive(*held[0], sim.now))
    sim.run_until(sim.now + 0.5)
    assert "counter" not in sim.cores[target].apps["pipe"].awaiting
    assert where(sim, "counter") == {host}


def test_a_moves_target_restores_the_vertex_when_its_coordinator_and_old_host_go_together() -> None:
    """The vertex's host coordinates its move and restarts after the Switch, before the
    handover: the producer (on the target) placed the vertex on the target, so nobody holds it
    lost, and nobody is left to make the move a restore. The target hears the old host back in
    a new incarnation and restores the vertex in place from the producer's replay (its state,
    unreplicated, went with N3: the sink sees counts again). Before, it
    held the instance prepared, awaiting a handover for the switch's 60 s, and nothing ran the
    vertex (fault seed 230857)."""
    sim = started()
    assert where(sim, "counter") == {"N3"} and where(sim, "a") == {"N2"}
    sim.drop = lambda src, dst, msg: isinstance(msg, (m.Handover, m.HandoverEvents))
    sim.request("N3", m.RelocateRequest("pipe", "counter", target="N2"))
    sim.run_until(sim.now + 0.05)
    target = sim.cores["N2"].apps["pipe"]
    assert "counter" in target.awaiting and target.placed["counter"] == "N2"  # switched
    old_host_restarts_and_the_counter_runs_on(sim, "N2")


def old_host_restarts_and_the_counter_runs_on(sim: Simulation, target: str) -> None:
    """N3, the move's coordinator and old host, restarts before the handover: the counter
    runs on ``target`` after, and counts on (its state went with N3)."""
    sim.drop = None
    sim.crash("N3")
    sim.run_until(sim.now + 0.05)
    sim.revive("N3")
    sim.run_until(sim.now + 3.0)
    assert where(sim, "counter") == {target}
    before = sink_stats(sim)
    sim.run_until(sim.now + 1.0)
    after = sink_stats(sim)
    assert after["count"] > before["count"] + 400  # (the counter's state went with N3)


def test_a_moves_target_that_missed_the_switch_restores_the_vertex_when_its_old_host_goes() -> None:
    """As above, but the target is no producer of the vertex and the old host's ``Moved``
    never reached it (cut off as the move switched): its own view still places the vertex on
    the old host, the others' on the target. When the old host, the move's coordinator,
    comes back in a new incarnation, the target restores the vertex in place all the same.
    Before, it awaited the handover, nobody else held the vertex lost, and nothing ran it
    (fault seed 285674: each of two nodes held the other the recovery's coordinator)."""
    sim = started()
    assert where(sim, "counter") == {"N3"} and where(sim, "sink") == {"N4"}

    def drop(src: str, dst: str, msg: m.Message) -> bool:
        to_target = dst == "N4" and isinstance(msg, m.Moved) and msg.vertex == "counter"
        return to_target or isinstance(msg, (m.Handover, m.HandoverEvents))

    sim.drop = drop
    sim.request("N3", m.RelocateRequest("pipe", "counter", target="N4"))
    sim.run_until(sim.now + 0.05)
    target = sim.cores["N4"].apps["pipe"]
    assert "counter" in target.awaiting and target.placed["counter"] == "N3"  # not told
    assert sim.cores["N2"].apps["pipe"].placed["counter"] == "N4"  # switched
    old_host_restarts_and_the_counter_runs_on(sim, "N4")


def restored_in_place_with_rewires_lost() -> Simulation:
    """N3, which runs ``counter``, restarts and N1 restores it in place; N1's rewires are lost,
    so the replacement waits for its producer."""
    sim = started()
    assert where(sim, "counter") == {"N3"}
    sim.drop = lambda src, dst, msg: src == "N1" and isinstance(msg, m.Rewire)
    sim.crash("N3")
    sim.run_until(sim.now + 0.05)
    sim.revive("N3")
    sim.run_until(sim.now + 0.3)
    return sim


def test_a_restores_target_takes_it_over_when_its_coordinator_is_heard_back_restarted() -> None:
    """N3 restarts and N1 restores its ``counter`` in place; the restore's rewires are lost,
    so the replacement waits for its producer. N1 then goes, and N3 hears of its next
    process only from a ``NodeUp`` (no detector here ever holds N1 failed): the restore went
    with N1's last process, and N3 coordinates it from here on, as when a restore's
    coordinator fails. Before, it awaited the surviving ends for good, holding the app while
    taking no part in it (fault seed 264860: N1 reset at a heal; the others ran a twin of the
    vertex at a later move, so nobody restored it again). A rejoin after a healed cut (no
    restart) leaves the restore to its coordinator."""
    sim = restored_in_place_with_rewires_lost()
    core = sim.cores["N3"]
    dep = core.apps["pipe"]
    assert "counter" in dep.awaiting and dep.restoring["counter"].coordinator == "N1"
    core.restorer.on_peer_rejoined(PeerRejoined("N1"))  # (a cut healed: it ran on)
    assert dep.restoring["counter"].coordinator == "N1"
    sim.drop = None
    for c in sim.cores.values():
        c.liveness.dead_after_s = 1e9  # nobody holds N1 failed
    sim.crash("N1")
    sim.apply("N3", core.receive("N2", m.NodeUp("N1", 1), sim.now))
    sim.run_until(sim.now + 2.0)
    assert "counter" not in dep.awaiting and where(sim, "counter") == {"N3"}


def test_a_restore_ends_on_a_later_move_of_its_vertex_held_lost_only_as_it_began() -> None:
    """N3 restarts and N1 restores its ``counter`` there; the restore's rewires are lost, so
    the replacement waits for its producer. A relayed word then places the counter on N2 at a
    later move: N1's view keeps it vanished (a relayed word says where, not that it survived),
    as it was when the restore began. The restore was asked on a view from before that move
    (its ends may have moved with it), so at its next retry it ends, drops the replacement, and
    the recovery rule looks at the vertex on the view it has now. Before, it asked the same
    ends again until its last attempt, 6 s, holding the app (fault seed 274022: N2 coordinated
    the restore of ``j`` on itself, whose coordinator had reset; ``j`` ran on N7, restored at
    move 1 across a cut, its producer and consumer moved with it, and N2's rewires went to
    their old node, which said nothing)."""
    sim = restored_in_place_with_rewires_lost()
    core, target = sim.cores["N1"], sim.cores["N3"].apps["pipe"]
    (reloc,) = [p for p in core.procedures.values() if isinstance(p, Relocation) and p.restore]
    assert reloc.target == "N3" and "counter" in target.awaiting
    dep = core.apps["pipe"]
    assert "counter" in dep.vanished and dep.versions.get("counter", 0) == 0
    sim.apply("N1", core.receive("N4", m.Moved("pipe", "counter", "N2", -1, 1), sim.now))
    assert dep.placed["counter"] == "N2" and "counter" in dep.vanished
    sim.run_until(sim.now + 1.0)
    assert reloc.pid not in core.procedures and reloc.done
    assert target.restoring.get("counter") is None or target.restoring["counter"].rid != reloc.pid
    sim.drop = None
    sim.run_until(sim.now + 3.0)
    (host,) = where(sim, "counter")
    before = sink_stats(sim)
    sim.run_until(sim.now + 1.0)
    assert sink_stats(sim)["count"] > before["count"] + 400
    assert {c.apps["pipe"].placed["counter"] for c in sim.cores.values()} == {host}


def test_a_rewire_to_a_node_its_end_left_is_told_where_that_end_runs() -> None:
    """N4 restarts and N1 restores its ``sink`` in place; before the restore rewires ``b``, N3
    moves ``b`` to N2 and N1 is not told (as a coordinator that hosts no part of the app, not
    a member, is not). N1's rewire for ``b`` goes to N3, which runs it no more: refused, and
    N3 tells N1 where its view places ``b``; the restore's retry rewires N2 and the sink runs
    on. Before, N3 said nothing and N1 asked it every second, the sink running nowhere (fault
    seed 306377: ``b`` moved off N3 just before N1's restore of its consumer ``k1`` there)."""
    sim = started()
    untold: set[str] = set()  # who sent N1 the move's news (lost, and every copy sent again)

    def lose(src: str, dst: str, msg: m.Message) -> bool:
        if dst == "N1" and isinstance(msg, m.Moved) and msg.vertex == "b":
            untold.add(src)
            return True
        return src == "N1" and isinstance(msg, m.Prepare)  # (the restore waits for the move)

    sim.drop = lose
    sim.crash("N4")
    sim.run_until(sim.now + 0.05)
    sim.revive("N4")
    sim.run_until(sim.now + 0.3)
    core = sim.cores["N1"]
    (reloc,) = [p for p in core.procedures.values() if isinstance(p, Relocation) and p.restore]
    assert (reloc.vertex, reloc.target) == ("sink", "N4") and where(sim, "sink") == set()
    assert relocate(sim, "N3", vertex="b", target="N2").ok
    dep = core.apps["pipe"]
    assert dep.placed["b"] == "N3" and where(sim, "b") == {"N2"}  # N1 was not told
    for node in untold:  # their streams give the news up (as past KEEP_S): N1 never hears it
        sim.cores[node].streams.forget("N1")
    sim.drop = None
    sim.run_until(sim.now + 1.0)  # (the restore's retry: its rewire refused, N1 told)
    assert dep.placed["b"] == "N2"
    sim.run_until(sim.now + 1.0)  # (its next: N2 resumes the sink)
    assert where(sim, "sink") == {"N4"}
    assert reloc.pid not in core.procedures
    before = sink_stats(sim)
    sim.run_until(sim.now + 1.0)
    assert sink_stats(sim)["count"] > before["count"] + 400
