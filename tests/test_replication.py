"""Chain replication in virtual time: a stateful vertex's state survives its node's death
(the output equals a failure-free run's), a replica's death re-replicates, replicas: 0 keeps
the old behaviour (state restarts), and the app file's replication attributes are checked."""

from __future__ import annotations

from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.errors import AppError
from mso.model.appfile import loads_app
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore
from mso.protocol import effects as fx
from mso.protocol import kept
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.protocol.events import MonitorTick
from mso.protocol.procedures.deploy import holders
from mso.protocol.procedures.instance import H
from mso.protocol.state import AppState
from mso.sim.runner import Simulation
from test_failure import emitted, mesh, recoveries, started, stats, where

# planner: paper: the scenario needs the counter on an interior node (it kills it); the default
# bytes split keeps the 64-byte pipe on the sources' node
COUNTER = """
name: pipe
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 100,
        output: runtime_vertices:Num}
  mid: {code: runtime_vertices:Counter, output: runtime_vertices:Num REPLICAS}
  sink: {code: runtime_vertices:Recorder, pinned: N6}
edges: [[src, mid], [mid, sink]]
"""


def counter_app(replicas: int | None = None) -> str:
    return COUNTER.replace("REPLICAS", "" if replicas is None else f", replicas: {replicas}")


def replication(sim: Simulation, vertex: str = "mid") -> dict[str, Any]:
    node = where(sim, "pipe", vertex)
    out: dict[str, Any] = sim.cores[node].status(sim.now)["apps"]["pipe"]["replication"][vertex]
    return out


def kill_host(sim: Simulation, run_s: float = 4.0) -> str:
    victim = where(sim, "pipe", "mid")
    assert victim not in ("N1", "N6"), victim
    sim.kill(victim, convergence_s=0.3)
    sim.run_until(sim.now + run_s)
    return victim


def said(effects: list[fx.Effect]) -> list[tuple[str, m.Message]]:
    """Whom each send of ``effects`` goes to and what it says (as a control stream's frame
    carries it)."""
    return [(e.dst, e.said) for e in effects if isinstance(e, fx.Send)]


def assert_continuous(sim: Simulation) -> None:
    """The counter's output at the sink is 0, 1, 2, ... with one number per source event:
    what a run without failure gives (no reset to 0, no repeat, none lost)."""
    got = stats(sim, "pipe", "sink")
    sent = emitted(sim, "pipe", "src")
    assert got["repeats"] == 0 and got["out_of_order"] == 0, got
    assert got["next"] == got["count"], got  # the counter never went back
    assert sent - 5 <= got["count"] <= sent, (got, sent)


def test_counter_survives_the_death_of_its_host() -> None:
    sim = started(counter_app())  # replicas: 1 by default (Counter has get_state)
    sim.run_until(sim.now + 1.5)
    rep = replication(sim)
    assert len(rep["replicas"]) == 1 and rep["snapshots"] >= 1, rep
    assert rep["bytes_per_snapshot"] > 0 and rep["interval_s"] > 0, rep
    victim = kill_host(sim)
    assert where(sim, "pipe", "mid") != victim
    (rec,) = recoveries(sim, "pipe")
    assert rec["ok"], rec
    before = stats(sim, "pipe", "sink")["count"]
    assert before > 400
    assert_continuous(sim)


def test_replicas_zero_restarts_the_state_as_before() -> None:
    sim = started(counter_app(0))
    sim.run_until(sim.now + 1.5)
    kill_host(sim)
    got = stats(sim, "pipe", "sink")
    assert got["repeats"] > 50, got  # the counter started again from 0
    assert sim.cores["N1"].apps["pipe"].replicas == {}


def ladder() -> Network:
    """N1 and N6 joined by four two-hop paths: any two middle nodes may die."""
    nodes = [NodeSpec(f"N{i}") for i in range(1, 7)]
    mids = ["N2", "N3", "N4", "N5"]
    links = [LinkSpec(a, b, delay_ms=1.0) for m in mids for a, b in (("N1", m), (m, "N6"))]
    return Network(nodes, links)


def test_two_replicas_survive_two_deaths_in_turn() -> None:
    sim = started(counter_app(2), ladder())
    sim.run_until(sim.now + 1.5)
    assert len(replication(sim)["replicas"]) == 2
    first = kill_host(sim, run_s=4.0)
    assert_continuous(sim)
    assert len(replication(sim)["replicas"]) == 2  # the replacement replicates anew
    second = kill_host(sim, run_s=4.0)
    assert second != first
    assert_continuous(sim)


def test_a_replica_dying_is_replaced_and_the_state_still_survives() -> None:
    sim = started(counter_app(2))
    sim.run_until(sim.now + 1.5)
    host = where(sim, "pipe", "mid")
    replicas = replication(sim)["replicas"]
    # the chain successor's node first (the sink's), then the nearest other node
    assert replicas[0] == "N6" and replicas[1] not in ("N1", host), replicas
    sim.kill(replicas[1], convergence_s=0.3)
    sim.run_until(sim.now + 3.0)
    assert where(sim, "pipe", "mid") == host
    rep = replication(sim)
    assert rep["rereplicated"] >= 1 and replicas[1] not in rep["replicas"], rep
    assert len(rep["replicas"]) == 2 and rep["lag_s"] < 1.5, rep
    kill_host(sim)
    assert_continuous(sim)


def test_a_restore_asked_again_after_its_replacement_ran_keeps_the_count() -> None:
    """The host dies 0.3 s in, while its replica holds only the snapshot taken at the start
    (position 0) and its producer's last ack said the output stood at about 30. The replica's
    answer to the replacement's fetch is held up: its route to the replacement is lost (as
    babeld lost one node's routes after a relay died) until the coordinator's restore has
    timed out and asked again. (Lost on the way, as this test once had it, the answer is sent
    again by its control stream within ``RTO_S``, well inside the restore's step: a loss alone
    no longer makes the restore ask again.) The route comes back as the restore asks again:
    the held answer arrives, the replacement runs from the snapshot, and then the producer's
    second Resume (the Rewire sent again) reaches it. It is numbered from its snapshot: that
    Resume must not renumber its output from the producer's positions (the counter said 0 at
    position 31: the sink got 31 numbers twice; the emulator's kill -9 test under load, 4 and
    10)."""
    sim = Simulation(mesh())
    sim.request("N1", m.DeployRequest(counter_app(), "app.yaml"))
    while not any(isinstance(r, m.DeployReply) for _, _, r in sim.replies):
        sim.run_until(sim.now + 0.01)
    sim.run_until(sim.now + 0.3)
    assert replication(sim)["snapshots"] == 1  # the one at position 0
    assert sim.cores["N1"].apps["pipe"].out[0].positions[1] > 10
    (replica,) = replication(sim)["replicas"]
    prepares: list[tuple[float, str]] = []  # a restore's Prepare: when, to whom
    prepared: list[float] = []  # when the replacement answered one
    fetches: list[str] = []  # who fetched the replica's copy
    resumes: list[tuple[float, str]] = []

    def tap(src: str, dst: str, frame: m.Message) -> None:
        msg = m.carried(frame)  # (a tap sees the frame as sent)
        if isinstance(msg, m.Prepare) and msg.restore:
            prepares.append((sim.now, dst))
        if isinstance(msg, m.Prepared) and msg.node == src:
            prepared.append(sim.now)
        if isinstance(msg, m.FetchReplica) and dst == replica:
            fetches.append(src)
        if isinstance(msg, m.Resume) and msg.producer and msg.edge == 0:
            resumes.append((sim.now, dst))

    sim.taps.append(tap)
    victim = where(sim, "pipe", "mid")
    sim.kill(victim, convergence_s=0.3)
    while not fetches:  # (1 ms a hop: the fetch reaches the replica after this)
        sim.run_until(sim.now + 0.0002)
    replacement = fetches[0]
    sim.lose_route(replica, replacement)
    while len(prepared) < 2:  # the restore timed out and asked again: its target answers
        sim.run_until(sim.now + 0.0002)
    sim.lose_route(replica, replacement, lost=False)
    sim.run_until(sim.now + 4.0)
    assert where(sim, "pipe", "mid") == replacement and replacement != victim
    assert {dst for _, dst in prepares} == {replacement}
    ran = sim.cores[replacement].apps["pipe"].moved["mid"][0]
    assert ran > prepares[1][0]  # (the fetch's answer came only once the restore asked again)
    assert [t for t, dst in resumes if dst == replacement and t >= ran], resumes  # asked again
    assert_continuous(sim)


def alone_on_n1() -> Simulation:
    """The counter on N1 with its one replica on N2, then the link between them cut: no node
    left in reach to replace the replica."""
    pair = Network([NodeSpec("N1"), NodeSpec("N2")], [LinkSpec("N1", "N2", delay_ms=1.0)])
    doc = (
        counter_app()
        .replace("{code: runtime_vertices:Counter,", "{code: runtime_vertices:Counter, pinned: N1,")
        .replace("pinned: N6", "pinned: N1")
    )
    sim = started(doc, pair)
    dep = sim.cores["N1"].apps["pipe"]
    assert dep.replica_nodes["mid"] == ["N2"] and "N2" in holders(dep)
    sim.network.remove_link("N1", "N2")
    sim.links_changed()
    sim.run_until(sim.now + 2.0)
    return sim


def test_a_producer_not_running_yet_says_it_retains_nothing_for_a_restore() -> None:
    """A restore of the counter rewires its producer's end; that end, a replacement (or a
    move's target) not running yet, has a new channel at 0 that retained nothing of what the
    instance before made, and says so (``Resume.retained`` -1): the counter's replacement
    does not take a replica's snapshot whose replay would never come, and its state restarts,
    declared. Before, it said it retained from 0 and a snapshot at 0 was taken (fault seed
    277659: the count went back at the sink with no state restart declared)."""
    sim = started(counter_app())
    sim.run_until(sim.now + 1.5)
    node, host = where(sim, "pipe", "src"), where(sim, "pipe", "mid")
    core, dep = sim.cores[node], sim.cores[node].apps["pipe"]

    def retained() -> int:
        rewire = m.Rewire("pipe", 0, host, 1234, True)
        effects = core.receive(host, rewire, sim.now)
        sent = [e.said for e in effects if isinstance(e, fx.Send) and e.dst == host]
        (said,) = [r for r in sent if isinstance(r, m.Resume)]
        return said.retained

    assert retained() >= 0  # running: from its newest replicated snapshot on
    h = dep.instances.pop("src")  # its replacement, not running yet: no channel of its own
    h.life.state = H.AWAITING
    dep.awaiting["src"] = h
    del dep.out[0]
    assert retained() == -1


def test_a_replica_replaced_by_none_is_no_longer_named_by_its_host() -> None:
    """The counter's one replica goes out of reach and no other node is left to replace it:
    the host tells it it is none and names none in its own view too. Before, the view (which
    the host's syncs carry, and which says who holds the app) still named the old replica, so
    a node synced by the host gave it the app again after it had let it go (fault seed
    84069: it held the app past the quiet phase, taking no part in it)."""
    sim = alone_on_n1()
    dep = sim.cores["N1"].apps["pipe"]
    assert replication(sim)["replicas"] == []
    assert dep.replica_nodes["mid"] == [] and "N2" not in holders(dep)
    assert "N2" not in kept.record(dep).replicas["mid"]  # (what a sync of this view says)


def test_a_new_instance_with_no_replica_in_reach_names_none_in_its_hosts_view() -> None:
    """A new instance of the counter (restarted in place after its process crashed) whose
    host's view names the last instance's replica (as a restore's ``Prepare`` or a sync names
    it), out of reach: from its first snapshot, held by none, the view names none. Before, it
    kept naming the old replica until a new one was found, and the host's syncs gave that
    node, told meanwhile it was none, the app again (fault seed 250055: N6 restored a vertex
    while cut off, and 5 s later synced the node it chose as a replica with a view naming
    N4, which was passed the app 0.5 s before the quiet end, taking no part)."""
    sim = alone_on_n1()
    core = sim.cores["N1"]
    dep = core.apps["pipe"]
    crashed = dep.instances["mid"]
    sim.apply("N1", core.on_vertex(fx.VertexCrashed(crashed.instance, reason="killed"), sim.now))
    while "mid" not in dep.instances or not dep.instances["mid"].started:
        sim.run_until(sim.now + 0.001)
    dep.replica_nodes["mid"] = ["N2"]  # (the last instance's replica, by this view)
    sim.run_until(sim.now + 2.0)
    assert dep.instances["mid"].instance != crashed.instance
    assert dep.replica_nodes["mid"] == [] and "N2" not in holders(dep)


def test_a_host_short_of_a_replica_takes_one_as_soon_as_a_node_is_in_reach() -> None:
    """The counter's one replica was cut off and none was left to replace it; the link comes
    back: N2 is its replica again at once, holding a snapshot, not at the next snapshot due by
    time. Before, a host took another replica only with a snapshot due by time (5 s): one
    due by events (every second here) reset that clock, so the count was kept nowhere for as
    long as it ran (control loss seed 283: restored on a node alone in a cut, the vertex's
    replica was chosen 5 s after the heal, as the run ended, and its lost ``Replicate`` left
    the node synced the app holding it, taking no part)."""
    sim = alone_on_n1()
    dep = sim.cores["N1"].apps["pipe"]
    assert replication(sim)["replicas"] == []
    sim.network.add_link(LinkSpec("N1", "N2", delay_ms=1.0))
    sim.links_changed()
    sim.run_until(sim.now + 0.5)
    assert replication(sim)["replicas"] == ["N2"]
    assert dep.replica_nodes["mid"] == ["N2"]
    assert "mid" in sim.cores["N2"].apps["pipe"].held


def test_a_restarted_host_does_not_tell_a_copy_of_its_lost_instance_to_go() -> None:
    """The counter's host restarts; the replica's ask whether it is still one (held while
    the host was down) reaches the new process, which runs no counter. A copy whose host
    failed is kept: the replacement starts from it. Before, the host answered it ran none,
    the replica let its copy go, and the restored counter started again from 0 (fault seed
    77821: the replica let go a newer copy, of the restored vertex, and the app with it)."""
    sim = started(counter_app())
    sim.run_until(sim.now + 1.5)
    host = where(sim, "pipe", "mid")
    (replica,) = replication(sim)["replicas"]
    copy = sim.cores[replica].apps["pipe"].held["mid"]
    sim.crash(host)
    sim.run_until(sim.now + 0.05)
    sim.revive(host)
    ask = m.ReplicaAck("pipe", "mid", copy.k)
    sim.apply(host, sim.cores[host].receive(replica, ask, sim.now))
    sim.run_until(sim.now + 0.02)
    assert "mid" in sim.cores[replica].apps["pipe"].held
    sim.run_until(sim.now + 5.0)
    assert_continuous(sim)


def test_a_copy_whose_maker_restarted_is_settled_by_the_vertexs_host_by_this_nodes_view() -> None:
    """N2 holds a copy of the counter made on N1, which then restarted; the counter runs on
    N3 now, restored by a node that never named N2 its replica. N1's new process does not
    answer for its last one's instance (seed 77821), so N2 asks N3, the host by its view,
    too: told it is none, it lets the copy and the app go (fault seed 122799: it asked N1
    alone, every second, and held the app past the quiet phase)."""
    doc = counter_app().replace("pinned: N6", "pinned: N3")
    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N3": ("N3", 1)}, 0.0)
    placed = {"src": "N1", "mid": "N1", "sink": "N3"}
    core.receive("N1", m.AppSync("pipe", "N1", doc, 0, placed, replicas={"mid": ["N2"]}), 1.0)
    core.receive("N1", m.Replicate("pipe", "mid", 1, b"\x05", {0: 10}, {1: (10, [])}), 1.0)
    dep = core.apps["pipe"]
    assert "mid" in dep.held
    core.receive("N1", NodeCore("N1", incarnation=1).membership.beat(), 1.5)  # restarted
    core.receive("N3", m.Moved("pipe", "mid", "N3", 0, 1), 1.6)  # restored there
    _asks_n3_and_lets_go(core, dep)


def test_a_copy_whose_maker_restarted_and_whose_vertex_this_view_lost_looks_it_up() -> None:
    """N2 holds a copy of the counter made on N1, which then restarted (the counter vanished
    by N2's view); the counter was restored on N3 from another replica by a node that never
    named N2 (its news of N2 was lost), and nobody tells N2, hosting nothing, of the restore.
    N1's new process does not answer for its last one's instance (seed 77821), so N2 looks up
    where the counter runs, then asks N3: told it is none, it lets the copy and the app go
    (fault seed 267786: it asked N1 alone, every second, and held the app past the quiet
    phase)."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N1", NodeCore("N1", incarnation=1).membership.beat(), 1.5)  # restarted
    assert "mid" in dep.vanished
    effects = core.on_timer(MonitorTick(), 2.0)
    queries = {
        e.dst: e.said
        for e in effects
        if isinstance(e, fx.Send) and isinstance(e.said, m.PlacementQuery)
    }
    assert sorted(queries) == ["N1", "N4"], effects  # the nodes its view names
    qid = queries["N4"].qid
    core.receive("N1", m.PlacementReply("pipe", qid, {}), 2.01)  # (holds none of it now)
    placed = {"src": "N1", "mid": "N3", "sink": "N4"}
    effects = core.receive("N4", m.PlacementReply("pipe", qid, placed, {"mid": 1}), 2.01)
    assert dep.placed["mid"] == "N3" and "mid" not in dep.vanished
    assert ("N3", m.PlacementQuery("pipe", qid)) in said(effects)  # (named by the answer)
    core.receive("N3", m.PlacementReply("pipe", qid, placed, {"mid": 1}), 2.02)
    _asks_n3_and_lets_go(core, dep)


def test_a_copy_fetched_for_a_restore_is_settled_by_the_node_that_fetched_it() -> None:
    """N2 holds a copy of the counter made on N1; N1 restarts (its counter vanished) and N3
    restores the counter on itself from N2's copy (its ``FetchReplica``). N2 never hears of
    the move, so its view still places the counter on N1; the new host's replica set, naming
    other nodes, is the word of the vertex's host by that restore: N2 lets the copy and the
    app go. Refused as not from the host by its view, N2 held the app past the quiet phase
    taking no part (fault seed 162928). A node that did not fetch it is still refused."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N4", m.ReplicaSet("pipe", "mid", ["N5"]), 1.5)  # not its host, nor fetched
    assert "mid" in dep.held
    core.receive("N1", NodeCore("N1", incarnation=1).membership.beat(), 1.8)  # restarted
    assert "mid" in dep.vanished
    effects = core.receive("N3", m.FetchReplica("pipe", "mid", 77), 2.0)
    assert any(isinstance(e, fx.Send) and isinstance(e.said, m.Replicate) for e in effects)
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"]), 3.0)
    assert "mid" not in dep.held and dep.placed["mid"] == "N1"  # (its view, unchanged)
    for t in (4.0, 5.0, 6.0):
        core.on_timer(MonitorTick(), t)
    assert "pipe" not in core.apps


def test_a_member_that_fetched_a_copy_of_a_vertex_on_a_live_host_cannot_settle_it() -> None:
    """N2 holds a copy of the counter, which runs on N1, alive and not restarted in N2's
    view. The member N3 asks for the copy as a restore would (``FetchReplica``) and then
    names other replicas (``ReplicaSet``): a restore needs the vertex lost (its host held
    failed, or its instance vanished with a restart), which N2's view does not hold, so the
    set is refused and counted and the copy kept. Before, having fetched it made N3's word
    settle it: a captured member made a replica drop the state of a vertex it did not host."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N3", m.FetchReplica("pipe", "mid", 77), 2.0)
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"]), 2.1)
    assert "mid" in dep.held and dep.replica_nodes["mid"] == ["N2"]
    assert core.refusals["replica_set_by_fetcher_of_a_vertex_not_lost"] == 1
    core.receive("N1", m.ReplicaSet("pipe", "mid", ["N4"]), 2.2)  # its host's word counts
    assert "mid" not in dep.held


def test_a_later_hosts_set_settles_a_copy_its_view_places_elsewhere() -> None:
    """N2 holds a copy of the counter made on N1 (at its deployment's placement, version 0).
    The counter moves to N3 and N2, hosting nothing of the app, is not told: its view still
    places it on N1. N3's set without N2, at the move's version (1), is the word of the
    vertex's host by a later move than N2's view and copy know of: N2 lets the copy and the
    app go. Refused on the old view, N2 kept both until it asked N1 at its next round, and held
    the app past the quiet phase (control loss seed 731). A set at no later version (a node
    answering for itself; N3 at the copy's own move) is still refused."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"]), 1.5)  # (answers for itself)
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"], 0), 1.5)  # (no later move)
    assert "mid" in dep.held and core.refusals["replica_set_not_from_host"] == 2
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"], 1), 2.0)
    assert "mid" not in dep.held and dep.placed["mid"] == "N1"  # (its view, unchanged)
    for t in (3.0, 4.0):
        core.on_timer(MonitorTick(), t)
    assert "pipe" not in core.apps


def test_a_set_from_a_move_older_than_the_copys_does_not_settle_it() -> None:
    """N2's copy of the counter was made by N5 at its second move (N2's view, never told, still
    places the counter on N1). A set without N2 from N3, the host by the first move, sent
    before the second and delivered late, is older than the copy: refused, the copy kept."""
    core, dep = _replica_of_mid_on_n1()
    core.receive(
        "N5", m.Replicate("pipe", "mid", 1, b"\x09", {0: 20}, {1: (20, [])}, version=2), 1.5
    )
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"], 1), 2.0)
    assert dep.held["mid"].src == "N5" and core.refusals["replica_set_not_from_host"] == 1


def test_the_old_hosts_none_does_not_settle_a_copy_made_at_a_later_move() -> None:
    """N2's view, never told of the counter's move, still places it on N1; the counter's new
    host N5 sends N2 its first snapshot (at the move's version, 1), which replaces N1's copy.
    N1's answer to an ask sent before (held by a cut: "none", as it answers for itself) is
    the word of the host by a view older than the copy: refused, the copy and the app kept.
    Taken, N2 let both go while N5 named it its replica to the end (fault seed 329996). The
    copy's maker still settles it."""
    core, dep = _replica_of_mid_on_n1()
    core.receive(
        "N5", m.Replicate("pipe", "mid", 1, b"\x09", {0: 20}, {1: (20, [])}, version=1), 1.5
    )
    core.receive("N1", m.ReplicaSet("pipe", "mid", []), 2.0)
    assert dep.held["mid"].src == "N5" and core.refusals["replica_set_not_from_host"] == 1
    assert dep.placed["mid"] == "N1"  # (its view, unchanged)
    core.receive("N5", m.ReplicaSet("pipe", "mid", ["N4"], 1), 2.5)
    assert "mid" not in dep.held


def test_with_operator_keys_a_later_hosts_set_counts_only_where_it_may_tell() -> None:
    """With operator keys a node's claim of a later move is taken as a ``Moved`` from it would
    be (``placement.may_tell``): a member naming any version cannot make a replica drop its
    copy of a vertex running on a live host in its view; once the view holds that host
    failed, the new host's set settles it."""
    core, dep = _replica_of_mid_on_n1()
    core.authority = Authority(operators={"op": Ed25519PrivateKey.generate().public_key()})
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"], 7), 2.0)
    assert "mid" in dep.held and core.refusals["replica_set_not_from_host"] == 1
    core.membership.failed.add("N1")
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"], 7), 2.5)
    assert "mid" not in dep.held


def test_a_restarted_hosts_first_snapshot_replaces_the_copy_its_last_process_made() -> None:
    """N2 holds snapshot 1 of the counter made on N1; N1 restarts, restores the counter and
    sends its new instance's snapshot 1. Same host, same number, but a newer instance's: N2
    keeps it (and it is what N2 acknowledged). Before, taken as the old copy sent again, the
    copy stayed the last process's: a restore from it started from old state, and N2, asking
    as for a copy whose maker is gone, asked the host by its stale view, N3, which said it was
    none: N2 let the copy and the app go, still N1's replica (fault seed 314002)."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N1", NodeCore("N1", incarnation=1).membership.beat(), 1.5)  # restarted
    core.receive("N3", m.Moved("pipe", "mid", "N3", 0, 1), 1.6)  # a view gone stale since
    effects = core.receive(
        "N1", m.Replicate("pipe", "mid", 1, b"\x1c", {0: 28}, {1: (28, [])}), 2.0
    )
    assert ("N1", m.ReplicaAck("pipe", "mid", 1)) in said(effects)
    copy = dep.held["mid"]
    assert (copy.state, copy.inputs, copy.src_incarnation) == (b"\x1c", {0: 28}, 1)
    effects = core.on_timer(MonitorTick(), 3.5)
    asked = [dst for dst, msg in said(effects) if isinstance(msg, m.ReplicaAck)]
    assert asked == ["N1"], effects  # its maker, alive: not the host by a stale view


def test_a_lower_snapshot_number_from_the_copys_host_is_a_new_instances() -> None:
    """The counter moved off N1 and back (N2 heard of neither move); N1's new instance
    numbers its snapshots from 1 again. Its control stream delivers N1's frames in order, so
    a snapshot after snapshot 3 is newer whatever its number: N2 keeps it."""
    core, dep = _replica_of_mid_on_n1()
    core.receive("N1", m.Replicate("pipe", "mid", 3, b"\x07", {0: 30}, {1: (30, [])}), 1.2)
    core.receive("N1", m.Replicate("pipe", "mid", 1, b"\x02", {0: 40}, {1: (40, [])}), 2.0)
    assert (dep.held["mid"].k, dep.held["mid"].inputs) == (1, {0: 40})
    core.receive("N1", m.Replicate("pipe", "mid", 1, b"\x02", {0: 40}, {1: (40, [])}), 2.5)
    assert core.replicator.held.stale == 1  # (the same one sent again: a refresh)


def _asks_n3_and_lets_go(core: NodeCore, dep: AppState) -> None:
    """At its next round N2 asks N3, the counter's host by its view, whether it is still a
    replica; told the set without it, it lets the copy go, then the app."""
    effects = core.on_timer(MonitorTick(), 3.0)
    assert ("N3", m.ReplicaAck("pipe", "mid", 1)) in said(effects)
    core.receive("N3", m.ReplicaSet("pipe", "mid", ["N4"]), 3.1)
    assert "mid" not in dep.held
    for t in (4.0, 5.0):
        core.on_timer(MonitorTick(), t)
    assert "pipe" not in core.apps


def _replica_of_mid_on_n1() -> tuple[NodeCore, AppState]:
    """N2, the counter's replica, holding a copy made on N1, the counter's host."""
    doc = counter_app().replace("pinned: N6", "pinned: N4")
    core = NodeCore("N2")
    core.set_routes({"N1": ("N1", 1), "N3": ("N3", 1), "N4": ("N4", 1)}, 0.0)
    placed = {"src": "N1", "mid": "N1", "sink": "N4"}
    core.receive("N1", m.AppSync("pipe", "N1", doc, 0, placed, replicas={"mid": ["N2"]}), 1.0)
    core.receive("N1", m.Replicate("pipe", "mid", 1, b"\x05", {0: 10}, {1: (10, [])}), 1.0)
    return core, core.apps["pipe"]


def test_replication_attributes_are_validated_and_defaulted() -> None:
    app = loads_app(counter_app())
    assert app.replicas("mid") == 1 and app.replicas("src") == 0 and app.replicas("sink") == 0
    assert loads_app(counter_app(2)).replicas("mid") == 2
    stateless = COUNTER.replace("runtime_vertices:Counter", "runtime_vertices:Double")
    assert loads_app(stateless.replace("REPLICAS", "")).replicas("mid") == 0
    bad = {
        "replicas: 3": "expected 0, 1 or 2 replicas",
        "replicas: yes": "expected 0, 1 or 2 replicas",
        "snapshot_events: 0": "expected a whole number of events",
        "snapshot_s: -1": "expected a number of seconds",
    }
    for attr, why in bad.items():
        with pytest.raises(AppError, match=why) as exc:
            loads_app(COUNTER.replace("REPLICAS", f", {attr}"), file="app.yaml")
        assert "vertices.mid." in str(exc.value) and "app.yaml:" in str(exc.value)
    src = COUNTER.replace("rate: 100,", "rate: 100, replicas: 1,").replace("REPLICAS", "")
    with pytest.raises(AppError, match="a source keeps no replica"):
        loads_app(src)


@pytest.mark.slow
def test_kill_9_of_the_host_on_the_emulator_keeps_the_count(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Real node processes: SIGKILL the node hosting the counter; the replacement starts from
    its replica and the sink's numbers go on with no repeat and no gap."""
    import asyncio
    import os
    from pathlib import Path

    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario
    from test_emulator import MESH
    from waits import until

    tests = str(Path(__file__).resolve().parent)  # node processes import the test vertices
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{tests}{os.pathsep}{path}" if path else tests)

    async def run() -> tuple[str, int, dict[str, Any]]:
        emu = Emulator(loads_scenario(MESH), convergence_s=0.2)
        await emu.start()
        try:
            reply = await emu.deploy(counter_app(), "pipe.yaml", "N1")
            assert reply.ok, reply.error
            victim = reply.placement["mid"]
            assert victim not in ("N1", "N6")

            def replicated(st: dict[str, Any]) -> bool:  # snapshots every 100 events
                return bool(st[victim]["apps"]["pipe"]["replication"]["mid"]["snapshots"] >= 1)

            await until(lambda: emu.status(victim), replicated, 10, "a replicated snapshot")
            emu.kill(victim)

            def read() -> Any:
                return emu.status("N1")

            def moved(st: dict[str, Any]) -> bool:  # a live node runs mid again
                hosts = [
                    n
                    for n, s in st.items()
                    if "mid" in s["apps"].get("pipe", {"vertices": {}})["vertices"]
                ]
                return victim not in st and bool(hosts)

            status = await until(read, moved, 10, f"mid restored off {victim}")
            emitted = int(status["N1"]["apps"]["pipe"]["vertices"]["src"]["emitted"])

            def arrived(st: dict[str, Any]) -> bool:  # what was in flight
                return bool(
                    st["N6"]["apps"]["pipe"]["vertices"]["sink"]["stats"]["count"] >= emitted
                )

            status = await until(read, arrived, 5, f"the sink's count at {emitted}")
            return victim, emitted, status
        finally:
            await emu.stop()

    victim, emitted, status = asyncio.run(run())
    hosts = [
        n
        for n, st in status.items()
        if "mid" in st["apps"].get("pipe", {"vertices": {}})["vertices"]
    ]
    assert len(hosts) == 1 and hosts[0] != victim
    got = status["N6"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert got["repeats"] == 0 and got["out_of_order"] == 0, got
    assert got["next"] == got["count"] >= emitted, (got, emitted)  # the count never went back
