"""Chain replication of a stateful vertex's state (the paper's future work, §3.4/§5), every
role in one place: the host, its replicas, the producers of its inputs and a replacement.

A vertex with state (``replicas: 1`` by default, see docs/app-format.md) survives the death of
its node with no event lost or repeated in its output::

    producer(s)              host                       replica(s)
      retain events  ──▶   every N events / T s:
      from the last        snapshot, aligned: drain
      replicated           what was fed, then take the
      snapshot             state and the positions
                             Replicate(k) ─────────────▶  keep the newest
                                          ◀─────────────  ReplicaAck(k)
             ◀──────────  Release(upto = position of k) (once every replica holds k)

The snapshot is *aligned* as an asynchronous barrier snapshot's is: a mark in the instance's
queue waits until everything fed before it is processed (:class:`~.state.SnapshotMark`), so
the state, the input positions (events processed per edge) and the output positions (events
produced, with those not yet acknowledged downstream) agree. Each producer keeps, past their
ack, the events after the newest snapshot every replica holds (``OutChannel.retain``); a
``Release`` moves that retention on.

When the host dies, the restore (:mod:`.restore`) prepares a replacement; the replacement
fetches the newest snapshot from a replica (``FetchReplica``; local if it holds one itself),
its producers replay from their retention, and it starts from the snapshot's state and
positions: inputs from the snapshot's positions (earlier replayed events are duplicates),
outputs numbered from the snapshot's and its unacknowledged output sent again, so its
consumers drop what they already had. The output equals a failure-free run's for a vertex
that is deterministic in the order of its inputs. With no usable snapshot (no replica left,
or a producer that cannot replay from its position: it died too), the replacement starts from
its constructor, as a vertex with ``replicas: 0`` does.

A host's :class:`Replication` is IDLE between snapshots, ALIGNING while the mark waits,
TAKING while the executor encodes the state, REPLICATING until every replica acknowledged.
A replica that does not acknowledge within ``ACK_TIMEOUT_S`` is sent the snapshot again; after
``ACK_ATTEMPTS`` it is replaced, as a failed one is at once (re-replication: the next node is
chosen and sent the snapshot). A new replica set is broadcast (``ReplicaSet``) once it holds a
snapshot, so a replacement never asks a replica that has nothing yet.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import ClassVar

from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import REPLICA_OWNER, DataPlane
from mso.protocol.events import (
    AppMissing,
    InstanceReady,
    PeerFailed,
    PlacementStale,
    ReplacementPrepared,
    ReplicationTick,
    RoutesChanged,
    SnapshotAligned,
    Snapshotted,
)
from mso.protocol.procedures import placement
from mso.protocol.procedures.base import STEP_TIMEOUT_S, StateMachine, Table
from mso.protocol.procedures.deploy import holders
from mso.protocol.provenance import Marks
from mso.protocol.state import (
    SNAPSHOT_MARK,
    AppState,
    HostedInstance,
    ReplicationCost,
    Restoring,
    Snapshot,
)

ACK_TIMEOUT_S = STEP_TIMEOUT_S  # a replica silent this long is sent the snapshot again ...
ACK_ATTEMPTS = 3  # ... and after this many sends, replaced
MIN_TICK_S = 0.05
# a snapshot carries the output not yet acknowledged downstream; past this (a consumer out of
# reach, its backlog held here) it waits for the backlog to drain rather than make one frame
# of it: the producers retain a little longer meanwhile
MAX_SNAPSHOT_BYTES = 4 << 20


class S(enum.Enum):
    IDLE = "idle"
    ALIGNING = "aligning"
    TAKING = "taking"
    REPLICATING = "replicating"


class ReplicationEvent(enum.Enum):
    """What moves a host's Replication along its table."""

    DUE = "due"  # a snapshot is due (events, time, a new or replaced replica)
    ALIGNED = "aligned"  # the instance processed everything fed before the mark
    TAKEN = "taken"  # the executor encoded the state
    ACKED = "acked"  # one replica holds it
    ALL_ACKED = "all_acked"  # every replica holds it: producers release
    DEFERRED = "deferred"  # too much output unacknowledged to send with it: later
    RESEND = "resend"  # a replica did not acknowledge in time
    REPLICA_LOST = "replica_lost"  # a replica failed or stayed silent: another is chosen


class Replication(StateMachine):
    """The host's part: one replicated vertex instance's snapshots and replicas."""

    NAME = "replication"
    INITIAL = S.IDLE
    TRANSITIONS: ClassVar[Table] = {
        S.IDLE: {ReplicationEvent.DUE: S.ALIGNING, ReplicationEvent.REPLICA_LOST: S.IDLE},
        S.ALIGNING: {
            ReplicationEvent.ALIGNED: S.TAKING,
            ReplicationEvent.DEFERRED: S.IDLE,
            ReplicationEvent.REPLICA_LOST: S.ALIGNING,
        },
        S.TAKING: {ReplicationEvent.TAKEN: S.REPLICATING, ReplicationEvent.REPLICA_LOST: S.TAKING},
        S.REPLICATING: {
            ReplicationEvent.ACKED: S.REPLICATING,
            ReplicationEvent.ALL_ACKED: S.IDLE,
            ReplicationEvent.RESEND: S.REPLICATING,
            ReplicationEvent.REPLICA_LOST: S.REPLICATING,
        },
    }

    def __init__(self, app: str, vertex: str, instance: int, now: float) -> None:
        super().__init__()
        self.app = app
        self.vertex = vertex
        self.instance = instance
        self.k = 0
        self.replicas: list[str] = []
        self.announced: list[str] = []  # the set broadcast last
        self.acked: set[str] = set()
        self.attempts: dict[str, int] = {}  # replica -> sends of the current snapshot
        self.told: set[str] = set()  # replicas sent the app by this host (issue 24.1)
        self.former: set[str] = set()  # replicas replaced while out of reach, not told so
        self.marks: Marks | None = None  # a forwarder's, at the snapshot
        self.markgens: dict[int, int] = {}  # the generations they are of (not 0)
        self.snapshot: Snapshot | None = None  # being replicated (the newest taken)
        self.inputs: dict[int, int] = {}  # positions captured at the mark
        self.outputs: dict[int, tuple[int, list[bytes]]] = {}
        self.counts = (0, 0)  # processed, emitted at the mark
        self.aligned_at = now
        self.taken_at = -1e9
        self.sent_at = now

    @property
    def name(self) -> str:
        return f"replication of {self.vertex}"


@dataclass
class _Held:
    """Counts of the replica side at this node (status of the procedure's other roles)."""

    stored: int = 0
    stale: int = 0
    served: int = 0


class Replicator:
    """This node's part in chain replication, in every role (module docstring)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        self.ctx = ctx
        self.dp = dp
        self.hosting: dict[tuple[str, str], Replication] = {}
        self._armed: set[str] = set()  # apps whose tick is set
        self.held = _Held()
        self._asked: dict[tuple[str, str], float] = {}  # (app, vertex) -> asked its host

    def on_reset(self) -> None:
        self.hosting.clear()
        self._armed.clear()

    # -- the host: snapshots at marks, sends them, releases the producers ----------------------
    def on_instance_ready(self, ev: InstanceReady) -> None:
        """A replicated vertex's instance started here (a deployment, a move, a replacement):
        its replication begins at the next tick, once it runs."""
        dep = self.ctx.apps.get(ev.app)
        if dep is not None and dep.replicas.get(ev.vertex):
            self._arm(ev.app, self.ctx.now)
            # a host is not its own replica: a copy held here from before (it was one, or a
            # replacement here started from it) would keep the app here for ever once the
            # vertex moves on (issue 24.1)
            dep.held.pop(ev.vertex, None)

    def _arm(self, app: str, at: float) -> None:
        if app not in self._armed:
            self._armed.add(app)
            self.ctx.set_timer(ReplicationTick(app), at)

    def tick(self, key: ReplicationTick, now: float) -> None:
        """Start replicating new instances, take the snapshots due by time, send again what
        was not acknowledged; set the next tick while a replicated vertex is here."""
        app = key.app
        self._armed.discard(app)
        dep = self.ctx.apps.get(app)
        period: float | None = None
        for vid, n in (dep.replicas if dep is not None else {}).items():
            assert dep is not None
            h = dep.instances.get(vid)
            rep = self.hosting.get((app, vid))
            if h is None or not h.started or h.crashed:
                if rep is not None:
                    del self.hosting[(app, vid)]
                    dep.replication.pop(vid, None)
                if vid in dep.awaiting:
                    period = ACK_TIMEOUT_S if period is None else min(period, ACK_TIMEOUT_S)
                continue
            v = dep.app.vertices[vid]
            period = min(period or v.snapshot_s, v.snapshot_s, ACK_TIMEOUT_S)
            if rep is None or rep.instance != h.instance:
                rep = self.hosting[(app, vid)] = Replication(app, vid, h.instance, now)
                dep.replication[vid] = ReplicationCost(since=now)
                rep.replicas = self._choose(dep, vid, n, [])
                # the replicas of the instance before (a move, a restore): told the new set
                rep.former = set(dep.replica_nodes.get(vid, [])) - {self.ctx.id}
                self._due(dep, h, rep)
            elif self._top_up(dep, h, rep):
                pass  # (too few replicas, and another node is in reach now: a snapshot)
            elif rep.state is S.IDLE and now - rep.taken_at >= v.snapshot_s - 1e-9:
                if len(rep.replicas) < n:  # too few nodes were reachable: try again
                    rep.replicas = self._choose(dep, vid, n, rep.replicas)
                if h.processed != rep.counts[0] or rep.replicas != rep.announced:
                    self._due(dep, h, rep)
            elif rep.state is S.REPLICATING and now - rep.sent_at >= ACK_TIMEOUT_S - 1e-9:
                self._resend(dep, rep, now)
        if self.hosting and dep is None:
            for k in [k for k in self.hosting if k[0] == app]:
                del self.hosting[k]
        if period is not None:
            self._arm(app, now + max(period, MIN_TICK_S))

    def _choose(self, dep: AppState, vid: str, n: int, keep: list[str]) -> list[str]:
        """``n`` replica nodes for ``vid``: those kept, then its successors' nodes (its chain
        successor first), then the nearest other nodes; never this node nor a failed one."""
        failed, me = self.ctx.failed, self.ctx.id
        reach = self.ctx.distances()
        out = [r for r in keep if r not in failed and r != me and r in reach][:n]
        succ = [dep.placed[s] for s in dep.app.successors()[vid] if s in dep.placed]
        order = sorted(reach, key=lambda node: (node not in succ, reach[node], node))
        for node in order:
            if len(out) >= n:
                break
            if node not in out and node != me and node not in failed:
                out.append(node)
        return out

    def _top_up(self, dep: AppState, h: HostedInstance, rep: Replication) -> bool:
        """Between snapshots, a vertex with fewer replicas than it asks for (none was in
        reach when they were chosen: a restore on a node cut off, a replica lost with no
        other to take its place) takes one as soon as a node is in reach, and sends it a
        snapshot at once -- not at the next snapshot due by time or events, seconds on, the
        vertex's state kept nowhere meanwhile (control loss seed 283: restored on a node
        alone in a cut, its replica chosen 5 s after the heal, as the run ended)."""
        n = dep.replicas.get(rep.vertex, 0)
        if rep.state is not S.IDLE or len(rep.replicas) >= n:
            return False
        more = self._choose(dep, rep.vertex, n, rep.replicas)
        if len(more) <= len(rep.replicas):
            return False
        rep.replicas = more
        self._due(dep, h, rep)
        return True

    def _due(self, dep: AppState, h: HostedInstance, rep: Replication) -> None:
        """Ask for an aligned snapshot: a mark ahead of what waits to be fed."""
        rep.on(ReplicationEvent.DUE)
        h.snapshot_at = 0
        if SNAPSHOT_MARK not in h.pending:  # (the data plane may have queued one: events)
            h.pending.appendleft(SNAPSHOT_MARK)
        self.dp.pump(dep, rep.vertex)

    def on_aligned(self, ev: SnapshotAligned) -> None:
        """Everything fed before the mark is processed: take the positions, then the state."""
        dep = self.ctx.apps.get(ev.app)
        rep = self.hosting.get((ev.app, ev.vertex))
        h = dep.instances.get(ev.vertex) if dep is not None else None
        if dep is None or rep is None or h is None or h.instance != rep.instance:
            return
        if rep.state is S.IDLE:  # the data plane's mark: due by the events processed
            rep.on(ReplicationEvent.DUE)
        elif rep.state is not S.ALIGNING:
            return  # (a mark queued before a re-replication's own: one snapshot is enough)
        edges = dep.app.edges
        rep.inputs = {
            i: (ch.processed if (ch := dep.inc.get(i)) is not None else 0)
            for i, e in enumerate(edges)
            if e.dst == ev.vertex
        }
        rep.outputs = {}
        for o in dep.out_edges.get(ev.vertex, []):
            out = self.dp.out(dep, o)
            if out.kept_bytes > MAX_SNAPSHOT_BYTES:
                rep.on(ReplicationEvent.DEFERRED)
                rep.taken_at = self.ctx.now  # (tried again by time)
                return
            rep.outputs[o] = out.unacked()
        rep.on(ReplicationEvent.ALIGNED)
        rep.counts = (h.processed, h.emitted)
        rep.marks, rep.markgens = None, {}
        if ev.vertex in dep.layout.forwarders:  # (one input edge)
            (i,) = rep.inputs
            ch = dep.inc.get(i)
            catch_up = dep.catch_up.get(ev.vertex)
            held = catch_up.held if catch_up is not None else []
            later = [evs for it in h.pending if isinstance(it, tuple) for evs in it[1]]
            rep.marks = provenance.processed(ch.marks if ch else {}, [*later, *held])
            rep.markgens = dict(ch.markgens) if ch else {}
        rep.aligned_at = self.ctx.now
        rep.k += 1
        self.dp.submit(h, fx.SnapshotVertex(h.instance, -rep.k))  # (relocations' are >= 0)

    def on_snapshotted(self, ev: Snapshotted) -> None:
        """The state is taken: send it to every replica."""
        res = ev.result
        rep = self.hosting.get((ev.app, ev.vertex))
        dep = self.ctx.apps.get(ev.app)
        if res.token >= 0 or rep is None or dep is None or res.instance != rep.instance:
            return
        if -res.token != rep.k or rep.state is not S.TAKING:
            return
        rep.on(ReplicationEvent.TAKEN)
        snap = Snapshot(
            rep.k, res.state, rep.inputs, rep.outputs, *rep.counts, src=self.ctx.id,
            marks=rep.marks, markgens=rep.markgens,
        )  # fmt: skip
        cost = dep.replication.setdefault(ev.vertex, ReplicationCost(since=self.ctx.now))
        if rep.taken_at > 0:
            cost.interval_s = rep.aligned_at - rep.taken_at
        rep.taken_at = rep.aligned_at
        rep.snapshot = snap
        rep.acked = set()
        rep.attempts = {}
        cost.last_bytes = snap.size
        if not rep.replicas:  # no other node to hold it (yet): its state is not kept, and
            rep.on(ReplicationEvent.ALL_ACKED)  # its producers need not keep events for it
            self._all_acked(dep, rep)
            return
        for r in rep.replicas:
            self._send(dep, rep, r)

    def _send(self, dep: AppState, rep: Replication, node: str) -> None:
        snap = rep.snapshot
        if snap is None:
            return
        rep.attempts[node] = rep.attempts.get(node, 0) + 1
        rep.sent_at = self.ctx.now
        new = node not in rep.told and node not in holders(dep)
        rep.told.add(node)
        if new or rep.attempts[node] > 1:
            # only the nodes that take part in an app hold it (issue 24.1): a new replica,
            # or one silent (reset, restarted, or it let the app go), gets it first
            self.ctx.publish(AppMissing(rep.app, node, ahead=True))
        self.ctx.send(node, _replicate(rep.app, rep.vertex, snap, version=_hosted(dep, rep)))
        cost = dep.replication.get(rep.vertex)
        if cost is not None:
            cost.bytes_sent += snap.size

    def _resend(self, dep: AppState, rep: Replication, now: float) -> None:
        """Replicas silent since the snapshot was sent: again, or replaced after a few."""
        cost = dep.replication.get(rep.vertex)
        for node in [r for r in rep.replicas if r not in rep.acked]:
            if rep.attempts.get(node, 0) >= ACK_ATTEMPTS:
                self._replace(dep, rep, node)
                continue
            rep.on(ReplicationEvent.RESEND)
            if cost is not None:
                cost.resent += 1
            self._send(dep, rep, node)

    def on_replica_ack(self, src: str, msg: m.ReplicaAck) -> None:
        rep = self.hosting.get((msg.app, msg.vertex))
        dep = self.ctx.apps.get(msg.app)
        if rep is None or src not in rep.replicas:
            # a copy's holder asks whether it is still a replica (ask_if_replica): not of
            # this node's instance, if any (the set it has, or none) -- unless the instance
            # went with this node's last process (placed here, vanished): a copy whose host
            # failed is kept, as its replacement may start from it, and that replacement's
            # host tells the replica its set (fault seed 77821: an ask held while this node
            # was down was answered by its next process, and the replica let go a newer
            # copy, of the restored vertex, and the app with it)
            nodes = list(rep.replicas) if rep is not None else []
            version = _hosted(dep, rep) if rep is not None and dep is not None else -1
            here = dep is not None and dep.placed.get(msg.vertex) == self.ctx.id
            gone = here and rep is None and dep is not None and msg.vertex in dep.vanished
            if len(msg.vertex) <= 256 and msg.vertex and src not in nodes and not gone:
                self.ctx.send(src, m.ReplicaSet(msg.app, msg.vertex, nodes, version))
                if rep is not None and dep is not None and src in rep.announced:
                    # told so, it lets its copy and the app go: no longer named a replica in
                    # this node's syncs (seed 86613: a new replica's node, synced ahead of its
                    # first snapshot, passed the app on to the old one, back empty)
                    rep.announced = [n for n in rep.announced if n != src]
                    dep.replica_nodes[msg.vertex] = list(rep.announced)
        elif msg.k == -1 and dep is not None and rep.snapshot is not None:
            self._send(dep, rep, src)  # a replica with no copy asks for it (ask_if_replica)
            return
        if rep is None or dep is None or rep.state is not S.REPLICATING or msg.k != rep.k:
            self.ctx.dropped()  # (a late ack of an earlier snapshot, or of a gone instance)
            return
        if src not in rep.replicas:
            self.ctx.refusal("replica_ack_not_a_replica")
            return
        rep.acked.add(src)
        if not set(rep.replicas) <= rep.acked:
            rep.on(ReplicationEvent.ACKED)
            return
        rep.on(ReplicationEvent.ALL_ACKED)
        self._all_acked(dep, rep)

    def _all_acked(self, dep: AppState, rep: Replication) -> None:
        """Every replica holds the snapshot: its producers may forget what came before it;
        the next one is due after ``snapshot_events`` more events (or by time)."""
        snap = rep.snapshot
        assert snap is not None
        edges = dep.app.edges
        for i, pos in snap.inputs.items():
            producer = dep.placed.get(edges[i].src)
            if producer is not None and producer not in self.ctx.failed:
                self.ctx.send(producer, m.Release(rep.app, i, pos))
        cost = dep.replication.get(rep.vertex)
        if cost is not None:
            cost.snapshots += 1
            cost.acked_at = rep.aligned_at
            cost.acked_processed = snap.processed
            cost.replicas = list(rep.replicas)
        # replicas replaced since (in reach): told they are no longer, so they let their
        # snapshot, and the app, go (issue 24.1: only the nodes that take part hold it)
        routes = self.ctx.routes
        told = {n for n in rep.former if n in routes and n not in rep.replicas}
        rep.former -= told | set(rep.replicas)
        to = told
        view = dep.replica_nodes.get(rep.vertex, [])
        if rep.replicas != rep.announced or view != rep.replicas:  # (none too: a node told
            # it is none is no holder by this view either, nor a copy to restore from -- its
            # producers released what came before this snapshot; fault seed 84069: a host's
            # syncs still named a replica it had told it was none, and gave it the app again.
            # And the view's set is this instance's from its first snapshot held, none
            # included: a replacement restored with no node in reach kept its last
            # instance's replica in its view, and its syncs 5 s later gave that node, told
            # meanwhile it was none, the app again: fault seed 250055)
            before, rep.announced = rep.announced, list(rep.replicas)
            dep.replica_nodes[rep.vertex] = list(rep.announced)
            to = holders(dep) | set(before) | told  # (the app's holders, not everyone)
        msg = m.ReplicaSet(rep.app, rep.vertex, list(rep.replicas), _hosted(dep, rep))
        for node in sorted(to - {self.ctx.id}):
            self.ctx.send(node, msg)
        h = dep.instances.get(rep.vertex)
        if h is not None and h.instance == rep.instance:
            h.snapshot_at = h.processed + dep.app.vertices[rep.vertex].snapshot_events

    def _replace(self, dep: AppState, rep: Replication, node: str) -> None:
        """A replica failed or stays silent: choose another; it gets the snapshot under way,
        or, between snapshots, a new one at once (re-replication)."""
        n = dep.replicas.get(rep.vertex, 0)
        keep = [r for r in rep.replicas if r != node]
        rep.former.add(node)
        rep.replicas = self._choose(dep, rep.vertex, n, keep)
        rep.on(ReplicationEvent.REPLICA_LOST)
        rep.acked &= set(rep.replicas)
        cost = dep.replication.get(rep.vertex)
        if cost is not None:
            cost.rereplicated += 1
        if rep.state is S.REPLICATING:
            for r in rep.replicas:
                if r not in rep.acked and r not in rep.attempts:
                    self._send(dep, rep, r)
            if set(rep.replicas) <= rep.acked:
                rep.on(ReplicationEvent.ALL_ACKED)
                self._all_acked(dep, rep)
        elif rep.state is S.IDLE:
            h = dep.instances.get(rep.vertex)
            if h is not None and h.instance == rep.instance:
                self._due(dep, h, rep)

    def on_peer_failed(self, ev: PeerFailed) -> None:
        """A replica's node failed: replaced. A replacement fetching from it stops waiting
        for it (with no replica left, it starts from its constructor)."""
        self._lose_replicas({ev.node})

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """A replica's node out of reach is not failed (membership may hold it unreachable
        for as long as it is away), but a snapshot cannot reach it nor a replacement fetch
        from it: replaced as a failed one is (it keeps what it holds, unused)."""
        if ev.changed:
            me, routes = self.ctx.id, self.ctx.routes
            self._lose_replicas({n for n in ev.changed if n != me and n not in routes})
        if ev.appeared:  # (a replica short taken at once, not at the next tick)
            for rep in list(self.hosting.values()):
                dep = self.ctx.apps.get(rep.app)
                h = dep.instances.get(rep.vertex) if dep is not None else None
                if dep is None or h is None or h.instance != rep.instance:
                    continue
                if h.started and not h.crashed:
                    self._top_up(dep, h, rep)

    def _lose_replicas(self, nodes: set[str]) -> None:
        if not nodes:
            return
        for rep in list(self.hosting.values()):
            dep = self.ctx.apps.get(rep.app)
            for node in sorted(nodes & set(rep.replicas)):
                if dep is not None:
                    self._replace(dep, rep, node)
        for dep in list(self.ctx.apps.values()):
            # a replacement prepared here may end restores (the handlers change the table)
            for vid, restoring in list(dep.restoring.items()):
                if dep.restoring.get(vid) is restoring and nodes & restoring.fetching:
                    restoring.fetching -= nodes
                    if not restoring.fetching:
                        self.ctx.publish(ReplacementPrepared(dep.app.name, vid))

    # -- a replica: keeps the newest snapshot, acknowledges, serves a replacement --------------
    def on_replicate(self, src: str, msg: m.Replicate) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not dep.replicas.get(msg.vertex) or not _valid(dep, msg):
            self.ctx.refusal("replicate_invalid")
            return
        snap = Snapshot(
            msg.k, msg.state, dict(msg.inputs), dict(msg.outputs), msg.processed, msg.emitted,
            src=src, marks=provenance.from_wire(msg.marks), markgens=dict(msg.markgens),
            version=msg.version,
        )  # fmt: skip
        if msg.rid:  # an answer to a replacement's fetch
            self._fetched(dep, src, msg, snap)
            return
        old = dep.held.get(msg.vertex)
        snap.got_at = self.ctx.now
        snap.src_incarnation = self.ctx.incarnation_of(src, 0)
        # the newest copy is the one its host sent last: its control stream delivers the
        # host's frames in order (an earlier process's dropped once a later one's came). The
        # number orders the snapshots of one instance only: a host numbers each instance's
        # from 1, so a number not above the copy's is no sign of a stale snapshot; one equal
        # to the copy in number and content is the copy sent again (fault seed 314002: a
        # host restarted and restored the vertex, and its new instance's snapshot 1, taken
        # for the old process's sent again, was acknowledged but not kept; the old copy was
        # asked about as one whose maker was gone, of the host by this node's stale view,
        # which said it was none, and this node let the app go, still its host's replica)
        if old is not None and _sent_again(old, snap):
            old.got_at = self.ctx.now
            self.held.stale += 1
        else:
            dep.held[msg.vertex] = snap
            self.held.stored += 1
        self.ctx.send(src, m.ReplicaAck(msg.app, msg.vertex, msg.k))

    def ask_if_replica(self, dep: AppState, now: float, every: float) -> None:
        """This node takes no other part in the app and its copies have not been refreshed
        for ``every``: ask each copy's host, by acknowledging the copy again, whether this
        node is still its replica (one replaced while out of reach, or by an instance it
        was not told of, is told so and lets the copy go: issue 24.1). A host that failed
        is not asked: its replacement may fetch the copy. A copy whose maker is gone and
        whose vertex this view has lost is not waited on either: this node looks up where
        the vertex runs (once a round for all such copies), and asks that host next."""
        me, failed, app = self.ctx.id, self.ctx.failed, dep.app.name
        looked = False
        for vid, snap in dep.held.items():
            src = snap.src
            if now - snap.asked_at < every:
                continue
            gone = src in failed or self.ctx.incarnation_of(src, 0) > snap.src_incarnation
            lost = gone and vid in dep.lost(failed)
            if now - snap.got_at < every:
                if not lost:
                    continue  # (refreshed lately; a copy whose maker is gone is not)
            elif src and src != me and src not in failed:
                snap.asked_at = now
                self.ctx.send(src, m.ReplicaAck(app, vid, snap.k))
            # the instance that made the copy is gone (its node failed, or restarted: then
            # it does not answer for it) and the vertex runs on elsewhere: its host by this
            # node's view says whether this node is its replica (fault seed 122799: restored
            # by a node cut off as the copy was made, which never named this one, the
            # vertex's new host was not asked and the copy, and the app, held for ever)
            host = dep.placed.get(vid, "")
            runs = host not in ("", me, src) and host not in failed and vid not in dep.vanished
            if gone and runs:
                snap.asked_at = now
                self.ctx.send(host, m.ReplicaAck(app, vid, snap.k))
            elif lost and not looked:
                # lost by this view, which nobody keeps up to date (this node hosts none of
                # the app): its replacement's host tells its replicas their set, but only
                # those the restore's coordinator knew of, and nobody tells this node of the
                # restore. So it looks up where the vertex runs, and asks that host next
                # (fault seed 267786: named a replica across a cut, the copy's maker reset
                # at the heal, the vertex restored elsewhere from the replica before; it
                # asked only the maker's node, which does not answer for an instance gone)
                snap.asked_at = now
                looked = True
                self.ctx.publish(PlacementStale(app, wide=False, sync=True))
        # named a replica with no copy here (reset, restarted, or the app came with a sync):
        # the host by this node's view sends one, or says this node is none
        for vid, nodes in dep.replica_nodes.items():
            host = dep.placed.get(vid, "")
            if me not in nodes or vid in dep.held or not host or host == me or host in failed:
                continue
            if now - self._asked.get((app, vid), -every) >= every:
                self._asked[(app, vid)] = now
                self.ctx.send(host, m.ReplicaAck(app, vid, -1))
        if len(self._asked) > 4096:  # (bounded: the oldest go)
            for key in sorted(self._asked, key=self._asked.__getitem__)[:2048]:
                del self._asked[key]

    def on_fetch(self, src: str, msg: m.FetchReplica) -> None:
        """A replacement asks for the snapshot held here."""
        dep = self.ctx.apps.get(msg.app)
        if dep is not None and msg.vertex not in dep.replicas:
            self.ctx.refusal("fetch_replica_unknown")
            return
        # (a node that let the app go holds no copy: it says so, and the replacement goes
        # on with the others' answers instead of waiting for it)
        snap = dep.held.get(msg.vertex) if dep is not None else None
        self.held.served += 1
        if snap is None:
            reply = m.Replicate(msg.app, msg.vertex, -1, b"", {}, {}, rid=msg.rid)
        else:
            reply = _replicate(msg.app, msg.vertex, snap, msg.rid)
            snap.fetched_by = src
        self.ctx.send(src, reply)

    def on_replica_set(self, src: str, msg: m.ReplicaSet) -> None:
        """Where a vertex's replicas are now; a node no longer among them forgets its copy."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.vertex not in dep.replicas or len(msg.nodes) > 2:
            self.ctx.refusal("replica_set_invalid")
            return
        copy = dep.held.get(msg.vertex)
        settles = copy is None or (
            src in (copy.src, self._host_of(dep, msg.vertex, copy), self.ctx.id)
            or self._later_host(dep, src, msg, copy)
        )
        if copy is not None and not settles:
            # a copy is dropped on the word of the instance that made it, or of the vertex's
            # host: a node that once hosted it answers for itself, "none" (seed 87093: a
            # replica asked the vertex's host before a move it heard of late, and dropped the
            # copy the new host had just made; no node held the vertex's state). The node
            # whose restore fetched the copy is the vertex's host by that restore, whatever
            # this view says (fault seed 162928: a replica whose view still placed the vertex
            # on its failed host refused the new host's set, and held the app for ever) --
            # but only while this view has the vertex lost, as a restore needs: a member that
            # fetched the copy of a vertex running on a live host made any replica drop it.
            # So is the host by a later move than this view's and the copy's (its set says
            # at which): a node hosting nothing of the app is not told of moves, and the new
            # host's set was refused on its old view (control loss seed 731: the replica of a
            # vertex moved in the quiet phase held the copy, and the app, until it asked the
            # old host a second later, then held the app past the quiet phase)
            if src != copy.fetched_by:
                self.ctx.refusal("replica_set_not_from_host")
                return
            if msg.vertex not in dep.lost(self.ctx.failed):
                self.ctx.refusal("replica_set_by_fetcher_of_a_vertex_not_lost")
                return
        dep.replica_nodes[msg.vertex] = list(msg.nodes)
        if self.ctx.id not in msg.nodes and src != self.ctx.id:
            dep.held.pop(msg.vertex, None)

    def _host_of(self, dep: AppState, vertex: str, copy: Snapshot) -> str:
        """The vertex's host by this view, whose word settles ``copy`` -- none if the copy
        was made at a later move than the view knows of (a node hosting nothing of the app
        is not told of moves): that host ran an instance before the copy's, and its set
        ("none", as it answers for itself) says nothing of the copy (fault seed 329996: a
        replica's ask of the counter's old host, held by a cut, was answered after the heal,
        once the new host's first snapshot had replaced the old host's copy here; the
        replica let that copy, and the app, go, and the new host named it to the end)."""
        if copy.version > dep.versions.get(vertex, 0):
            return ""
        return dep.placed.get(vertex, "")

    def _later_host(self, dep: AppState, src: str, msg: m.ReplicaSet, copy: Snapshot) -> bool:
        """``src`` runs the vertex at a later move than this view and the copy's host knew of
        (by its set's version): a move this node, hosting nothing of the app, was not told of.
        With operator keys, only where ``src`` may tell this view so (``placement.may_tell``:
        its host here failed or the vertex vanished), as a ``Moved`` from it would be taken."""
        if msg.version <= max(dep.versions.get(msg.vertex, 0), copy.version):
            return False
        failed = self.ctx.failed
        return not self.ctx.authority.signed or placement.may_tell(dep, msg.vertex, src, failed)

    # -- a producer: forgets what a replica no longer needs ------------------------------------
    def on_release(self, msg: m.Release) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges) or msg.upto < 0:
            self.ctx.refusal("release_unknown_edge")
            return
        out = dep.out.get(msg.edge)
        if out is not None:
            out.release(REPLICA_OWNER, msg.upto)
        fresh = dep.fresh_from.get(msg.edge)
        if fresh is not None and msg.upto > fresh:  # the replicas counted new events
            del dep.fresh_from[msg.edge]

    def on_replay(self, msg: m.Replay) -> None:
        """A replacement starts from a replica's snapshot: what it counted ends at ``start``;
        send again from there (acknowledged only so far, with the snapshot's positions)."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("replay_unknown_edge")
            return
        out = dep.out.get(msg.edge)
        if out is None or not out.base <= msg.start <= out.acked:
            self.ctx.refusal("replay_not_retained")  # (the replacement waits for what comes)
            return
        if msg.start < out.acked:
            out.rewind(msg.start)
            out.positions = dict(msg.positions)
        out.sent = out.acked  # what it holds goes (again), a window at a time
        out.waiting_since = self.ctx.now
        self.dp.sf.drain(dep, msg.edge)

    # -- a replacement: fetches the newest snapshot before it runs ------------------------------
    def on_replacement_prepared(self, ev: ReplacementPrepared) -> None:
        """A replacement of a replicated vertex started here: ask its replicas for its state
        (or take the copy held here); it runs once one answered, or none is left to ask."""
        dep = self.ctx.apps.get(ev.app)
        restoring = dep.restoring.get(ev.vertex) if dep is not None else None
        if dep is None or restoring is None or not dep.replicas.get(ev.vertex):
            return
        if restoring.fetched and not restoring.fetching:
            return
        if not restoring.fetched:
            restoring.fetched = True
            held = dep.held.get(ev.vertex)
            if held is not None:
                restoring.replica = held
                return
            me, failed = self.ctx.id, self.ctx.failed
            nodes = dep.replica_nodes.get(ev.vertex, [])
            restoring.fetching = {n for n in nodes if n != me and n not in failed}
        for node in sorted(restoring.fetching):  # (asked again on a restore's retry)
            self.ctx.send(node, m.FetchReplica(ev.app, ev.vertex, restoring.rid))

    def _fetched(self, dep: AppState, src: str, msg: m.Replicate, snap: Snapshot) -> None:
        restoring = dep.restoring.get(msg.vertex)
        if restoring is None or restoring.rid != msg.rid or src not in restoring.fetching:
            self.ctx.dropped()  # (answered after another replica did)
            return
        restoring.fetching.discard(src)
        if msg.k >= 0:
            restoring.replica = snap
            restoring.fetching.clear()
        if not restoring.fetching:  # it may run now (once every end has resumed it)
            self.ctx.publish(ReplacementPrepared(dep.app.name, msg.vertex))


def _valid(dep: AppState, msg: m.Replicate) -> bool:
    """A snapshot's positions name the vertex's own input and output edges."""
    edges = dep.app.edges
    n = len(edges)
    ins = all(0 <= i < n and edges[i].dst == msg.vertex and p >= 0 for i, p in msg.inputs.items())
    outs = all(0 <= o < n and edges[o].src == msg.vertex for o in msg.outputs)
    return ins and outs


def _sent_again(copy: Snapshot, snap: Snapshot) -> bool:
    """``snap`` is the snapshot ``copy`` is, sent again by its host (same number, same
    content): the number alone starts again with each instance its host runs."""
    return (copy.src, copy.k, copy.state, copy.inputs, copy.outputs) == (
        snap.src, snap.k, snap.state, snap.inputs, snap.outputs,
    ) and (copy.processed, copy.emitted) == (snap.processed, snap.emitted)  # fmt: skip


def _replicate(
    app: str, vertex: str, snap: Snapshot, rid: int = 0, version: int = -1
) -> m.Replicate:
    """``snap`` on the wire: to a replica (``rid`` 0), or to a replacement that fetched it;
    ``version``: its host's placement version of the vertex (the copy's own if -1)."""
    return m.Replicate(
        app, vertex, snap.k, snap.state, snap.inputs, snap.outputs, snap.processed,
        snap.emitted, rid, provenance.to_wire(snap.marks), snap.markgens,
        snap.version if version < 0 else version,
    )  # fmt: skip


def _hosted(dep: AppState, rep: Replication) -> int:
    """The placement version of ``rep``'s vertex here while this node runs ``rep``'s
    instance (what its replica sets and snapshots say), else -1: it answers for itself."""
    h = dep.instances.get(rep.vertex)
    if h is None or h.instance != rep.instance or rep.vertex in dep.vanished:
        return -1
    return dep.versions.get(rep.vertex, 0)


def usable(dep: AppState, vertex: str, restoring: Restoring) -> Snapshot | None:
    """The snapshot a replacement starts from, if it can: every input's producer resumed it
    and still retains the events from the snapshot's position on (a producer that died too,
    or lost its retention, cannot replay them), and no output went further down than the
    snapshot's position to a consumer that is being replaced too (nothing would drop what it
    makes again). Otherwise its constructor's state, as without replicas."""
    snap = restoring.replica
    if snap is None:
        return None
    for i, e in enumerate(dep.app.edges):
        if e.dst == vertex:
            start = restoring.retained.get(i)
            if start is None or start > snap.inputs.get(i, 0):
                return None
            if i in restoring.fresh:  # its producer numbers the edge anew (lost with its
                return None  # own producers): the snapshot's position is of a numbering
                # that is gone, and taken as its own the new events were dropped (6390)
            if snap.inputs.get(i, 0) > restoring.remade.get(i, snap.inputs.get(i, 0)):
                return None  # a merge restored since made those numbers anew (44712)
        elif e.src == vertex and i not in restoring.consumer_start:
            # its consumer is being replaced too: what the snapshot's output position is
            # behind what went further down would reach it as new (no end left to drop it)
            acked = snap.outputs.get(i, (0, []))[0]
            if restoring.positions.get(i, acked) > acked:
                return None
    return snap
