"""A node's tables: what the core knows, and the primitives every procedure acts through.

The node core (:mod:`mso.node.core`) is assembled from layers, each in its own module and each
one node's part in one group of procedures, lowest first:

- :mod:`mso.node.tables` — the tables (apps, hosted instances, routes, failed nodes, open
  procedures) and the effect primitives (send, broadcast, reply, timers, procedure lifetimes);
- :mod:`mso.node.dataplane` — vertex instances in the executor, edges, acks, backpressure;
- :mod:`mso.node.deployment` — distributed Algorithm 1: announce, probe, place, build, start;
- :mod:`mso.node.relocation` — relocation and restore at the coordinator, the producer, the old
  host and the new host;
- :mod:`mso.node.remapping` — chain and global remap, and failure recovery;
- :mod:`mso.node.membership` — heartbeats, failure detection, incarnations, reset, rejoin;
- :mod:`mso.node.core` — the router: message type → handler, timers, status.

A layer calls only itself and the layers below. Where a lower layer must let a higher one act
(an instance has started; a marker reached an instance; a relocation ended), it calls a hook
declared here, which the higher layer overrides and chains with ``super()``.
"""

from __future__ import annotations

import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import msgspec

from mso.model.app import App, Vertex
from mso.model.network import PowerModel
from mso.node.liveness import DEAD_AFTER_S, HEARTBEAT_S, Liveness
from mso.node.monitor import Monitor
from mso.planning.placement import Hop, Layout
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.effects import Effect, Reply, Send, SetTimer
from mso.protocol.procedures.base import Deadline, Procedure
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.hosting import InstanceLife
from mso.protocol.procedures.membership import PeerLife
from mso.protocol.procedures.relocate import Relocation
from mso.protocol.procedures.remap import Remap

if TYPE_CHECKING:
    from mso.protocol.effects import VertexSnapshot

QUEUE_EVENTS = 1024  # events fed to an instance's worker and not processed yet, at most
FEED_BATCH = 256  # events per feed at most, so markers and stops are not held behind a batch
SOURCE_RUN = 4096  # calls of a rated source per run at most
BUSY_AFTER_S = 1.0  # an instance working on one effect this long is reported busy ...
HUNG_AFTER_S = 10.0  # ... and this long, hung (status only: it never takes the node down)


@dataclass
class Restoring:
    """A replacement instance waiting to hear where each of its surviving edges stands."""

    rid: int
    coordinator: str
    pending: set[tuple[int, bool]]
    positions: dict[int, int] = field(default_factory=dict)  # output -> from producers' acks
    consumer_start: dict[int, int] = field(default_factory=dict)  # output -> consumer expects


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


def crash_status(rec: Crashes | None) -> dict[str, Any]:
    """A vertex's crashes here, as status shows them next to its state."""
    if rec is None:
        return {"crashes": 0, "restarts": 0, "last_crash": "", "not_restarted": ""}
    return {
        "crashes": rec.count,
        "restarts": rec.restarts,
        "last_crash": rec.last,
        "not_restarted": rec.gave_up,
    }


@dataclass
class Hosted:
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
    pending: deque[tuple[int, list[bytes], float] | m.Marker] = field(default_factory=deque)
    # a rated source: schedule origin and calls asked for; a loop source: credit granted
    t0: float = 0.0
    asked: int = 0
    credit: int = 0
    ended: bool = False
    handing_over: m.Marker | None = None  # snapshot asked for this relocation
    crashed: str = ""  # its child process died unasked: how (no results come any more)
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


@dataclass
class Deployment:
    """One app on this node: the shared layout, what is placed, what runs here."""

    app: App
    layout: Layout
    origin: str
    placed: dict[str, str]
    placed_chains: set[int] = field(default_factory=set)
    started_chains: set[int] = field(default_factory=set)
    probes: dict[int, dict[int, list[Hop]]] = field(default_factory=dict)
    probes_expected: dict[int, int] = field(default_factory=dict)
    parts_pending: dict[int, set[str]] = field(default_factory=dict)
    stones: dict[str, Hosted] = field(default_factory=dict)
    out: dict[int, OutChannel] = field(default_factory=dict)
    inc: dict[int, InChannel] = field(default_factory=dict)
    gates: dict[str, AckGate] = field(default_factory=dict)  # vertex -> chained acks
    decoders: dict[int, msgspec.msgpack.Decoder[Any]] = field(default_factory=dict)
    running: bool = False
    epoch: int = 0
    awaiting: dict[str, Hosted] = field(default_factory=dict)  # prepared, awaiting handover
    building: dict[int, tuple[str, set[str]]] = field(default_factory=dict)  # chain -> (asker,
    # vertices still starting)
    preparing: dict[str, tuple[int, str, bool]] = field(default_factory=dict)  # vertex -> (rid,
    # coordinator, restore) until its instance has started
    stash: dict[int, list[tuple[int, list[bytes]]]] = field(default_factory=dict)
    markers: dict[str, set[int]] = field(default_factory=dict)  # vertex -> edges marked
    blocked_sources: set[str] = field(default_factory=set)
    started_at: float = 0.0
    parked: dict[int, str] = field(default_factory=dict)  # chain -> why it cannot run
    parked_edges: set[int] = field(default_factory=set)  # edges of parked chains
    dropped: dict[int, int] = field(default_factory=dict)  # edge -> events a parked chain lost
    recovering: int | None = None  # the remap recovering from a failure, at its coordinator
    restoring: dict[str, Restoring] = field(default_factory=dict)  # replacements awaiting
    recoveries: list[dict[str, Any]] = field(default_factory=list)  # what was done, bounded
    # vertices whose instances went with a node that has since rejoined: restored like lost ones
    vanished: set[str] = field(default_factory=set)
    handed: dict[str, str] = field(default_factory=dict)  # vertex -> where this node handed it
    document: str = ""  # the app file as deployed, for a node that rejoins
    crashes: dict[str, Crashes] = field(default_factory=dict)  # vertex -> its crashes here
    crashed: dict[str, Hosted] = field(default_factory=dict)  # crashed, not in ``stones``
    delays: dict[int, float] = field(default_factory=dict)  # at a tail's node: chain -> ms
    moved: dict[str, tuple[float, str]] = field(default_factory=dict)  # vertex -> (when, from)
    placed_at: dict[int, float] = field(default_factory=dict)  # chain -> when last (re)mapped
    route_changed: dict[int, float] = field(default_factory=dict)  # chain -> last route change
    chain_delay: dict[int, tuple[float, float]] = field(default_factory=dict)  # at a head's
    # at the origin only
    built: set[int] = field(default_factory=set)
    client: int | None = None
    requested_at: float = 0.0
    out_edges: dict[str, list[int]] = field(default_factory=dict)


class AppPolicies(Protocol):
    """What deployment and membership need of the management rules: an app's policy checked
    (and loaded) when the app arrives, and forgotten when it goes."""

    def app_policy(self, app: str, spec: Any, where: str) -> None: ...

    def forget(self, app: str) -> None: ...


class NodeTables:
    """One node's tables and the primitives that act on them (see the module docstring)."""

    # an illegal transition raises (tests set this) instead of only being counted
    strict = False
    manager: AppPolicies

    def __init__(
        self,
        node_id: str,
        *,
        capacity: float = 1.0,
        window: int = 4096,
        power: PowerModel | None = None,
        battery_wh: float | None = None,
        heartbeat_s: float = HEARTBEAT_S,
        dead_after_s: float = DEAD_AFTER_S,
        incarnation: int = 0,
    ) -> None:
        self.id = node_id
        # grows when this node restarts (the daemon passes its start time) or rejoins after a
        # partition: others then know its old instances are gone
        self.incarnation = incarnation
        self.capacity = capacity
        self.power = power or PowerModel()
        self.liveness = Liveness(heartbeat_s, dead_after_s)
        self.failures: list[dict[str, Any]] = []  # failed nodes: who, when, detected by whom
        self.rejoins: list[dict[str, Any]] = []  # nodes back as a new incarnation: who, when
        self.monitor = Monitor(power or PowerModel(), battery_wh, cpu_speed=capacity)
        # read only to report how long a request took; None in simulation (``now`` is exact)
        self.clock: Callable[[], float] | None = None
        self.work_ms = 0.0  # modelled CPU work of every event processed here (cost units)
        self.cpu_ms = 0.0  # measured CPU time of the vertex code that ran here
        # cumulative (bytes sent, bytes received) as the driver counts them
        self.traffic: Callable[[], tuple[int, int]] = lambda: (0, 0)
        self.window = window
        self.routes: dict[str, tuple[str, int]] = {}  # destination -> (next hop, hops)
        self.apps: dict[str, Deployment] = {}
        self.dropped_messages = 0
        # well-typed messages refused for their meaning (a vertex, edge or procedure that is
        # not there; a member's command that needs an operator), by reason; each is also one
        # of ``dropped_messages``
        self.refusals: dict[str, int] = {}
        # operator keys and the undeploys they signed; open (no keys) unless the driver shares
        # its own (``mso node --operator-key``), which the transport checks frames with too
        self.authority = Authority()
        self._effects: list[Effect] = []
        self._work: deque[tuple[str, str, m.Message]] = deque()
        # vertex instances this node asked the executor for: id -> (app, vertex)
        self._instances: dict[int, tuple[str, str]] = {}
        self._next_instance = 0
        # ids of procedures this node coordinates: distinct per node, small enough for msgpack
        self._rid = self._rid_base = (zlib.crc32(node_id.encode()) & 0xFFFFFF) << 20
        self._probes_waiting: list[tuple[float, m.Probe]] = []  # (give up at, probe)
        self._handover_to: dict[int, str] = {}  # rid -> coordinator, at a relocation's target
        # per edge: (first seq, events, when the oldest entered its chain)
        self._outbox: dict[tuple[str, int], tuple[int, list[bytes], float]] = {}
        # procedures this node coordinates, by id: each has a deadline timer
        self.procedures: dict[int, Procedure] = {}
        self.illegal_transitions = 0
        self.handler_errors = 0  # messages whose handling raised (a bug), and the last one
        self.last_handler_error = ""
        self._now = 0.0
        self.status_hook: Callable[[], dict[str, Any]] | None = None  # the driver's counters
        self._deploy_clients: dict[str, tuple[int, float]] = {}
        self._epochs = zlib.crc32(node_id.encode()) & 0xFFFF
        # messages for an app whose announcement has not arrived yet (another path overtook it)
        self._early: dict[str, list[tuple[str, m.Message]]] = {}
        self.dead: set[str] = set()  # nodes known to have failed (fail-stop)
        self.peers: dict[str, PeerLife] = {}  # each other node's state, by its table
        # nodes out of this node's reach that it asks others about before declaring them
        # failed: node -> its Suspicion's procedure id (one each, so bounded by the nodes)
        self._suspicions: dict[str, int] = {}
        # nodes this node was asked about, does not hear, reaches, and asked itself: node ->
        # its Vouch's procedure id (one each, bounded by the nodes it reaches)
        self._vouching: dict[str, int] = {}
        self._incarnations: dict[str, int] = {}  # last incarnation heard of, per node
        self._dead_incarnation: dict[str, int] = {}  # the incarnation declared failed
        self._beats = 0
        self._briefed: dict[str, float] = {}  # neighbour -> its link's start, once told our figures
        # nodes that rejoined while this node's own view was in dispute (it holds a reachable
        # node failed: a healed partition whose losing side has not reset yet): synced after
        self._sync_pending: set[str] = set()

    def _elapsed_ms(self, since: float) -> float:
        """Time since a request, for the replies that report it: the driver's clock when it
        gave one (a whole deployment can finish inside one synchronous run), else ``now``."""
        end = self.clock() if self.clock is not None else self._now
        return max(0.0, end - since) * 1e3

    @property
    def now(self) -> float:
        return self._now

    def _refusal(self, reason: str) -> None:
        """A message refused for its meaning: nothing changed; counted by reason."""
        self.dropped_messages += 1
        if reason in self.refusals or len(self.refusals) < 64:
            self.refusals[reason] = self.refusals.get(reason, 0) + 1

    def send(self, dst: str, msg: m.Message) -> None:
        self._send(dst, msg)

    def broadcast(self, msg: m.Message) -> None:
        self._broadcast(msg)

    def reply(self, client: int, msg: m.Message) -> None:
        self._effects.append(Reply(client, msg))

    def set_timer(self, key: Any, at: float) -> None:
        self._effects.append(SetTimer(key, at))

    def elapsed_ms(self, since: float) -> float:
        return self._elapsed_ms(since)

    def _ours(self, pid: int) -> bool:
        """``pid`` is (was) a procedure of this node's: an answer to it may come late."""
        return self._rid_base < pid <= self._rid

    def _reloc(self, pid: int) -> Relocation | None:
        proc = self.procedures.get(pid)
        return proc if isinstance(proc, Relocation) else None

    def _remap(self, pid: int | None) -> Remap | None:
        proc = self.procedures.get(pid) if pid is not None else None
        return proc if isinstance(proc, Remap) else None

    def _deploying(self, app: str) -> Deploy | None:
        for proc in self.procedures.values():
            if isinstance(proc, Deploy) and proc.app == app:
                return proc
        return None

    def _relocations(self) -> list[Relocation]:
        return [p for p in self.procedures.values() if isinstance(p, Relocation)]

    def _begin(self, proc: Procedure) -> None:
        self.procedures[proc.pid] = proc
        self._effects.append(SetTimer(Deadline(proc.pid), proc.deadline))

    def _end(self, pid: int) -> None:
        if self.procedures.pop(pid, None) is not None:
            self._effects.append(fx.CancelTimer(Deadline(pid)))

    def open_procedures(self, now: float) -> list[dict[str, Any]]:
        """Procedures still running here, with their deadlines (overdue ones flagged)."""
        return [
            p.describe() | {"id": pid, "overdue": now > p.deadline}
            for pid, p in sorted(self.procedures.items())
        ]

    def _send(self, dst: str, msg: m.Message) -> None:
        if dst == self.id:
            self._work.append((self.id, "", msg))
        else:
            self._effects.append(Send(dst, msg))

    def _broadcast(self, msg: m.Message) -> None:
        """To every node not held failed, including those heard of but out of reach right
        now: a partition shorter than failure detection declares nobody failed, so no rejoin
        would ever tell them what they missed; the driver holds the frame until routes come
        back (``mso.net.forwarding``), and a longer cut ends in a rejoin, which syncs."""
        for n in sorted({*self.known_nodes(), *self._incarnations}):
            if n not in self.dead:
                self._send(n, msg)

    def known_nodes(self) -> list[str]:
        return sorted({self.id, *self.routes})

    def route_hops(self) -> dict[str, int]:
        """Hops to each node this node routes to (itself not included)."""
        return {n: hops for n, (_, hops) in self.routes.items()}

    def _distances(self) -> dict[str, int]:
        return {**self.route_hops(), self.id: 0}

    def _sample(self, now: float) -> None:
        out, inc = self.traffic()
        self.monitor.sample(now, self.work_ms, out, inc, self.cpu_ms)

    def _lost(self, dep: Deployment) -> set[str]:
        """Vertices with no running instance: on a failed node, or gone with a node's old
        incarnation."""
        return {v for v, n in dep.placed.items() if n in self.dead} | dep.vanished

    # -- hooks: a lower layer lets a higher one act; each override chains with super() -------
    def _instance_ready(self, dep: Deployment, vid: str) -> None:
        """An instance's code was constructed (``open()`` ran): a build or a move goes on."""

    def _instance_failed(self, dep: Deployment, vid: str, error: str) -> None:
        """An instance's code failed at construction: whoever asked for it is told."""

    def _instance_crashed(self, dep: Deployment, vid: str, h: Hosted, now: float) -> None:
        """A started instance's process died unasked (counted already): recover it."""

    def _on_marker(self, dep: Deployment, msg: m.Marker) -> None:
        """A relocation's marker reached an instance, behind every event sent before it."""

    def _snapshotted(self, dep: Deployment, vid: str, h: Hosted, res: VertexSnapshot) -> None:
        """An instance's state was taken for a relocation."""

    def _app_missing(self, dep: Deployment, node: str) -> None:
        """``node`` refused to host a vertex of ``dep``'s app: it does not hold the app."""
