"""What a node holds of each app (:class:`AppState`) and of each vertex instance it hosts.

Every component of the node core reads and writes these records through the app they belong
to; none keeps a second copy. The data plane owns the instances and channels, the procedures
their own bookkeeping fields (marked below by who uses them).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, Self, TypeVar, cast

import msgspec

from mso.model.app import App, Vertex
from mso.planning.placement import Hop, Layout
from mso.protocol import messages as m
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.procedures.instance import InstanceLife
from mso.protocol.provenance import CatchUp, Head, Held, Marks

V = TypeVar("V")
# a frame come before its consumer runs: (seq, events, when they entered their chain, the
# generations the frame named, ``Data.gens``: None where it said none)
Stashed = tuple[int, list[bytes], float, dict[int, int] | None]
BUSY_AFTER_S = 1.0  # an instance working on one effect this long is reported busy ...
HUNG_AFTER_S = 10.0  # ... and this long, hung (status only: it never takes the node down)


@dataclass
class Snapshot:
    """A replicated vertex's state, aligned with its channels: taken when it had processed
    exactly ``inputs`` (edge -> events) and produced ``outputs`` (edge -> (acked, the events
    not yet acknowledged)). Held by its replicas; a replacement starts from it."""

    k: int
    state: bytes
    inputs: dict[int, int]
    outputs: dict[int, tuple[int, list[bytes]]]
    processed: int = 0
    emitted: int = 0
    src: str = ""  # the host it came from
    # a forwarder's: what it had processed of the merge's inputs (mso.protocol.provenance)
    marks: Marks | None = None
    markgens: dict[int, int] = field(default_factory=dict)  # the generations they are of
    # at a replica: when its host last sent it (or this one again), and when this node last
    # asked that host whether it is still a replica (issue 24.1: a replica replaced unheard
    # would hold the snapshot, and the app, for ever)
    got_at: float = 0.0
    asked_at: float = 0.0
    src_incarnation: int = 0  # the incarnation of ``src`` it came from, as this node knew it
    # the node whose restore of the vertex fetched it (``m.FetchReplica``): its host by that
    # restore, whose word on the replica set counts though this view places it elsewhere
    fetched_by: str = ""
    # the vertex's placement version at the host that took it (``m.Replicate.version``)
    version: int = 0

    @property
    def size(self) -> int:
        """Bytes it takes on the wire, roughly: the state and the unacknowledged output."""
        return len(self.state) + sum(len(e) for _, evs in self.outputs.values() for e in evs)


class SnapshotMark:
    """In an instance's pending queue: take a replication snapshot once everything fed
    before it has been processed (aligned, as a relocation's marker is)."""


SNAPSHOT_MARK = SnapshotMark()


@dataclass
class ReplicationCost:
    """What replicating one vertex hosted here costs and how far its replicas lag (status)."""

    replicas: list[str] = field(default_factory=list)
    snapshots: int = 0  # acknowledged by every replica
    bytes_sent: int = 0  # snapshot bytes sent, to every replica
    last_bytes: int = 0  # of the newest snapshot
    interval_s: float = 0.0  # between the last two snapshots taken
    since: float = 0.0  # when this host started replicating it
    acked_at: float | None = None  # when the newest snapshot was taken (acknowledged since)
    acked_processed: int = 0  # events it had processed then
    resent: int = 0  # snapshots sent again (a replica did not acknowledge in time)
    rereplicated: int = 0  # replicas replaced (failed or silent)


@dataclass
class Restoring:
    """A replacement instance waiting to hear where each of its surviving edges stands (and,
    for a replicated vertex, for its state from a replica)."""

    rid: int
    coordinator: str
    pending: set[tuple[int, bool]]
    positions: dict[int, int] = field(default_factory=dict)  # output -> from producers' acks
    gens: dict[int, int] = field(default_factory=dict)  # their numberings' generations (not 0)
    consumer_start: dict[int, int] = field(default_factory=dict)  # output -> consumer expects
    consumer_gen: dict[int, int] = field(default_factory=dict)  # output -> of that numbering
    # output -> the consumer's own output positions at that start, where it knew them exactly
    consumer_positions: dict[int, dict[int, int]] = field(default_factory=dict)
    consumer_gens: dict[int, dict[int, int]] = field(default_factory=dict)  # (their gens)
    # output -> what its consumer has of a merge's inputs (mso.protocol.provenance)
    consumer_marks: dict[int, Marks] = field(default_factory=dict)
    consumer_markgens: dict[int, dict[int, int]] = field(default_factory=dict)  # (their gens)
    fresh: set[int] = field(default_factory=set)  # inputs their producer numbers anew
    new: set[int] = field(default_factory=set)  # inputs whose events are all new (Resume.new)
    # a forwarder's: the merge's inputs its restored producer (the merge) numbers anew
    renumbered: set[int] = field(default_factory=set)
    retained: dict[int, int] = field(default_factory=dict)  # input -> first event replayed
    remade: dict[int, int] = field(default_factory=dict)  # input -> a merge's first remade
    unheld: set[int] = field(default_factory=set)  # outputs whose consumer's start is a guess
    resumed: set[int] = field(default_factory=set)  # inputs whose producer survived
    replica: Snapshot | None = None  # the state it starts from (None: from its constructor)
    fetching: set[str] = field(default_factory=set)  # replicas asked, none answered yet
    fetched: bool = False  # the replicas were asked (or there are none)


@dataclass
class Crashes:
    """One vertex's crashes at this node (its child process died unasked): how many, the
    last one's reason, when the recent ones were (the restart budget), restores done."""

    count: int = 0
    restarts: int = 0
    last: str = ""
    times: list[float] = field(default_factory=list)
    restoring: int | None = None  # the in-place restore under way (its procedure id)
    gave_up: str = ""  # why it stays crashed (its restart budget is spent)


class EdgeStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One edge's ends at this node: what its producer here sent and holds, its consumer here
    got, and what the edge's bound and QoS gave up (counted, never silent)."""

    sent: int  # events numbered (the next sequence number)
    delivered: int
    duplicates: int
    in_flight: int  # unacknowledged, sent or waiting
    events_per_s: float
    waiting: int = 0  # not sent yet: the consumer is out of reach, or a backlog drains
    held_bytes: int = 0  # bytes the producer keeps (memory and spill)
    spilled_bytes: int = 0  # of which in the spill store
    dropped: int = 0  # given up past the bound (overflow policy), or best effort unreachable
    superseded: int = 0  # keep_last: replaced by newer ones (not lost)
    expired: int = 0  # lifespan
    lost: int = 0  # best effort: lost on the way, not sent again
    resent: int = 0  # events sent more than once (go-back-N, an outage, a replay)
    resent_bytes: int = 0
    deadline_missed: int = 0
    late: bool = False  # nothing arrived within deadline_ms


class VertexStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One vertex instance at this node: its state, counters and crashes; ``stats`` is
    whatever its code's ``stats()`` returned (free-form)."""

    kind: str
    state: str
    busy_s: float
    queued: int
    processed: int
    emitted: int
    calls: int
    ended: bool  # its stream is over (a source's, or every input's)
    errors: int
    cpu_s: float
    last_error: str
    stats: Any
    crashes: int
    restarts: int
    last_crash: str
    not_restarted: str


class ReplicationStatus(msgspec.Struct, frozen=True, kw_only=True):
    """A replicated vertex at its host: where its replicas are, what it costs, how far they
    lag (events processed since, and age of, the newest snapshot every replica holds)."""

    replicas: list[str]
    snapshots: int
    bytes_per_snapshot: int
    bytes_per_s: float
    interval_s: float
    lag_events: int
    lag_s: float | None
    resent: int
    rereplicated: int


class AppStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One app as this node holds and runs it (chains and edges by name)."""

    running: bool
    parked: dict[str, str]  # chain -> why it cannot run
    recoveries: list[dict[str, Any]]  # what each recovery did (mso.protocol.procedures.remap)
    given_up: dict[str, int]  # edge -> events dropped, expired or lost by its bound and QoS
    chain_delay_ms: dict[str, float]
    slo_ms: float | None
    origin: str
    placement: dict[str, str]
    chains: list[list[str]]
    vertices: dict[str, VertexStatus]
    edges: dict[str, EdgeStatus]
    # each vertex placed by capability: the nodes that qualify, best first (§3.3)
    capable: dict[str, list[str]] = msgspec.field(default_factory=dict)
    replication: dict[str, ReplicationStatus] = {}


@dataclass
class HostedInstance:
    """The core's record of one vertex instance whose code runs in the executor: what it was
    given, what it reported back, and where a source stands in its schedule."""

    instance: int
    vertex: Vertex
    kind: str
    started: bool = False
    mode: str = ""  # a source's: timer (rated) or loop (paced by credit)
    processed: int = 0
    emitted: int = 0  # events produced (not calls)
    calls: int = 0  # times a source was called
    errors: int = 0
    cpu_s: float = 0.0
    bytes_in: int = 0  # encoded size of the events it consumed and produced
    bytes_out: int = 0
    last_error: str = ""
    stats: Any = None
    state_size: int = 0
    # effects submitted whose results have not come back, events among them, since when
    jobs: int = 0
    queued: int = 0
    busy_since: float | None = None
    # delivered, not yet fed: (edge, events, when they entered their chain) or a marker
    pending: deque[tuple[int, list[bytes], float] | m.Marker | SnapshotMark] = field(
        default_factory=deque
    )
    snapshot_at: int = 0  # a replicated vertex: snapshot once ``processed`` reaches it (0: no)
    # a rated source: schedule origin and calls asked for; a loop source: credit granted
    t0: float = 0.0
    asked: int = 0
    credit: int = 0
    ended: bool = False
    handing_over: m.Marker | None = None  # snapshot asked for this relocation
    crashed: str = ""  # its child process died unasked: how (no results come any more)
    # the replacement of a crashed instance: events still to feed one at a time (the replay),
    # so a crash on one event does not take the results of those before it in its batch along
    one_by_one: int = 0
    # a replacement started from a replica's snapshot: its output is numbered from the
    # snapshot's positions, the lost instance's own, never a guess to correct by a producer's
    # Resume (``Restorer.anchor``)
    from_snapshot: bool = False
    # a forwarder: the headers of each batch fed, in order (mso.protocol.provenance)
    heads: deque[list[Head]] = field(default_factory=deque)
    life: InstanceLife = field(init=False)  # its state at this host, by the table

    def __post_init__(self) -> None:
        self.life = InstanceLife(self.vertex.id)

    @property
    def rate(self) -> float:
        v = self.vertex
        if v.rate:
            return v.rate
        return 1.0 if v.code is None else 0.0  # a stand-in ticks once a second

    def state(self, now: float) -> str:
        if self.crashed:
            return "crashed"
        if not self.started:
            return "starting"
        busy = now - self.busy_since if self.busy_since is not None else 0.0
        return "hung" if busy >= HUNG_AFTER_S else "busy" if busy >= BUSY_AFTER_S else "running"

    def status(self, now: float, crashes: Crashes | None) -> VertexStatus:
        """This instance for status, with its vertex's crashes here (kept apart from it: they
        outlive the instance)."""
        rec = crashes or Crashes()
        return VertexStatus(
            kind=self.kind,
            state=self.state(now),
            busy_s=round(now - self.busy_since, 3) if self.busy_since else 0.0,
            queued=self.queued + sum(len(p[1]) for p in self.pending if isinstance(p, tuple)),
            processed=self.processed,
            emitted=self.emitted,
            calls=self.calls,
            ended=self.ended,
            errors=self.errors,
            cpu_s=self.cpu_s,
            last_error=self.last_error,
            stats=self.stats,
            crashes=rec.count,
            restarts=rec.restarts,
            last_crash=rec.last,
            not_restarted=rec.gave_up,
        )


class Engaged:
    """Which apps a node takes part in: an app's :class:`Hosted`, :class:`Placed` and
    :class:`Vanished` put its name in ``apps`` when they gain or change an entry (the data
    plane when it measures a chain's delay), and :class:`Apps` points every app it holds at
    its own set. A beat and a monitor period read these apps only, not every app held (at
    1,000 nodes a node holds 50 apps and runs part of 0-2: walking all 50 on every beat and
    every monitor period was a third of the simulator's CPU)."""

    __slots__ = ("apps", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self.apps: set[str] = set()  # an app no node table holds yet: its own set

    def note(self) -> None:
        self.apps.add(self.name)


class _Noting(dict[str, V]):
    """A dict that notes its app engaged whenever it gains (or changes) an entry."""

    __slots__ = ("engaged",)

    def __init__(self, engaged: Engaged, items: dict[str, V] | None = None) -> None:
        super().__init__(items or {})
        self.engaged = engaged
        if self:
            engaged.note()

    def __setitem__(self, key: str, value: V) -> None:
        super().__setitem__(key, value)
        self.engaged.note()

    def setdefault(self, key: str, default: V) -> V:
        self.engaged.note()
        return super().setdefault(key, default)

    def update(self, *args: Any, **kwargs: V) -> None:
        super().update(*args, **kwargs)
        self.engaged.note()

    def __ior__(self, other: Any) -> Self:  # type: ignore[override,misc]
        self.update(other)
        return self


class Hosted(_Noting["HostedInstance"]):
    """An app's instances on this node (vertex -> instance)."""

    __slots__ = ()


class Placed(_Noting[str]):
    """Where this node holds each vertex of an app to run (vertex -> node): any change may
    place one here (changed in place only, never assigned anew). With it, the nodes whose
    instance of a vertex a restore replaced (:meth:`restored`), until the view places the
    vertex there again: such an instance may run on, cut off, until its node resets, and
    its frames are numbered in its own run, not its replacement's (fault seed 162674)."""

    __slots__ = ("gone",)

    def __init__(self, engaged: Engaged, items: dict[str, str] | None = None) -> None:
        super().__init__(engaged, items)
        self.gone: dict[str, set[str]] | None = None  # (made when needed: most hold none)

    def __setitem__(self, key: str, value: str) -> None:
        super().__setitem__(key, value)
        if self.gone is not None and key in self.gone:
            self._back(key, value)

    def update(self, *args: Any, **kwargs: str) -> None:
        super().update(*args, **kwargs)
        if self.gone is not None:
            for key in [k for k in self.gone if k in self]:
                self._back(key, self[key])

    def _back(self, vertex: str, node: str) -> None:
        """The view places ``vertex`` on ``node``: an instance there is not one replaced."""
        assert self.gone is not None
        nodes = self.gone[vertex]
        nodes.discard(node)
        if not nodes:
            del self.gone[vertex]
        if not self.gone:
            self.gone = None

    def restored(self, vertex: str, node: str) -> None:
        """A restore's word: ``vertex`` runs on ``node`` now, replacing the instance where
        this view held it (if elsewhere)."""
        old = self.get(vertex)
        if old is not None and old != node:
            if self.gone is None:
                self.gone = {}
            self.gone.setdefault(vertex, set()).add(old)
        self[vertex] = node

    def replaced(self, vertex: str, node: str) -> bool:
        """Does this view hold ``node``'s instance of ``vertex`` replaced by a restore? (A
        node it neither places the vertex on nor knows replaced -- a move's old host sending
        its last frames before the switch -- is not.)"""
        return self.gone is not None and node in self.gone.get(vertex, ())


class Vanished(set[str]):
    """An app's vertices whose instances went with a node's old incarnation: a set that notes
    its app engaged whenever it gains one (assigned only in place: :meth:`replace`)."""

    __slots__ = ("engaged",)

    def __init__(self, engaged: Engaged) -> None:
        super().__init__()
        self.engaged = engaged

    def add(self, vertex: str) -> None:
        super().add(vertex)
        self.engaged.note()

    def update(self, *others: Iterable[str]) -> None:
        super().update(*others)
        self.engaged.note()

    def symmetric_difference_update(self, other: Iterable[str]) -> None:
        super().symmetric_difference_update(other)
        self.engaged.note()

    def __ior__(self, other: AbstractSet[str]) -> Self:  # type: ignore[override,misc]
        self.update(other)
        return self

    def __ixor__(self, other: AbstractSet[str]) -> Self:  # type: ignore[override,misc]
        self.symmetric_difference_update(other)
        return self

    def replace(self, vertices: Iterable[str]) -> None:
        self.clear()
        self.update(vertices)


class Apps(dict[str, "AppState"]):
    """A node's apps (name -> what it holds of each), and ``engaged``: the names of those it
    may take part in -- instances, vanished vertices or chain delays measured here, or a
    vertex placed here (a superset: an app that lost them stays until :meth:`engaged_apps`
    looks)."""

    __slots__ = ("engaged", "node")

    def __init__(self, node: str = "") -> None:
        super().__init__()
        self.node = node  # this node: an app placing a vertex here is engaged
        self.engaged: set[str] = set()

    def __setitem__(self, name: str, dep: AppState) -> None:
        super().__setitem__(name, dep)
        dep.engaged.apps = self.engaged
        if self._engaged(dep):
            self.engaged.add(name)

    def _engaged(self, dep: AppState) -> bool:
        return bool(dep.instances or dep.vanished or dep.delays or self.node in dep.placed.values())

    def engaged_apps(self) -> list[AppState]:
        """The apps this node takes part in, in no particular order; the others are
        forgotten from ``engaged``."""
        out = []
        for name in list(self.engaged):
            dep = self.get(name)
            if dep is not None and self._engaged(dep):
                out.append(dep)
            else:
                self.engaged.discard(name)
        return out


def lazy(make: Callable[[], object]) -> Any:
    """An :class:`AppState` table made the first time it is read: every node holds every app
    but takes part in few, and about forty empty tables per app held were two thirds of an
    idle node's memory for it (``bench/node_memory.py``)."""
    return field(init=False, repr=False, compare=False, metadata={"lazy": make})


@dataclass(slots=True)
class AppState:
    """One app as this node holds it: the shared layout, where each vertex is placed, the
    instances that run here and their channels, and each procedure's per-app bookkeeping."""

    app: App
    layout: Layout
    origin: str
    placed: dict[str, str]
    # vertex -> how many moves of it this node knows of: news of an older move loses
    # (:mod:`mso.protocol.procedures.placement`)
    versions: dict[str, int] = lazy(dict)
    # the losses this node last looked the placement up for (:meth:`losses`; it hosts no
    # part of the app, so its view is not kept up to date): a recovery it would coordinate
    # may act on the answers until they change, and no new lookup is started before
    looked_up: tuple[frozenset[str], frozenset[str]] | None = None
    # the view is the one this node's last process kept in its store (mso.protocol.kept),
    # heard from no other node since: the first sync from another node may overrule it
    stored: bool = False
    # while ``stored``: the incarnation its last process knew of each node the view places a
    # vertex on (the record's): a sync of this view names it for a node this process has not
    # heard yet, as its placement there is that incarnation's (fault seed 265408)
    kept_incarnations: dict[str, int] = lazy(dict)
    placed_chains: set[int] = lazy(set)
    started_chains: set[int] = lazy(set)
    probes: dict[int, dict[int, list[Hop]]] = lazy(dict)
    probes_expected: dict[int, int] = lazy(dict)
    parts_pending: dict[int, set[str]] = lazy(dict)
    instances: Hosted = field(init=False)
    out: dict[int, OutChannel] = lazy(dict)
    inc: dict[int, InChannel] = lazy(dict)
    gates: dict[str, AckGate] = lazy(dict)  # vertex -> chained acks
    # a merge's replacement: vertex -> output -> what that consumer has (sent no more)
    marks: dict[str, dict[int, Marks]] = lazy(dict)
    # a stamped replacement: vertex -> output -> input -> (what that consumer had, the
    # generation it names): held by generation, also where ``marks`` let one go as of a
    # numbering gone (an input numbered anew may come back to it: fault seed 150917)
    aside: dict[str, dict[int, Held]] = lazy(dict)
    # a forwarder's replacement: vertex -> its input up to its consumer's marks first
    catch_up: dict[str, CatchUp] = lazy(dict)
    decoders: dict[int, msgspec.msgpack.Decoder[Any]] = lazy(dict)
    running: bool = False
    epoch: int = 0
    awaiting: dict[str, HostedInstance] = lazy(dict)  # prepared, awaiting handover
    building: dict[int, tuple[str, set[str]]] = lazy(dict)  # chain -> (asker,
    # vertices still starting)
    preparing: dict[str, tuple[int, str, bool]] = lazy(dict)  # vertex -> (rid,
    # coordinator, restore) until its instance has started
    # edge -> (seq, events, when they entered their chain, the generations their frame
    # named: Data.gens): kept until the handover
    stash: dict[int, list[Stashed]] = lazy(dict)
    markers: dict[str, set[int]] = lazy(dict)  # vertex -> edges marked
    blocked_sources: set[str] = lazy(set)
    started_at: float = 0.0
    parked: dict[int, str] = lazy(dict)  # chain -> why it cannot run
    recovering: int | None = None  # the remap recovering from a failure, at its coordinator
    restoring: dict[str, Restoring] = lazy(dict)  # replacements awaiting
    recoveries: list[dict[str, Any]] = lazy(list)  # what was done, bounded
    # vertices whose instances went with a node that has since rejoined: restored like lost ones
    vanished: Vanished = field(init=False)
    handed: dict[str, str] = lazy(dict)  # vertex -> where this node handed it
    # vertices held lost on news of an instance gone with its node's old incarnation that
    # displaced a placement on a live node, while a lookup asks that node (it may run them
    # still): a recovery waits for the answers (:func:`placement.on_moved`)
    checking: set[str] = lazy(set)
    # with operator keys, a node that learnt the app from a sync: the unpinned vertices it
    # places on its senders' word, not yet corroborated (vertex -> node -> senders saying so)
    hearsay: dict[str, dict[str, set[str]]] = lazy(dict)
    document: str = ""  # the app file as deployed, for a node that rejoins
    crashes: dict[str, Crashes] = lazy(dict)  # vertex -> its crashes here
    # crashed, not in ``instances``
    crashed: dict[str, HostedInstance] = lazy(dict)
    delays: dict[int, float] = lazy(dict)  # at a tail's node: chain -> ms
    moved: dict[str, tuple[float, str]] = lazy(dict)  # vertex -> (when, from)
    # vertex -> when this node last learnt it moved (a Moved, a sync): a chain end's next
    # move of it waits its interval from then (mso.protocol.warrant)
    moved_at: dict[str, float] = lazy(dict)
    placed_at: dict[int, float] = lazy(dict)  # chain -> when last (re)mapped
    route_changed: dict[int, float] = lazy(dict)  # chain -> last route change
    chain_delay: dict[int, tuple[float, float]] = lazy(dict)  # at a head's
    # at the origin only
    built: set[int] = lazy(set)
    # each vertex placed by capability: the nodes that qualify, best first (§3.3)
    capable: dict[str, list[str]] = field(default_factory=dict)
    # chain replication: vertex -> replicas kept; at its host, what it costs; at a replica,
    # the snapshot held; everywhere, where its replicas are (the host's broadcast)
    replicas: dict[str, int] = field(init=False)
    replication: dict[str, ReplicationCost] = lazy(dict)
    held: dict[str, Snapshot] = lazy(dict)
    replica_nodes: dict[str, list[str]] = lazy(dict)
    # at a producer's node: edge -> the first event that is new, made by a producer restored
    # without its predecessor's history (a source, a state restarted, or one fed by such):
    # the events a replica of its consumer counted are not among them, so they cannot replay
    # them; forgotten once the consumer's replicas hold a snapshot past it (``m.Release``)
    fresh_from: dict[int, int] = lazy(dict)
    # per restored merge: its inputs numbered anew at its restore (told to its forwarder)
    renumbered: dict[str, set[int]] = lazy(dict)
    # at a producer's node: edge -> the move (rid) it last switched that edge for; a Switch
    # the move's coordinator sends again (one lost to a producer out of reach) is not taken twice
    switched: dict[int, int] = lazy(dict)
    # at a producer's node: edge -> the node its last switch's marker went to, and the marker
    # (sent again with the move's Switch sent again: markers go unsequenced, as data does,
    # and one lost left the move waiting for it the switch's 60 s; control loss seed 134)
    marked_to: dict[int, tuple[str, m.Marker]] = lazy(dict)

    engaged: Engaged = field(init=False, repr=False, compare=False)

    @property
    def view(self) -> Placed:
        """``placed`` as the table it is made (given as a dict): with the nodes whose
        instance of a vertex a restore replaced (:meth:`Placed.restored`)."""
        return cast(Placed, self.placed)

    @property
    def out_edges(self) -> dict[str, list[int]]:
        """Vertex -> its output edges' indices: the layout's (the same at every node, shared
        where the layout is; it was a table per app per node)."""
        return self.layout.out_edges

    @property
    def in_edges(self) -> dict[str, list[int]]:
        """Vertex -> its input edges' indices: the layout's, as :attr:`out_edges`."""
        return self.layout.in_edges

    if not TYPE_CHECKING:  # (mypy keeps checking the attributes' names and types)

        def __getattr__(self, name: str) -> Any:
            """A lazy table not made yet (an unset slot): made now, and kept."""
            make = _LAZY.get(name)
            if make is None:
                raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
            value = make()
            setattr(self, name, value)
            return value

    def __post_init__(self) -> None:
        self.replicas = self.layout.replicas()
        self.engaged = Engaged(self.app.name)
        self.placed = Placed(self.engaged, self.placed)
        self.instances = Hosted(self.engaged)
        self.vanished = Vanished(self.engaged)

    def status(self, now: float) -> AppStatus:
        """This app as this node holds and runs it: placement, chains, parked chains and
        recoveries, each edge with an end here, each instance here (crashed ones too)."""
        up = max(now - self.started_at, 1e-9) if self.running else 0.0
        edges = {}
        given_up: dict[str, int] = {}
        for i, e in enumerate(self.app.edges):
            if i in self.out or i in self.inc:
                inc = self.inc.get(i)
                out = self.out.get(i)
                sent = out.next_seq if out else 0
                name = f"{e.src}->{e.dst}"
                edges[name] = EdgeStatus(
                    sent=sent,
                    delivered=inc.expected if inc else 0,
                    duplicates=inc.duplicates if inc else 0,
                    in_flight=out.in_flight if out else 0,
                    events_per_s=(sent / up) if up else 0.0,
                    waiting=out.next_seq - out.sent if out else 0,
                    held_bytes=out.kept_bytes if out else 0,
                    spilled_bytes=out.spill_bytes if out else 0,
                    dropped=out.dropped if out else 0,
                    superseded=(out.superseded if out else 0) + (inc.superseded if inc else 0),
                    expired=(out.expired if out else 0) + (inc.expired if inc else 0),
                    lost=out.given_up if out else 0,
                    resent=out.resent if out else 0,
                    resent_bytes=out.resent_bytes if out else 0,
                    deadline_missed=inc.deadline_missed if inc else 0,
                    late=bool(
                        inc is not None
                        and e.deadline_ms is not None
                        and inc.last_at is not None
                        and (now - inc.last_at) * 1e3 > e.deadline_ms
                    ),
                )
                gone = edges[name].dropped + edges[name].expired + edges[name].lost
                if gone:
                    given_up[name] = gone
        chains = self.layout.chains
        return AppStatus(
            running=self.running,
            parked={chains[c].name: why for c, why in self.parked.items()},
            recoveries=list(self.recoveries),
            given_up=given_up,
            chain_delay_ms={chains[c].name: round(ms, 3) for c, ms in sorted(self.delays.items())},
            slo_ms=self.app.slo_ms,
            origin=self.origin,
            placement=dict(self.placed),
            chains=[list(c.vertices) for c in chains],
            vertices={
                vid: h.status(now, self.crashes.get(vid))
                for vid, h in (self.crashed | self.instances).items()
            },
            edges=edges,
            capable={v: list(ns) for v, ns in self.capable.items()},
            replication={
                vid: self._replication(vid, cost, now)
                for vid, cost in self.replication.items()
                if vid in self.instances
            },
        )

    def _replication(self, vid: str, cost: ReplicationCost, now: float) -> ReplicationStatus:
        h = self.instances[vid]
        up = max(now - cost.since, 1e-9)
        return ReplicationStatus(
            replicas=list(cost.replicas),
            snapshots=cost.snapshots,
            bytes_per_snapshot=cost.last_bytes,
            bytes_per_s=round(cost.bytes_sent / up, 1),
            interval_s=round(cost.interval_s, 3),
            lag_events=h.processed - cost.acked_processed,
            lag_s=None if cost.acked_at is None else round(now - cost.acked_at, 3),
            resent=cost.resent,
            rereplicated=cost.rereplicated,
        )

    def hosts_part(self) -> bool:
        """This node runs (or is starting, or restoring) an instance of the app: it is told
        of every move of the app's vertices."""
        return bool(self.instances or self.awaiting or self.restoring or self.crashed)

    def unconfirmed(self, vertex: str) -> bool:
        """Whether this node placed ``vertex`` on a sync's word alone and no node's own word
        it runs there stands uncontested: hearsay (a node that learnt the app from syncs,
        with operator keys) that only another node's word, or a tie, supports. Its events
        wait here (store and forward) rather than go where the word says, until two senders
        agree or the node named says so itself and no sender names another
        (:mod:`mso.protocol.procedures.membership.sync`)."""
        votes = self.hearsay.get(vertex)
        if votes is None:
            return False
        node = self.placed.get(vertex, "")
        named = {n for n, senders in votes.items() if senders}
        return named != {node} or node not in votes[node]

    def lost(self, failed: set[str]) -> set[str]:
        """Vertices with no running instance: on a failed node, or gone with a node's old
        incarnation."""
        return {v for v, n in self.placed.items() if n in failed} | self.vanished

    def losses(self, failed: set[str]) -> tuple[frozenset[str], frozenset[str]]:
        """The failed nodes and the vertices this view counts lost: a view not kept up to date
        is looked up again when either changes. A restart fails nobody, only vanishes what its
        node ran (fault seed 117806: looked up for one node's restart, a holder coordinated the
        next node's on the view it had, restored a vertex moved away meanwhile, and two ran)."""
        return frozenset(failed), frozenset(self.lost(failed))


# a lazy table's name -> what makes it (:func:`lazy`)
_LAZY: dict[str, Callable[[], object]] = {
    f.name: f.metadata["lazy"] for f in fields(AppState) if "lazy" in f.metadata
}
