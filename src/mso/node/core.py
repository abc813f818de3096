"""The node core: one node's tables and its part in every distributed procedure. Sans-IO.

Fed ``(message, now)``, ``(timer, now)`` or a client request; returns effects (send a message to
a node, reply to a client, set a timer). It never reads a clock or a socket: the asyncio driver
(``mso.node.driver``) supplies real time and connections, a simulator can supply virtual ones.

Deployment (Algorithm 1, distributed): the origin announces the app to every node; each node
derives the same :class:`~mso.planning.placement.Layout`; the node holding a ready chain's head
probes toward the chain's target hop by hop, places the chain with the shared placement code,
broadcasts the placement (which activates the chains that depended on it), and builds the
chain's overlay by asking each node on it to host its vertices. When every chain is built the
origin starts the sources.
"""

from __future__ import annotations

import zlib
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from mso.errors import MsoError
from mso.management import RuleSettings, load_policy
from mso.model.app import App, Vertex
from mso.model.appfile import loads_app
from mso.model.network import PowerModel
from mso.node.liveness import DEAD_AFTER_S, HEARTBEAT_S, Liveness
from mso.node.manager import Manager
from mso.node.monitor import Monitor
from mso.planning.placement import Hop, Layout
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.effects import Effect, Reply, Send, SetTimer
from mso.protocol.procedures.base import Deadline, IllegalTransition, Procedure, Retry
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.relocate import STEP_ATTEMPTS, STEP_TIMEOUT_S, Relocation
from mso.protocol.procedures.remap import PROBE_ATTEMPTS, Remap
from mso.protocol.procedures.remap import S as RemapState
from mso.protocol.procedures.status import StatusFanout

__all__ = ["Effect", "NodeCore", "Reply", "Send", "SetTimer"]


ACK_EVERY = 256  # events processed before an ack is sent without waiting for the flush
RETRANSMIT_S = 0.25
MAX_WAITING_PROBES = 256  # probes held at a hop whose route still goes through a failed node
REJOIN_EVERY = 10  # heartbeat periods between heartbeats to reachable nodes declared failed
SOURCE_BURST = 256  # events a rate-less source emits per turn
MONITOR_PERIOD_S = 1.0  # how often the monitor samples on its own
MAX_BATCH_BYTES = 64 * 1024  # a Data frame is sent once its events reach about this size
DELAY_SMOOTHING = 0.2  # weight of the newest batch in a chain's delay average


@dataclass
class Restoring:
    """A replacement instance waiting to hear where each of its surviving edges stands."""

    rid: int
    coordinator: str
    pending: set[tuple[int, bool]]
    positions: dict[int, int] = field(default_factory=dict)  # output -> from producers' acks
    consumer_start: dict[int, int] = field(default_factory=dict)  # output -> consumer expects


QUEUE_EVENTS = 1024  # events fed to an instance's worker and not processed yet, at most
FEED_BATCH = 256  # events per feed at most, so markers and stops are not held behind a batch
SOURCE_RUN = 4096  # calls of a rated source per run at most
BUSY_AFTER_S = 1.0  # an instance working on one effect this long is reported busy ...
HUNG_AFTER_S = 10.0  # ... and this long, hung (status only: it never takes the node down)


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

    @property
    def rate(self) -> float:
        v = self.vertex
        if v.rate:
            return v.rate
        return 1.0 if v.code is None else 0.0  # a stand-in ticks once a second

    def state(self, now: float) -> str:
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
    document: str = ""  # the app file as deployed, for a node that rejoins
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


class NodeCore:
    """One node's state machine."""

    # an illegal transition raises (tests set this) instead of only being counted
    strict = False

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
        policy: Any = None,
        manage: bool = True,
        rules: RuleSettings | None = None,
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
        self._effects: list[Effect] = []
        self._work: deque[tuple[str, str, m.Message]] = deque()
        # vertex instances this node asked the executor for: id -> (app, vertex)
        self._instances: dict[int, tuple[str, str]] = {}
        self._next_instance = 0
        # ids of procedures this node coordinates: distinct per node, small enough for msgpack
        self._rid = (zlib.crc32(node_id.encode()) & 0xFFFFFF) << 20
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
        self._incarnations: dict[str, int] = {}  # last incarnation heard of, per node
        self._dead_incarnation: dict[str, int] = {}  # the incarnation declared failed
        self._beats = 0
        # the router: message type -> the handler of the procedure it belongs to
        self._handlers: dict[type, Callable[[str, Any, float], None]] = {
            m.Data: lambda src, msg, now: self._on_data(msg),
            m.Ack: lambda src, msg, now: self._on_ack(msg, now),
            m.AppAnnounce: lambda src, msg, now: self._on_announce(msg, now),
            m.Probe: lambda src, msg, now: self._on_probe(msg),
            m.ProbeReply: lambda src, msg, now: self._on_probe_reply(msg),
            m.ChainPlaced: lambda src, msg, now: self._on_placed(msg),
            m.BuildChain: lambda src, msg, now: self._on_build(src, msg),
            m.ChainPartReady: lambda src, msg, now: self._on_part_ready(msg),
            m.ChainBuilt: lambda src, msg, now: self._on_built(msg, now),
            m.StartApp: lambda src, msg, now: self._on_start(msg, now),
            m.StopApp: lambda src, msg, now: self._on_stop_app(msg, now),
            m.DeployFailed: lambda src, msg, now: self._on_deploy_failed(msg, now),
            m.StatusRequest: lambda src, msg, now: self._send(
                src, m.StatusReply(req=msg.req, nodes={self.id: self.status(now)})
            ),
            m.StatusReply: lambda src, msg, now: self._on_status_reply(msg),
            m.Marker: lambda src, msg, now: self._on_marker_msg(msg, now),
            m.RelocateRequest: lambda src, msg, now: self._relocate_request(None, msg, now),
            m.Prepare: lambda src, msg, now: self._on_prepare(src, msg),
            m.Prepared: lambda src, msg, now: self._on_prepared(msg, now),
            m.Switch: lambda src, msg, now: self._on_switch(msg),
            m.Handover: lambda src, msg, now: self._on_handover(src, msg, now),
            m.Moved: lambda src, msg, now: self._on_moved(msg, now),
            m.HandoverDone: lambda src, msg, now: self._on_handover_done(msg, now),
            m.ChainDelay: lambda src, msg, now: self._on_chain_delay(msg, now),
            m.Heartbeat: lambda src, msg, now: self._on_heartbeat(src, msg, now),
            m.NodeDown: lambda src, msg, now: self._on_node_down(
                msg.node, msg.detector, now, msg.incarnation
            ),
            m.NodeUp: lambda src, msg, now: self._on_node_up(msg, now),
            m.AppSync: lambda src, msg, now: self._on_app_sync(msg, now),
            m.Rewire: lambda src, msg, now: self._on_rewire(msg, now),
            m.Resume: lambda src, msg, now: self._on_resume(msg, now),
        }
        # management rules and policies (§3.5); the node policy is checked here, at start
        self.manager = Manager(self, policy, rules, enabled=manage)

    # -- entry points -----------------------------------------------------------------------
    def _elapsed_ms(self, since: float) -> float:
        """Time since a request, for the replies that report it: the driver's clock when it
        gave one (a whole deployment can finish inside one synchronous run), else ``now``."""
        end = self.clock() if self.clock is not None else self._now
        return max(0.0, end - since) * 1e3

    def start(self, now: float) -> list[Effect]:
        """Begin monitoring; drivers call this once when the node starts."""
        self._sample(now)
        self._effects.append(SetTimer(("monitor",), now + MONITOR_PERIOD_S))
        self._effects.append(SetTimer(("heartbeat",), now + self.liveness.period_s))
        return self._run(now)

    def set_routes(self, routes: dict[str, tuple[str, int]], now: float = 0.0) -> list[Effect]:
        """Take the routing view's current routes; returns effects (a recovery waiting for
        routes around a failed node may start)."""
        self._now = now
        old, self.routes = self.routes, {d: r for d, r in routes.items() if d != self.id}
        self.monitor.note_routes(now, self.routes)
        changed = {d for d in set(old) | set(self.routes) if old.get(d) != self.routes.get(d)}
        for dep in self.apps.values():  # a route inside a chain changed (the route rule's event)
            for c in dep.layout.chains:
                if changed & {dep.placed.get(v) for v in c.vertices}:
                    dep.route_changed[c.index] = now
        neighbours = {d for d, (hop, _) in self.routes.items() if hop == d}
        self.liveness.set_routes(now, set(self.routes) - self.dead, neighbours)
        if set(self.routes) - set(old):  # a hello: newly reachable nodes learn our incarnation
            beat = self._beat()  # (and whom we hold failed, if a partition just healed)
            for d in sorted(set(self.routes) - set(old)):
                self._send(d, beat)
        waiting, self._probes_waiting = self._probes_waiting, []
        for deadline, probe in waiting:
            if deadline >= now:
                self._forward_probe(probe, now)
        for dep in list(self.apps.values()):
            self._maybe_recover(dep, now)
        return self._run(now)

    def _sample(self, now: float) -> None:
        out, inc = self.traffic()
        self.monitor.sample(now, self.work_ms, out, inc, self.cpu_ms)

    def known_nodes(self) -> list[str]:
        return sorted({self.id, *self.routes})

    def receive(self, src: str, msg: m.Message, now: float) -> list[Effect]:
        if src in self.dead:  # a node declared failed is heard only to rejoin
            if isinstance(msg, m.Heartbeat):
                self._now = now
                self._on_dead_heartbeat(src, msg, now)
                return self._run(now)
            self.dropped_messages += 1
            return []
        self.liveness.heard_from(src, now)
        self._work.append((src, "", msg))
        return self._run(now)

    def request(self, client: int, msg: m.Message, now: float) -> list[Effect]:
        """A request from a client connection (CLI, API, emulator controller)."""
        self._now = now
        if isinstance(msg, m.DeployRequest):
            self._deploy_request(client, msg, now)
        elif isinstance(msg, m.StopApp):
            if msg.app in self.apps:
                self._broadcast(msg)
            self._effects.append(Reply(client, m.StopApp(msg.app)))
        elif isinstance(msg, m.RelocateRequest):
            self._relocate_request(client, msg, now)
        elif isinstance(msg, m.RemapRequest):
            self._remap_request(client, msg, now)
        elif isinstance(msg, m.StatusRequest):
            self._status_request(client, msg, now)
        else:
            self.dropped_messages += 1
        return self._run(now)

    def on_timer(self, key: Any, now: float) -> list[Effect]:
        self._now = now
        try:
            self._on_timer(key, now)
        except IllegalTransition:
            self.illegal_transitions += 1
            if self.strict:
                raise
        return self._run(now)

    def _on_timer(self, key: Any, now: float) -> None:
        if isinstance(key, Deadline):
            proc = self.procedures.get(key.pid)
            if proc is not None and not proc.done:
                self._expire(proc, now)
            return
        if isinstance(key, Retry):
            proc = self.procedures.get(key.pid)
            if isinstance(proc, Relocation):
                self._step_timeout(key.pid, now)
            elif isinstance(proc, Remap):
                self._remap_probe_timeout(key.pid, key.attempt, now)
            return
        kind = key[0]
        if kind == "source":
            self._source_tick(key[1], key[2], now)
        elif kind == "retransmit":
            self._retransmit(key[1], now)
        elif kind == "monitor":
            self._sample(now)
            self._report_delays(now)
            self.manager.tick(now)
            self._effects.append(SetTimer(("monitor",), now + MONITOR_PERIOD_S))
        elif kind == "heartbeat":
            self._heartbeat(now)
        elif kind == "recover":
            dep = self.apps.get(key[1])
            if dep is not None:
                self._maybe_recover(dep, now)

    # -- procedures: the context they act through, their lifetimes ------------------------
    @property
    def now(self) -> float:
        return self._now

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

    def _expire(self, proc: Procedure, now: float) -> None:
        """A procedure's deadline passed: its defined failure, reported to whoever waits."""
        why = f"{proc.name} did not finish within {proc.deadline - proc.started_at:g} s"
        if isinstance(proc, Relocation):
            self._reloc_failed(proc, why, now)
        elif isinstance(proc, Remap):
            self._finish_remap(proc.pid, now, why)
        elif isinstance(proc, Deploy):  # a probe or a chain build was lost: stop it everywhere
            self._on_deploy_failed(m.DeployFailed(proc.app, f"{self.id}: {why}"), now)
            self._end(proc.pid)
        else:
            proc.expire(self)
            self._end(proc.pid)

    def open_procedures(self, now: float) -> list[dict[str, Any]]:
        """Procedures still running here, with their deadlines (overdue ones flagged)."""
        return [
            p.describe() | {"id": pid, "overdue": now > p.deadline}
            for pid, p in sorted(self.procedures.items())
        ]

    # -- the loop ---------------------------------------------------------------------------
    def _send(self, dst: str, msg: m.Message) -> None:
        if dst == self.id:
            self._work.append((self.id, "", msg))
        else:
            self._effects.append(Send(dst, msg))

    def _broadcast(self, msg: m.Message) -> None:
        for n in self.known_nodes():
            if n not in self.dead:
                self._send(n, msg)

    def _run(self, now: float) -> list[Effect]:
        self._now = now
        while self._work:
            src, _, msg = self._work.popleft()
            try:
                self._dispatch(src, msg, now)
            except MsoError:
                self.dropped_messages += 1
            except IllegalTransition:
                self.illegal_transitions += 1  # a message at the wrong moment: counted
                if self.strict:
                    raise
            except Exception as exc:  # a bug must cost one message, never the link or node
                self.handler_errors += 1
                self.last_handler_error = f"{type(msg).__name__}: {type(exc).__name__}: {exc}"
                if self.strict:
                    raise
        self._flush()
        out, self._effects = self._effects, []
        return out

    EARLY = (m.ChainPlaced, m.BuildChain, m.ChainPartReady, m.ChainBuilt, m.StartApp)
    MAX_EARLY = 1000

    def _dispatch(self, src: str, msg: m.Message, now: float) -> None:
        if isinstance(msg, self.EARLY) and msg.app not in self.apps:
            held = self._early.setdefault(msg.app, [])
            if len(held) < self.MAX_EARLY and len(self._early) <= 64:
                held.append((src, msg))  # replayed when the app's announcement arrives
            else:
                self.dropped_messages += 1
            return
        handler = self._handlers.get(type(msg))
        if handler is None:
            self.dropped_messages += 1  # a client's request, or a link message, from a node
            return
        handler(src, msg, now)

    def _on_stop_app(self, msg: m.StopApp, now: float) -> None:
        gone = self.apps.pop(msg.app, None)
        if gone is not None:
            self._stop_app(gone, "undeploy")
        self._early.pop(msg.app, None)
        self.manager.forget(msg.app)

    def _on_marker_msg(self, msg: m.Marker, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is not None and 0 <= msg.edge < len(dep.app.edges):
            self._enqueue(dep, dep.app.edges[msg.edge].dst, msg)

    def _on_moved(self, msg: m.Moved, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is not None and msg.vertex in dep.placed:
            dep.placed[msg.vertex] = msg.node
            dep.vanished.discard(msg.vertex)
            for c in dep.layout.chains:
                if msg.vertex in c.vertices:
                    dep.placed_at[c.index] = now

    def _on_chain_delay(self, msg: m.ChainDelay, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is not None and 0 <= msg.chain < len(dep.layout.chains):
            dep.chain_delay[msg.chain] = (msg.delay_ms, now)

    # -- deployment -------------------------------------------------------------------------
    def _deploy_request(self, client: int, req: m.DeployRequest, now: float) -> None:
        try:
            app = loads_app(req.document, file=req.file)
            load_policy(app.policy, where=f"{req.file}: policy")
        except MsoError as exc:
            self._effects.append(Reply(client, _failed_reply("", str(exc))))
            return
        if app.name in self.apps:
            reply = _failed_reply(app.name, f"an app named {app.name!r} is already deployed")
            self._effects.append(Reply(client, reply))
            return
        known = set(self.known_nodes())
        for v in app.vertices.values():
            if v.pinned is not None and v.pinned not in known:
                reason = (
                    f"vertex {v.id!r} is pinned to node {v.pinned!r}, which is not reachable "
                    f"(reachable: {', '.join(sorted(known))})"
                )
                self._effects.append(Reply(client, _failed_reply(app.name, reason)))
                return
        self._deploy_clients[app.name] = (client, now)
        self._rid += 1
        self._begin(Deploy(self._rid, now, app.name))
        epoch = self._epochs = (self._epochs + 1) & 0x7FFFFFFF
        self._broadcast(
            m.AppAnnounce(app=app.name, origin=self.id, document=req.document, epoch=epoch)
        )

    def _on_announce(self, msg: m.AppAnnounce, now: float) -> None:
        if msg.app in self.apps:
            return
        try:
            app = loads_app(msg.document, file=f"<{msg.app}>")
            self.manager.app_policy(app.name, app.policy, where=f"{self.id}: {app.name}: policy")
        except MsoError as exc:
            self._send(msg.origin, m.DeployFailed(app=msg.app, reason=f"{self.id}: {exc}"))
            return
        layout = Layout(app, msg.origin)
        dep = Deployment(
            app=app,
            layout=layout,
            origin=msg.origin,
            placed=layout.initial_placement(),
            epoch=msg.epoch,
            document=msg.document,
        )
        for i, e in enumerate(app.edges):
            dep.out_edges.setdefault(e.src, []).append(i)
        if msg.origin == self.id and msg.app in self._deploy_clients:
            dep.client, dep.requested_at = self._deploy_clients.pop(msg.app)
        self.apps[msg.app] = dep
        self._start_ready_chains(dep)
        for early in self._early.pop(msg.app, []):
            self._work.append((early[0], "", early[1]))

    def _distances(self) -> dict[str, int]:
        d = {n: hops for n, (_, hops) in self.routes.items()}
        d[self.id] = 0
        return d

    def _start_ready_chains(self, dep: Deployment) -> None:
        lay = dep.layout
        for ci in lay.order:
            if ci in dep.started_chains or not lay.ready(ci, dep.placed_chains):
                continue
            head = lay.chains[ci].head
            if dep.placed.get(head) != self.id:
                continue
            dep.started_chains.add(ci)
            target, _ = lay.target(ci, dep.placed, self._distances())
            pairs = lay.probes_needed(ci, dep.placed, target)
            dep.probes[ci] = {}
            if not pairs:
                self._place(dep, ci)
                continue
            dep.probes_expected[ci] = len(pairs)
            for k, (a, b) in enumerate(pairs):
                self._send(a, m.Probe(dep.app.name, ci, k, self.id, b, [], []))

    def _on_probe(self, msg: m.Probe) -> None:
        msg.nodes.append(self.id)
        msg.capacities.append(self.capacity)
        if msg.target == self.id:
            reply = m.ProbeReply(msg.app, msg.chain, msg.segment, msg.nodes, msg.capacities)
            self._send(msg.requester, reply)
            return
        self._forward_probe(msg, self._now)

    def _forward_probe(self, msg: m.Probe, now: float) -> None:
        nxt = self.routes.get(msg.target)
        if nxt is not None and nxt[0] in self.dead:
            # our routes do not go around a failure yet (the coordinator's already do): wait
            # for them rather than lose the probe and the coordinator's STEP_TIMEOUT_S
            if len(self._probes_waiting) < MAX_WAITING_PROBES:
                self._probes_waiting.append((now + STEP_TIMEOUT_S, msg))
            return
        if nxt is None:
            reply = m.ProbeReply(msg.app, msg.chain, msg.segment, [], [])
            self._send(msg.requester, reply)
            return
        self._effects.append(Send(nxt[0], msg))  # the next hop appends itself in turn

    def _on_probe_reply(self, msg: m.ProbeReply) -> None:
        if msg.chain < 0:
            self._on_remap_probe(msg)
            return
        dep = self.apps.get(msg.app)
        if dep is None or msg.chain not in dep.probes:
            return
        got = dep.probes[msg.chain]
        got[msg.segment] = [Hop(n, c) for n, c in zip(msg.nodes, msg.capacities, strict=False)]
        if len(got) == dep.probes_expected.get(msg.chain):
            self._place(dep, msg.chain)

    def _place(self, dep: Deployment, ci: int) -> None:
        lay = dep.layout
        hops_by_pair: dict[tuple[str, str], list[Hop]] = {}
        dep.probes_expected.pop(ci, None)
        for hops in dep.probes.pop(ci, {}).values():
            if hops:
                hops_by_pair[(hops[0].node, hops[-1].node)] = hops

        def probe(a: str, b: str) -> list[Hop]:
            return hops_by_pair.get((a, b), [])

        try:
            assigned, _ = lay.place(ci, dep.placed, probe, self._distances())
        except MsoError as exc:
            self._send(dep.origin, m.DeployFailed(dep.app.name, f"{self.id}: {exc}"))
            return
        self._broadcast(m.ChainPlaced(dep.app.name, ci, assigned))

    def _on_placed(self, msg: m.ChainPlaced) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.chain in dep.placed_chains:
            return
        dep.placed.update(msg.assignments)
        dep.placed_chains.add(msg.chain)
        chain = dep.layout.chains[msg.chain]
        if msg.assignments.get(chain.head) == self.id and msg.chain in dep.started_chains:
            by_node: dict[str, list[str]] = {}
            for v in chain.vertices:
                by_node.setdefault(msg.assignments[v], []).append(v)
            dep.parts_pending[msg.chain] = set(by_node)
            for node, verts in by_node.items():
                self._send(node, m.BuildChain(dep.app.name, msg.chain, verts))
        self._start_ready_chains(dep)

    def _on_build(self, src: str, msg: m.BuildChain) -> None:
        """Host this node's part of a chain; it is ready once every instance has started."""
        dep = self.apps.get(msg.app)
        if dep is None:
            return
        starting = set()
        for vid in msg.vertices:
            h = dep.stones.get(vid)
            if h is None:
                h = dep.stones[vid] = self._host(dep, vid)
            if not h.started:
                starting.add(vid)
        if starting:
            dep.building[msg.chain] = (src, starting)
        else:
            self._send(src, m.ChainPartReady(msg.app, msg.chain, self.id))

    def _on_part_ready(self, msg: m.ChainPartReady) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.chain not in dep.parts_pending:
            return
        pending = dep.parts_pending[msg.chain]
        pending.discard(msg.node)
        if not pending:
            del dep.parts_pending[msg.chain]
            self._send(dep.origin, m.ChainBuilt(msg.app, msg.chain))

    def _on_built(self, msg: m.ChainBuilt, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or dep.origin != self.id:
            return
        dep.built.add(msg.chain)
        proc = self._deploying(msg.app)
        if proc is not None:
            proc.on("built")
        if len(dep.built) == len(dep.layout.chains):
            if proc is not None:
                proc.on("all_built")
                self._end(proc.pid)
            self._broadcast(m.StartApp(msg.app))
            if dep.client is not None:
                elapsed = self._elapsed_ms(dep.requested_at)
                reply = m.DeployReply(msg.app, True, dict(dep.placed), elapsed)
                self._effects.append(Reply(dep.client, reply))
                dep.client = None

    def _on_deploy_failed(self, msg: m.DeployFailed, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or dep.origin != self.id:
            return
        proc = self._deploying(msg.app)
        if proc is not None:
            proc.fail(self, msg.reason)
            self._end(proc.pid)
        if dep.client is not None:
            self._effects.append(Reply(dep.client, _failed_reply(msg.app, msg.reason)))
            dep.client = None
        self._broadcast(m.StopApp(msg.app))

    def _on_start(self, msg: m.StartApp, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or dep.running:
            return
        dep.running = True
        dep.started_at = now
        dep.placed_at = dict.fromkeys(range(len(dep.layout.chains)), now)
        for vid, h in dep.stones.items():
            if h.kind == "source":
                self._start_source(dep, vid, now)
        self._effects.append(SetTimer(("retransmit", msg.app), now + RETRANSMIT_S))

    # -- vertex instances: the executor runs their code; results come back here ------------
    def _host(self, dep: Deployment, vid: str) -> Hosted:
        """Ask the executor for a new instance of ``vid``."""
        self._next_instance += 1
        iid = self._next_instance
        self._instances[iid] = (dep.app.name, vid)
        edges = dep.app.edges
        inputs = {i: dep.app.edge_format(e) for i, e in enumerate(edges) if e.dst == vid}
        h = Hosted(iid, dep.app.vertices[vid], dep.layout.kinds[vid])
        self._submit(h, fx.StartVertex(iid, dep.app.name, h.vertex, h.kind, inputs))
        return h

    def _submit(self, h: Hosted, eff: fx.VertexEffect, events: int = 0) -> None:
        self._effects.append(eff)
        h.jobs += 1
        h.queued += events
        if h.busy_since is None:
            h.busy_since = self._now

    def _stop(self, h: Hosted, reason: str) -> None:
        self._instances.pop(h.instance, None)
        self._effects.append(fx.StopVertex(h.instance, reason))

    def _stop_app(self, dep: Deployment, reason: str) -> None:
        for h in [*dep.stones.values(), *dep.awaiting.values()]:
            self._stop(h, reason)

    def _stop_all(self, reason: str) -> None:
        for dep in self.apps.values():
            self._stop_app(dep, reason)

    def on_vertex(self, res: fx.VertexResult, now: float) -> list[Effect]:
        """A result from the executor (drivers call this, like ``receive``)."""
        self._now = now
        owner = self._instances.get(res.instance)
        dep = self.apps.get(owner[0]) if owner is not None else None
        if owner is None or dep is None:
            return []  # stopped meanwhile
        vid = owner[1]
        h = dep.stones.get(vid) or dep.awaiting.get(vid)
        if h is None or h.instance != res.instance:
            return []
        h.jobs -= 1
        h.busy_since = now if h.jobs else None
        h.cpu_s += res.cpu_s
        self.cpu_ms += res.cpu_s * 1e3
        h.errors += res.errors
        h.last_error = res.last_error or h.last_error
        h.stats, h.state_size = res.stats, res.state_size
        if isinstance(res, fx.VertexStarted):
            self._started(dep, vid, h, res, now)
        elif isinstance(res, fx.VertexProcessed):
            self._processed(dep, vid, h, res, now)
        elif isinstance(res, fx.VertexEmitted):
            self._emitted(dep, vid, h, res, now)
        else:
            self._snapshotted(dep, vid, h, res)
        return self._run(now)

    def _started(
        self, dep: Deployment, vid: str, h: Hosted, res: fx.VertexStarted, now: float
    ) -> None:
        prep = dep.preparing.pop(vid, None)
        if res.error:  # user code failing at construction: refuse, change nothing
            self._stop(h, "failed")
            dep.stones.pop(vid, None)
            dep.awaiting.pop(vid, None)
            for ci, (_, starting) in list(dep.building.items()):
                if vid in starting:
                    del dep.building[ci]
                    self._send(dep.origin, m.DeployFailed(dep.app.name, f"{self.id}: {res.error}"))
            if prep is not None:
                dep.restoring.pop(vid, None)
                self._handover_to.pop(prep[0], None)
                error = f"{self.id}: {res.error}"
                self._send(prep[1], m.Prepared(dep.app.name, vid, prep[0], self.id, error))
            return
        h.started, h.mode = True, res.mode
        for ci, (asker, starting) in list(dep.building.items()):
            starting.discard(vid)
            if not starting:
                del dep.building[ci]
                self._send(asker, m.ChainPartReady(dep.app.name, ci, self.id))
        if prep is not None:
            rid, coordinator, restore = prep
            self._send(coordinator, m.Prepared(dep.app.name, vid, rid, self.id, ""))
            restoring = dep.restoring.get(vid)
            if restore and restoring is not None and not restoring.pending:
                self._activate(dep, vid)  # nothing to wait for (a lone vertex)
        if h.kind == "source" and vid in dep.stones:
            self._start_source(dep, vid, now)

    # -- data plane -------------------------------------------------------------------------
    def _out(self, dep: Deployment, edge: int) -> OutChannel:
        ch = dep.out.get(edge)
        if ch is None:
            ch = dep.out[edge] = OutChannel(window=self.window)
        return ch

    def _start_source(self, dep: Deployment, vid: str, now: float) -> None:
        h = dep.stones[vid]
        if not h.started or not dep.running:
            return
        if h.mode == "loop":
            self._grant(dep, vid)
            return
        h.t0, h.asked = now, 0
        self._effects.append(SetTimer(("source", dep.app.name, vid), now))

    def _room(self, dep: Deployment, vid: str) -> int:
        return min((self._out(dep, e).room for e in dep.out_edges.get(vid, [])), default=SOURCE_RUN)

    def _source_tick(self, app: str, vid: str, now: float) -> None:
        """A rated source keeps its schedule: event k is due at t0 + k / rate; a late tick
        asks for every event due since (up to the window), so the rate holds on average."""
        dep = self.apps.get(app)
        h = dep.stones.get(vid) if dep is not None else None
        if dep is None or h is None or not dep.running or not h.started or h.jobs:
            return  # a run in flight schedules the next tick when it is done
        rate = h.rate
        due = int((now - h.t0) * rate + 1e-9) + 1 - h.asked
        room = self._room(dep, vid)
        n = min(due, room, SOURCE_RUN)
        if n <= 0:
            if room <= 0:  # backpressure: a full window holds the source until an ack
                dep.blocked_sources.add(vid)
            else:
                self._effects.append(SetTimer(("source", app, vid), h.t0 + h.asked / rate))
            return
        self._submit(h, fx.RunSource(h.instance, h.asked, n, now))
        h.asked += n

    def _grant(self, dep: Deployment, vid: str) -> None:
        """A free-running source may make as many calls as its window has room for."""
        h = dep.stones[vid]
        if not h.started or h.ended or not dep.running:
            return
        room = self._room(dep, vid) - h.credit
        if room > 0 and (h.credit == 0 or room >= min(FEED_BATCH, self.window // 4)):
            h.credit += room
            self._effects.append(fx.Credit(h.instance, room))

    def _emitted(
        self, dep: Deployment, vid: str, h: Hosted, res: fx.VertexEmitted, now: float
    ) -> None:
        h.calls += res.calls
        self.work_ms += h.vertex.cost * res.calls
        edges = dep.out_edges.get(vid, [])
        if res.outputs:
            h.emitted += len(res.outputs)
            h.bytes_out += self._emit(dep, edges, res.outputs, now, -1) * len(edges)
        if h.mode == "loop":
            h.credit -= res.calls
            h.ended = res.ended
            self._grant(dep, vid)
        elif dep.running:
            at = h.t0 + h.asked / h.rate
            self._effects.append(SetTimer(("source", dep.app.name, vid), max(at, now)))

    def _emit(
        self, dep: Deployment, edges: Iterable[int], payloads: list[bytes], ts: float, chain: int
    ) -> int:
        """Send encoded events on every edge in ``edges``; returns their size in bytes.
        ``ts`` is when they entered chain ``chain``: an edge of that chain carries it on, an
        edge that starts another chain starts it from now."""
        for e in edges:
            if e in dep.parked_edges:
                dep.dropped[e] = dep.dropped.get(e, 0) + len(payloads)
                continue
            seq = self._out(dep, e).push_many(payloads, self._now)
            dst_node = dep.placed[dep.app.edges[e].dst]
            t = ts if dep.layout.edge_chain[e] == chain else self._now
            if dst_node == self.id:
                self._deliver(dep, e, seq, payloads, t)
            else:
                key = (dep.app.name, e)
                batch = self._outbox.get(key)
                if batch is None:
                    self._outbox[key] = batch = (seq, list(payloads), t)
                else:
                    batch[1].extend(payloads)
                if len(batch[1]) * len(payloads[0]) >= MAX_BATCH_BYTES:  # frames stay small
                    del self._outbox[key]
                    data = m.Data(dep.app.name, e, dep.epoch, batch[0], batch[1], batch[2])
                    self._effects.append(Send(dst_node, data))
        return sum(map(len, payloads))

    def _deliver(
        self, dep: Deployment, edge: int, seq: int, events: list[bytes], ts: float = 0.0
    ) -> None:
        dst = dep.app.edges[edge].dst
        if dst in dep.awaiting:  # moving here: keep until the handover
            dep.stash.setdefault(edge, []).append((seq, list(events)))
            return
        ch = dep.inc.get(edge)
        if ch is None:
            ch = dep.inc[edge] = InChannel()
        fresh = ch.accept(seq, events)
        if fresh:
            self._enqueue(dep, dst, (edge, fresh, ts))

    def _enqueue(
        self, dep: Deployment, vid: str, item: tuple[int, list[bytes], float] | m.Marker
    ) -> None:
        """Events and markers for an instance, in arrival order: a marker is handled once
        everything before it has been processed."""
        h = dep.stones.get(vid)
        if h is not None:
            h.pending.append(item)
            self._pump(dep, vid)

    def _pump(self, dep: Deployment, vid: str) -> None:
        """Feed the instance's worker while its bounded queue has room (backpressure: what
        is not fed is not acknowledged, so the producers' windows fill and they stop)."""
        h = dep.stones.get(vid)
        while h is not None and h.pending and h.handing_over is None:
            item = h.pending[0]
            if isinstance(item, m.Marker):
                if h.jobs:
                    return
                h.pending.popleft()
                self._on_marker(dep, item)
                continue
            if h.queued >= QUEUE_EVENTS:
                return
            edge, events, ts = item
            if len(events) > FEED_BATCH:
                feed = events[:FEED_BATCH]
                h.pending[0] = (edge, events[FEED_BATCH:], ts)
            else:
                h.pending.popleft()
                feed = events
            h.bytes_in += sum(map(len, feed))
            self._submit(h, fx.FeedVertex(h.instance, edge, feed, ts), len(feed))

    def _on_data(self, msg: m.Data) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.epoch != dep.epoch or not 0 <= msg.edge < len(dep.app.edges):
            self.dropped_messages += 1
            return
        dst = dep.app.edges[msg.edge].dst
        if dst in dep.awaiting:  # a relocated instance before its handover: keep for later
            dep.stash.setdefault(msg.edge, []).append((msg.seq, msg.events))
            return
        if dst not in dep.stones:
            self.dropped_messages += 1
            return
        self._deliver(dep, msg.edge, msg.seq, msg.events, msg.ts)

    def _processed(
        self, dep: Deployment, vid: str, h: Hosted, res: fx.VertexProcessed, now: float
    ) -> None:
        """A batch went through the edge's consumer: pass its outputs on, acknowledge."""
        edge = res.edge
        h.queued -= res.count
        h.processed += res.count
        self.work_ms += h.vertex.cost * res.count
        ch = dep.inc.get(edge)
        if ch is None:
            return
        ch.mark_processed(res.count)
        chain = dep.layout.edge_chain[edge]
        ts = res.ts
        if ts > 0 and dep.layout.chains[chain].tail == vid:  # end-to-end through the chain
            ms = (now - ts) * 1e3
            old = dep.delays.get(chain)
            dep.delays[chain] = (
                ms if old is None else DELAY_SMOOTHING * ms + (1 - DELAY_SMOOTHING) * old
            )
        out_edges = dep.out_edges.get(vid, [])
        if res.outputs and out_edges:
            h.emitted += len(res.outputs)
            sent = self._emit(dep, out_edges, res.outputs, ts, chain)
            h.bytes_out += sent * len(out_edges)
        if out_edges:  # chained acks: the inputs are acked once the outputs are
            if ch.released is None:
                ch.released = ch._acked
            gate = dep.gates.get(vid)
            if gate is None:
                gate = dep.gates[vid] = AckGate()
            gate.record({edge: ch.processed}, {o: self._out(dep, o).next_seq for o in out_edges})
            self._release(dep, vid)
        elif ch.processed - ch._acked >= ACK_EVERY:
            self._ack(dep, edge)
        self._pump(dep, vid)

    def _release(self, dep: Deployment, vid: str) -> None:
        """Acknowledge the inputs of ``vid`` as far as its outputs have been acknowledged."""
        gate = dep.gates.get(vid)
        if gate is None:
            return
        acked = {o: out.acked for o in dep.out_edges.get(vid, []) if (out := dep.out.get(o))}
        released = gate.release(acked)
        if released is None:
            return
        inputs, outputs = released
        for i, pos in inputs.items():
            ch = dep.inc.get(i)
            if ch is not None:
                ch.released = max(ch.released or 0, pos)
                ch.positions = outputs
                self._ack(dep, i)

    def _ack(self, dep: Deployment, edge: int) -> None:
        upto = dep.inc[edge].ack_due()
        if upto is None:
            return
        ch = dep.inc[edge]
        producer = dep.app.edges[edge].src
        src_node = dep.placed[producer]
        if src_node == self.id:
            out = self._out(dep, edge)
            if upto > out.next_seq:  # this channel never sent that far (a fresh one after a
                self.dropped_messages += 1  # move): nothing to release, never a crash
                return
            out.on_ack(upto, self._now)
            out.positions = ch.positions
            self._unblock(dep, edge)
            self._release(dep, producer)
        elif src_node not in self.dead:
            self._effects.append(
                Send(src_node, m.Ack(dep.app.name, edge, dep.epoch, upto, dict(ch.positions)))
            )

    def _on_ack(self, msg: m.Ack, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.epoch != dep.epoch or msg.edge not in dep.out:
            self.dropped_messages += 1
            return
        out = dep.out[msg.edge]
        try:
            out.on_ack(msg.upto, now)
        except ValueError:
            self.dropped_messages += 1
            return
        if msg.upto >= out.acked:
            out.positions = msg.positions
        self._unblock(dep, msg.edge)
        self._release(dep, dep.app.edges[msg.edge].src)

    def _unblock(self, dep: Deployment, edge: int) -> None:
        """An ack freed room on ``edge``: wake its producer if backpressure stopped it. A
        rated source skips the time it was held (a sensor does not deliver missed samples)."""
        producer = dep.app.edges[edge].src
        h = dep.stones.get(producer)
        if h is None or h.kind != "source":
            return
        if h.mode == "loop":
            self._grant(dep, producer)
        elif producer in dep.blocked_sources:
            dep.blocked_sources.discard(producer)
            h.t0 = self._now - h.asked / h.rate
            self._effects.append(SetTimer(("source", dep.app.name, producer), self._now))

    def _flush(self) -> None:
        for (app, edge), batch in self._outbox.items():
            dep = self.apps[app]
            dst = dep.placed[dep.app.edges[edge].dst]
            self._effects.append(Send(dst, m.Data(app, edge, dep.epoch, *batch)))
        self._outbox.clear()
        for dep in self.apps.values():
            for edge, ch in list(dep.inc.items()):
                if ch.reack or ch.processed != ch._acked:
                    self._ack(dep, edge)

    def _retransmit(self, app: str, now: float) -> None:
        """Go-back-N: resend what has waited a whole period without any ack progress."""
        dep = self.apps.get(app)
        if dep is None or not dep.running:
            return
        for edge, ch in dep.out.items():
            if ch.overdue(now, RETRANSMIT_S):
                dst = dep.placed[dep.app.edges[edge].dst]
                if dst in self.dead:  # held until the consumer is restored elsewhere
                    continue
                first, events = ch.unacked()
                if dst == self.id:
                    self._deliver(dep, edge, first, events)
                else:
                    self._effects.append(Send(dst, m.Data(app, edge, dep.epoch, first, events)))
                ch.waiting_since = now
        self._effects.append(SetTimer(("retransmit", app), now + RETRANSMIT_S))

    # -- relocation (§3.4.1) with a marker and state handover -------------------------------
    def _refuse(self, client: int | None, msg: m.RelocateRequest, reason: str) -> None:
        if client is not None:
            reply = m.RelocateReply(msg.app, msg.vertex, False, error=reason)
            self._effects.append(Reply(client, reply))

    def relocation_target(self, dep: Deployment, vertex: str, direction: str = "") -> str:
        """Where an upstream or downstream relocation takes ``vertex`` (MsoError if it cannot
        move): upstream is its predecessor's node; downstream is its successor's node or, when
        they share a node, the next node toward the chain's tail."""
        app, lay = dep.app, dep.layout
        if vertex not in app.vertices:
            raise MsoError(f"unknown vertex {vertex!r} in app {app.name!r}")
        for c in lay.chains:
            if vertex in (c.head, c.tail):
                raise MsoError(
                    f"{vertex!r} is an end of chain {c.name}; chain ends are never relocated "
                    f"(it would disturb the chains before or after it)"
                )
        pinned = app.vertices[vertex].pinned
        if pinned is not None:
            raise MsoError(f"{vertex!r} is pinned to {pinned}; pinned vertices are not relocated")
        if not direction:
            return ""
        (pred,) = app.predecessors()[vertex]
        (succ,) = app.successors()[vertex]
        here = dep.placed[vertex]
        if direction == "upstream":
            target = dep.placed[pred]
        elif direction == "downstream":
            target = dep.placed[succ]
            if target == here:
                tail = dep.placed[next(c for c in lay.chains if vertex in c.vertices).tail]
                route = self.routes.get(tail) if here == self.id else None
                target = route[0] if route else tail
        else:
            raise MsoError(f"expected direction 'upstream' or 'downstream', got {direction!r}")
        if target == here:
            where = "predecessor's" if direction == "upstream" else "next downstream"
            raise MsoError(f"{vertex!r} already runs on its {where} node {here}")
        return target

    def relocate(self, req: m.RelocateRequest, now: float) -> None:
        """Start a relocation this node coordinates (the management rules' entry point)."""
        self._relocate_request(None, req, now)

    def remap(self, req: m.RemapRequest, now: float) -> None:
        """Start a chain or global remap this node coordinates."""
        self._remap_request(None, req, now)

    def _relocate_request(self, client: int | None, msg: m.RelocateRequest, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not dep.running:
            self._refuse(client, msg, f"no running app named {msg.app!r}")
            return
        try:
            target = self.relocation_target(dep, msg.vertex, "" if msg.target else msg.direction)
        except MsoError as exc:
            self._refuse(client, msg, str(exc))
            return
        target = msg.target or target
        if target != self.id and target not in self.routes:
            self._refuse(client, msg, f"target node {target!r} is not reachable")
            return
        source = dep.placed[msg.vertex]
        if target == source:
            self._refuse(client, msg, f"{msg.vertex!r} already runs on {target}")
            return
        if any(r.app == msg.app and r.vertex == msg.vertex for r in self._relocations()):
            self._refuse(client, msg, f"{msg.vertex!r} is already being relocated")
            return
        self._rid += 1
        self._begin(Relocation(self._rid, now, msg.app, msg.vertex, source, target, client))
        self._send(target, m.Prepare(msg.app, msg.vertex, self._rid))

    def _on_prepare(self, src: str, msg: m.Prepare) -> None:
        """At a relocation's (or restore's) target: create the new instance; it is
        Prepared once the executor has started it (or refused if its code fails)."""
        dep = self.apps.get(msg.app)
        error = ""
        vid = msg.vertex
        if dep is None:
            error = f"{self.id} does not run app {msg.app!r}"
        elif vid not in dep.app.vertices:
            error = f"{self.id}: unknown vertex {vid!r}"
        elif vid not in dep.stones and vid not in dep.awaiting:
            dep.awaiting[vid] = self._host(dep, vid)
            dep.preparing[vid] = (msg.rid, src, msg.restore)
            self._handover_to[msg.rid] = src
            if msg.restore:
                pending = {(int(e), bool(p)) for e, p in msg.resumes}
                dep.restoring[vid] = Restoring(msg.rid, src, pending)
            return
        elif msg.restore and vid in dep.stones:  # it never went: nothing to restore
            self._send(src, m.Prepared(msg.app, vid, msg.rid, self.id, error))
            self._send(src, m.HandoverDone(dep.app.name, vid, msg.rid))
            self._broadcast(m.Moved(dep.app.name, vid, self.id))
            return
        elif msg.restore and vid in dep.awaiting:  # asked again, maybe by a new
            old = dep.restoring.get(vid)  # coordinator after the first one failed
            if old is None or old.rid != msg.rid:
                pending = {(int(e), bool(p)) for e, p in msg.resumes}
                dep.restoring[vid] = Restoring(msg.rid, src, pending)
                self._handover_to[msg.rid] = src
            if vid in dep.preparing:  # still starting: Prepared goes to the newest asker
                dep.preparing[vid] = (msg.rid, src, True)
                return
        self._send(src, m.Prepared(msg.app, vid, msg.rid, self.id, error))
        if dep is not None and not error and msg.restore:
            restoring = dep.restoring.get(vid)
            if restoring is not None and not restoring.pending:
                self._activate(dep, vid)  # nothing to wait for (a lone vertex)

    def _reloc_failed(self, reloc: Relocation, why: str, now: float) -> None:
        """A relocation or restore failed: whoever waits (a client, a remap) is told."""
        reloc.fail(self, why)
        self._end(reloc.pid)
        if self._remap(reloc.remap) is not None:
            assert reloc.remap is not None
            self._finish_remap(reloc.remap, now, why)
        else:
            self._refuse(reloc.client, m.RelocateRequest(reloc.app, reloc.vertex), why)

    def _on_prepared(self, msg: m.Prepared, now: float) -> None:
        reloc = self._reloc(msg.rid)
        dep = self.apps.get(msg.app)
        if reloc is None or dep is None:
            return
        if msg.error:
            self._reloc_failed(reloc, msg.error, now)
            return
        reloc.on("prepared_restore" if reloc.restore else "prepared")
        if reloc.restore:  # the surviving ends of its edges resume the replacement
            edges = dep.app.edges
            for edge, producer in reloc.resumes:
                other = dep.placed[edges[edge].src if producer else edges[edge].dst]
                self._send(other, m.Rewire(msg.app, edge, reloc.target, msg.rid, producer))
            return
        for e in dep.app.edges:
            if e.dst == msg.vertex:
                edge = dep.app.edges.index(e)
                self._send(dep.placed[e.src], m.Switch(msg.app, edge, reloc.target, msg.rid))

    def _on_switch(self, msg: m.Switch) -> None:
        """At the producer's node: new events go to the new instance; a marker goes the old way."""
        dep = self.apps.get(msg.app)
        if dep is None:
            return
        edge = dep.app.edges[msg.edge]
        old = dep.placed[edge.dst]
        key = (msg.app, msg.edge)
        batch = self._outbox.pop(key, None)
        if batch is not None:  # what is already queued leaves before the marker
            data = m.Data(msg.app, msg.edge, dep.epoch, *batch)
            self._effects.append(Send(old, data))
        seq = self._out(dep, msg.edge).next_seq
        dep.placed[edge.dst] = msg.to
        marker = m.Marker(msg.app, msg.edge, seq, msg.rid, msg.to)
        if old == self.id:
            self._enqueue(dep, edge.dst, marker)
        else:
            self._effects.append(Send(old, marker))

    def _on_marker(self, dep: Deployment, msg: m.Marker) -> None:
        """At the old instance's node: once every input is marked, hand the state over."""
        vid = dep.app.edges[msg.edge].dst
        h = dep.stones.get(vid)
        if h is None:
            return
        marked = dep.markers.setdefault(vid, set())
        marked.add(msg.edge)
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        if not set(ins) <= marked:
            return
        del dep.markers[vid]
        h.handing_over = msg  # the state is taken once everything before is processed
        self._submit(h, fx.SnapshotVertex(h.instance, msg.rid))

    def _snapshotted(self, dep: Deployment, vid: str, h: Hosted, res: fx.VertexSnapshot) -> None:
        """The old instance's state is taken: hand it and the channels over, then free it."""
        msg = h.handing_over
        if msg is None:
            return
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        for i in ins:  # acknowledge what the old instance processed, then forget the inputs
            self._ack(dep, i)
        inputs = {
            i: [ch.expected, ch._acked] if (ch := dep.inc.pop(i, None)) else [0, 0] for i in ins
        }
        outputs: dict[int, list[Any]] = {}
        for i in dep.out_edges.get(vid, []):
            out = dep.out.pop(i, None)
            if out is not None:
                _, events = out.unacked()
                outputs[i] = [out.next_seq, out.acked, events, out.positions]
        gate = dep.gates.pop(vid, None)
        key_batches = [k for k in self._outbox if k[0] == dep.app.name and k[1] in outputs]
        for k in key_batches:  # queued output leaves from here before the handover
            batch = self._outbox.pop(k)
            dst = dep.placed[dep.app.edges[k[1]].dst]
            self._effects.append(Send(dst, m.Data(k[0], k[1], dep.epoch, *batch)))
        self._stop(h, "moved")
        del dep.stones[vid]
        dep.placed[vid] = msg.to
        handover = m.Handover(
            dep.app.name,
            vid,
            msg.rid,
            res.state,
            inputs,
            outputs,
            h.processed,
            h.emitted,
            gate.to_wire() if gate is not None else [],
        )
        self._send(msg.to, handover)
        self._broadcast(m.Moved(dep.app.name, vid, msg.to))

    def _on_handover(self, src: str, msg: m.Handover, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.vertex not in dep.awaiting:
            return
        dep.moved[msg.vertex] = (now, src)
        h = dep.awaiting.pop(msg.vertex)
        self._effects.append(fx.RestoreVertex(h.instance, msg.state))  # before any feed
        h.processed, h.emitted = msg.processed, msg.emitted
        dep.stones[msg.vertex] = h
        dep.placed[msg.vertex] = self.id
        gated = bool(dep.out_edges.get(msg.vertex))
        for i, (expected, acked) in msg.inputs.items():
            dep.inc[i] = InChannel(
                expected=expected,
                processed=expected,
                _acked=acked,
                released=acked if gated else None,
            )
        for i, (next_seq, acked, events, positions) in msg.outputs.items():
            ch = OutChannel(window=self.window, next_seq=acked, acked=acked, waiting_since=now)
            ch.push_many(events, now)
            ch.next_seq = next_seq
            ch.positions = {int(k): int(v) for k, v in positions.items()}
            dep.out[i] = ch
        if msg.gate:
            dep.gates[msg.vertex] = AckGate.from_wire(msg.gate)
        for i in msg.inputs:  # what arrived early, in order, now that positions are known
            for seq, events in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                self._deliver(dep, i, seq, events)
        coordinator = self._handover_to.pop(msg.rid, None)
        if coordinator is not None:
            self._send(coordinator, m.HandoverDone(msg.app, msg.vertex, msg.rid))

    def _on_handover_done(self, msg: m.HandoverDone, now: float) -> None:
        reloc = self._reloc(msg.rid)
        if reloc is not None:
            reloc.on("handed_over")
            self._end(reloc.pid)
        if reloc is not None and reloc.restore:
            dep = self.apps.get(reloc.app)
            if dep is not None:
                dep.placed[reloc.vertex] = reloc.target
        if reloc is not None and reloc.remap is not None:
            self._remap_step(reloc.remap, now, moved=(reloc.vertex, reloc.target))
            return
        if reloc is None or reloc.client is None:
            return
        reply = m.RelocateReply(
            reloc.app, reloc.vertex, True, reloc.target, self._elapsed_ms(reloc.started_at)
        )
        self._effects.append(Reply(reloc.client, reply))

    # -- chain remap (§3.4.2) and global remap (§3.4.3) --------------------------------------
    def _remap_request(self, client: int | None, msg: m.RemapRequest, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not dep.running:
            self._remap_refuse(client, msg.app, f"no running app named {msg.app!r}")
            return
        lay = dep.layout
        bad = [c for c in msg.chains if not 0 <= c < len(lay.chains)]
        if bad or (not msg.chains and not msg.everything):
            reason = f"unknown chain {bad[0]}" if bad else "name the chains to remap, or all"
            reason += f" (chains 0..{len(lay.chains) - 1})"
            self._remap_refuse(client, msg.app, reason)
            return
        wanted = set(range(len(lay.chains))) if msg.everything else set(msg.chains)
        order = [c for c in lay.order if c in wanted]
        # what stays: everything outside the set, pinned vertices, the heads of chains fed from
        # outside the set (sources included), and a lone chain's head and tail (§3.4.2)
        chains = [lay.chains[c] for c in order]
        in_set = {v for c in chains for v in c.vertices}
        tails = {c.tail for c in chains}
        ends = {chains[0].head, chains[0].tail} if len(chains) == 1 else set()
        stays = {v for v in dep.placed if v not in in_set or v in lay.pinned or v in ends}
        stays |= {c.head for c in chains if c.head not in tails}
        placed = {v: dep.placed[v] for v in stays}
        movable = in_set - stays
        self._rid += 1
        self._begin(Remap(self._rid, now, msg.app, order, client, placed, movable))
        self._remap_next_chain(self._rid, now)

    def _remap_refuse(self, client: int | None, app: str, reason: str) -> None:
        if client is not None:
            self._effects.append(Reply(client, m.RemapReply(app, False, {}, error=reason)))

    def _remap_next_chain(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if not remap.chains:
            remap.on("placed_all")
            order = {v: i for i, v in enumerate(dep.app.topological_order())}
            moves = [
                (v, n)
                for v, n in remap.placed.items()
                if (v in remap.movable and dep.placed.get(v) != n) or v in dep.vanished
            ]
            # replacements for lost instances first (upstream first, so each one's producer
            # is running when it resumes), then the relocations of live ones
            lost = self._lost(dep)
            moves.sort(key=lambda vn: (vn[0] not in lost, order[vn[0]]))
            remap.moves = moves
            self._remap_step(rid, now)
            return
        ci = remap.chains[0]
        lay = dep.layout
        head = lay.chains[ci].head
        if head not in remap.placed:
            remap.placed[head] = self._live_home(dep, head, remap.placed)
        target, _ = lay.target(ci, remap.placed, self._distances())
        pairs = lay.probes_needed(ci, remap.placed, target)
        remap.probes, remap.expected = {}, len(pairs)
        if not pairs:
            self._remap_place(rid, now)
            return
        remap.on("probe")
        remap.probe_attempts += 1
        for k, (a, b) in enumerate(pairs):  # chain -1 - rid marks a remap's probe
            self._send(a, m.Probe(remap.app, -1, rid * 1000 + k, self.id, b, [], []))
        self._effects.append(SetTimer(Retry(rid, remap.probe_attempts), now + STEP_TIMEOUT_S))

    def _live_home(self, dep: Deployment, vertex: str, placed: dict[str, str]) -> str:
        """Where a vertex stays during a remap: its node, or if that failed, its first
        predecessor's (an upstream move), or for a lost unpinned source, this node."""
        node = dep.placed[vertex]
        if node not in self.dead:
            return node
        for pred in dep.app.predecessors()[vertex]:
            home = placed.get(pred, dep.placed[pred])
            if home not in self.dead:
                return home
        return self.id

    def _remap_probe_timeout(self, rid: int, attempt: int, now: float) -> None:
        """A probe was lost (a route through a failed node): probe again, a few times."""
        remap = self._remap(rid)
        if remap is None or attempt != remap.probe_attempts or len(remap.probes) >= remap.expected:
            return
        if remap.probe_attempts >= PROBE_ATTEMPTS:
            self._finish_remap(rid, now, "probes along the chain's route were not answered")
            return
        if remap.recovery is not None:
            remap.recovery["retried"].append(f"probe {remap.chains[0]}")
        self._remap_next_chain(rid, now)

    def _on_remap_probe(self, msg: m.ProbeReply) -> None:
        rid, k = divmod(msg.segment, 1000)
        remap = self._remap(rid)
        if remap is None or k in remap.probes or remap.state is not RemapState.PROBING:
            return
        remap.probes[k] = [Hop(n, c) for n, c in zip(msg.nodes, msg.capacities, strict=False)]
        if len(remap.probes) == remap.expected:
            self._remap_place(rid, self._now)

    def _remap_place(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        remap.on("placed")
        ci = remap.chains.pop(0)
        remap.probe_attempts = 0
        by_pair = {(h[0].node, h[-1].node): h for h in remap.probes.values() if h}
        try:
            assigned, _ = dep.layout.place(
                ci, remap.placed, lambda a, b: by_pair.get((a, b), []), self._distances()
            )
        except MsoError as exc:
            self._finish_remap(rid, now, str(exc))
            return
        remap.placed.update(assigned)
        self._remap_next_chain(rid, now)

    def _remap_step(self, rid: int, now: float, moved: tuple[str, str] | None = None) -> None:
        """Relocate (or, if its node failed, restore) the next vertex whose node changed;
        done when none is left."""
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if moved is not None:
            remap.on("moved")
            remap.moved[moved[0]] = moved[1]
        while remap.moves:
            vertex, node = remap.moves.pop(0)
            lost = dep.placed[vertex] in self.dead or vertex in dep.vanished
            if dep.placed.get(vertex) == node and not lost:
                continue
            if dep.layout.kinds[vertex] == "source" and not lost:
                continue
            self._rid += 1
            source = dep.placed[vertex]
            reloc = Relocation(self._rid, now, remap.app, vertex, source, node, None, remap=rid)
            self._begin(reloc)
            if lost:
                self._restore(dep, reloc, self._rid, now)
            else:
                self._send(node, m.Prepare(remap.app, vertex, self._rid))
            return
        remap.on("all_moved")
        self._finish_remap(rid, now, "")

    def _finish_remap(self, rid: int, now: float, error: str) -> None:
        remap = self._remap(rid)
        if remap is None:
            return
        if error:
            remap.fail(self, error)
        self._end(rid)
        if remap.client is not None:
            elapsed = self._elapsed_ms(remap.started_at)
            reply = m.RemapReply(remap.app, not error, remap.moved, elapsed, error)
            self._effects.append(Reply(remap.client, reply))
        dep = self.apps.get(remap.app)
        if remap.recovery is not None and dep is not None:
            remap.recovery.update(
                moved=dict(remap.moved),
                ok=not error,
                error=error,
                took_ms=round(self._elapsed_ms(remap.started_at), 3),
            )
            dep.recovering = None
            if error:  # e.g. no route yet to a node that is about to be declared failed too:
                # try again later (sooner if routes or failures change), never in a loop
                key = ("recover", dep.app.name)
                self._effects.append(SetTimer(key, now + STEP_TIMEOUT_S))
            else:
                self._maybe_recover(dep, now)  # another failure may have happened meanwhile

    def _report_delays(self, now: float) -> None:
        """Tell each chain's head node the delay measured at its tail (here)."""
        for dep in self.apps.values():
            for chain, ms in dep.delays.items():
                head = dep.placed[dep.layout.chains[chain].head]
                if head == self.id:
                    dep.chain_delay[chain] = (ms, now)
                elif head not in self.dead:
                    self._send(head, m.ChainDelay(dep.app.name, chain, ms))

    # -- fail-stop failures (§3.4, assumption 3) --------------------------------------------
    def _beat(self) -> m.Heartbeat:
        mon, pw = self.monitor, self.power
        return m.Heartbeat(
            self.id,
            self.capacity,
            mon.load,
            mon.drain_w,
            mon.remaining_j,
            mon.lifetime_s,
            [pw.idle_w, pw.cpu_w, pw.tx_uj_per_byte, pw.rx_uj_per_byte],
            self.incarnation,
            dict(self._dead_incarnation),
            self._leader(),
            self._hosting(),
        )

    def _heartbeat(self, now: float) -> None:
        """Tell the neighbours we live (with our figures); declare the silent ones failed."""
        beat = self._beat()
        for n in sorted(self.liveness.neighbours):
            if n not in self.dead:
                self._effects.append(Send(n, beat))
        self._beats += 1
        if self._beats % REJOIN_EVERY == 0:  # a failed node we can reach again: a healed
            for n in sorted(self.dead):  # partition; tell it, so one side rejoins the other
                if n in self.routes:
                    self._effects.append(Send(n, beat))
        for n in self.liveness.suspects(now, self.dead):
            self._on_node_down(n, self.id, now)
        self._effects.append(SetTimer(("heartbeat",), now + self.liveness.period_s))

    def _on_node_down(
        self, node: str, detector: str, now: float, incarnation: int | None = None
    ) -> None:
        if node in self.dead or node == self.id:
            return
        known = self._incarnations.get(node, 0)
        if incarnation is not None and incarnation < known:
            return  # that incarnation failed, and a newer one is already back
        self.dead.add(node)
        self._dead_incarnation[node] = known if incarnation is None else incarnation
        self.liveness.forget(node)
        self.failures.append({"node": node, "detector": detector, "at": now})
        del self.failures[:-50]
        self.monitor.note_event(now, f"node {node} failed (detected by {detector})")
        if detector == self.id:  # tell everyone; the others learn it from us or another detector
            for n in self.known_nodes():
                if n != self.id and n not in self.dead:
                    self._send(n, m.NodeDown(node, self.id, self._dead_incarnation[node]))
        for reloc in self._relocations():  # moves that needed the failed node
            if not reloc.restore and node in (reloc.source, reloc.target):
                reason = f"node {node} failed during the relocation of {reloc.vertex!r}"
                self._reloc_failed(reloc, reason, now)
        for dep in list(self.apps.values()):
            self._park(dep)
            self._maybe_recover(dep, now)

    def _park(self, dep: Deployment) -> None:
        """Chains with a vertex pinned to a failed node cannot run anywhere: park them. Their
        edges stop carrying events (counted as dropped), so a dead sink on one branch does not
        hold back, through acks and backpressure, the branches that still run."""
        for ci, chain in enumerate(dep.layout.chains):
            for v in chain.vertices:
                pin = dep.app.vertices[v].pinned
                if pin in self.dead and ci not in dep.parked:
                    dep.parked[ci] = f"{v!r} is pinned to failed node {pin}"
        edges = {e for e, c in enumerate(dep.layout.edge_chain) if c in dep.parked}
        for e in sorted(edges - dep.parked_edges):
            out = dep.out.get(e)
            if out is not None and out.in_flight:
                dep.dropped[e] = dep.dropped.get(e, 0) + out.in_flight
                out.on_ack(out.next_seq, self._now)
                producer = dep.app.edges[e].src
                if producer in dep.stones:
                    self._release(dep, producer)
                self._unblock(dep, e)
        dep.parked_edges |= edges

    def _lost(self, dep: Deployment) -> set[str]:
        """Vertices with no running instance: on a failed node, or gone with a node's old
        incarnation."""
        return {v for v, n in dep.placed.items() if n in self.dead} | dep.vanished

    # -- membership: restarts and healed partitions -----------------------------------------
    def _leader(self) -> str:
        return min({self.id, *(n for n in self.routes if n not in self.dead)})

    def _on_heartbeat(self, src: str, msg: m.Heartbeat, now: float) -> None:
        known = self._incarnations.get(src)
        if known is not None and msg.incarnation > known:  # it restarted: its instances went
            self._on_node_down(src, self.id, now)
            self._rejoin(src, msg.incarnation, now, announce=True)
            return
        self._incarnations[src] = msg.incarnation
        if self.routes.get(src, ("", 0))[0] == src:  # a neighbour's beat, not a hello
            self.liveness.heard_from(src, now, msg)
        if msg.dead.get(self.id) == self.incarnation and self._outranked_by(msg):
            self._reset(now, src)
        else:
            self._answer_stale_claim(src, msg)

    def _answer_stale_claim(self, src: str, msg: m.Heartbeat) -> None:
        """``src`` holds an older incarnation of ours failed: our beat tells it we are back."""
        claim = msg.dead.get(self.id)
        if claim is not None and claim < self.incarnation:
            self._send(src, self._beat())

    def _on_dead_heartbeat(self, src: str, msg: m.Heartbeat, now: float) -> None:
        """A node we declared failed is heard again: it restarted (a higher incarnation), or
        a partition healed. Then the side that loses the tie-break resets and rejoins."""
        if msg.incarnation > self._dead_incarnation.get(src, 0):
            self._rejoin(src, msg.incarnation, now, announce=True)
        elif msg.dead.get(self.id) == self.incarnation and self._outranked_by(msg):
            self._reset(now, src)
        else:
            self._answer_stale_claim(src, msg)

    def _hosting(self) -> int:
        return sum(len(dep.stones) for dep in self.apps.values())

    def _outranked_by(self, msg: m.Heartbeat) -> bool:
        """After a partition both sides may hold the other failed. A node that runs nothing
        yields to one that runs something (it loses nothing by resetting); otherwise the side
        that counts fewer failed nodes (the larger one), then the one with the lower leader,
        stays and the other resets. One-sided (we hold the sender alive), we reset."""
        if msg.node not in self.dead:
            return True

        def rank(hosting: int, dead: int, leader: str) -> tuple[bool, int, str]:
            return (hosting == 0, dead, leader)

        theirs = rank(msg.hosting, len(msg.dead), msg.leader or msg.node)
        return theirs < rank(self._hosting(), len(self.dead), self._leader())

    def _reset(self, now: float, by: str) -> None:
        """Rejoin as a new incarnation: the others have recovered without this node's
        instances, so it drops them (and every app) and is told the apps again."""
        dropped = sorted(self.apps)
        self._stop_all("reset")
        self.apps.clear()
        for pid in list(self.procedures):  # nobody waits for them any more
            self._end(pid)
        self._outbox.clear()
        self._early.clear()
        self._handover_to.clear()
        self._probes_waiting.clear()
        self._stop_all("reset")
        for node in self.dead:
            self.liveness.rejoin(node, now, node in self.routes, self.routes.get(node))
        self.dead.clear()
        self._dead_incarnation.clear()
        self.incarnation += 1
        self.monitor.note_event(
            now,
            f"declared failed by {by}: rejoined as incarnation {self.incarnation}"
            + (f", dropping {', '.join(dropped)}" if dropped else ""),
        )
        self._heartbeat(now)
        beat = self._beat()
        for n in sorted(self.routes):  # everyone learns the new incarnation, not just neighbours
            if n not in self.liveness.neighbours:
                self._send(n, beat)

    def _rejoin(self, node: str, incarnation: int, now: float, announce: bool) -> None:
        """``node`` is back with no instances: restore what it hosted, unpark what was pinned
        to it, and tell it the apps."""
        self.dead.discard(node)
        self._dead_incarnation.pop(node, None)
        self._incarnations[node] = incarnation
        self.liveness.rejoin(node, now, node in self.routes, self.routes.get(node))
        self.rejoins.append({"node": node, "incarnation": incarnation, "at": now})
        del self.rejoins[:-50]
        self.monitor.note_event(now, f"node {node} rejoined (incarnation {incarnation})")
        if announce:
            for n in self.known_nodes():
                if n not in (self.id, node) and n not in self.dead:
                    self._send(n, m.NodeUp(node, incarnation))
        for dep in list(self.apps.values()):
            dep.vanished |= {v for v, n in dep.placed.items() if n == node}
            self._unpark(dep)
            if not dep.running:
                continue
            sync = m.AppSync(
                dep.app.name,
                dep.origin,
                dep.document,
                dep.epoch,
                dict(dep.placed),
                sorted(dep.vanished),
            )
            self._send(node, sync)
            self._maybe_recover(dep, now)

    def _on_node_up(self, msg: m.NodeUp, now: float) -> None:
        if msg.node == self.id:
            return
        if msg.node not in self.dead and msg.node not in self._incarnations:
            self._incarnations[msg.node] = msg.incarnation
            return
        if msg.node in self.dead:
            if msg.incarnation > self._dead_incarnation.get(msg.node, 0):
                self._rejoin(msg.node, msg.incarnation, now, announce=False)
        elif msg.incarnation > self._incarnations.get(msg.node, msg.incarnation):
            self._on_node_down(msg.node, msg.node, now)  # restarted unnoticed by us
            self._rejoin(msg.node, msg.incarnation, now, announce=False)

    def _on_app_sync(self, msg: m.AppSync, now: float) -> None:
        if msg.app in self.apps:
            return
        try:
            app = loads_app(msg.document, file=f"<{msg.app}>")
            self.manager.app_policy(app.name, app.policy, where=f"{self.id}: {app.name}: policy")
        except MsoError as exc:
            self.monitor.note_event(now, f"cannot rejoin app {msg.app}: {exc}")
            return
        layout = Layout(app, msg.origin)
        placed = dict(layout.initial_placement()) | {
            v: n for v, n in msg.placed.items() if v in app.vertices
        }
        dep = Deployment(app, layout, msg.origin, placed, epoch=msg.epoch, document=msg.document)
        dep.vanished = {v for v in msg.vanished if v in app.vertices}
        dep.placed_chains = dep.started_chains = set(range(len(layout.chains)))
        dep.running, dep.started_at = True, now
        dep.placed_at = dict.fromkeys(range(len(layout.chains)), now)
        for i, e in enumerate(app.edges):
            dep.out_edges.setdefault(e.src, []).append(i)
        self.apps[msg.app] = dep
        # (re)arm go-back-N for the app: a timer left from before a reset may have lapsed
        self._effects.append(SetTimer(("retransmit", msg.app), now + RETRANSMIT_S))
        self._park(dep)
        self._maybe_recover(dep, now)

    def _unpark(self, dep: Deployment) -> None:
        """Chains parked for a pinned node that is back run again (after their restore)."""
        for ci in list(dep.parked):
            pins = {dep.app.vertices[v].pinned for v in dep.layout.chains[ci].vertices}
            if not pins & self.dead:
                del dep.parked[ci]
        dep.parked_edges = {e for e, c in enumerate(dep.layout.edge_chain) if c in dep.parked}

    def _maybe_recover(self, dep: Deployment, now: float) -> None:
        """Remap the chains that lost vertices with a failed node. Exactly one node acts for
        an app: the lowest-named surviving node that hosts part of it. Every node derives the
        same choice from the same placement and failure set, so two detectors never both
        remap (a coordinator that is itself dead is skipped by the same rule)."""
        if not dep.running or dep.recovering is not None:
            return
        lost = self._lost(dep)
        if not lost:
            return
        live = {n for v, n in dep.placed.items() if v not in lost}
        if min(live, default=None) != self.id:
            return
        if any(d in self.routes for d in self.dead) or any(
            hop in self.dead for hop, _ in self.routes.values()
        ):
            return  # wait for the routing view to route around the failure (set_routes)
        lay = dep.layout
        touched = [
            ci
            for ci, c in enumerate(lay.chains)
            if ci not in dep.parked and any(v in lost for v in c.vertices)
        ]
        if not touched:
            return
        chains = [lay.chains[c] for c in touched]
        in_set = {v for c in chains for v in c.vertices}
        ends = {v for c in chains for v in (c.head, c.tail)}
        stays = {v for v in dep.placed if v not in in_set or v in lay.pinned}
        stays |= {v for v in ends if v not in lost}
        placed = {v: dep.placed[v] for v in stays}
        order = [c for c in lay.order if c in touched]
        kind = "global" if any(v in lost for v in ends) else "chain"
        record: dict[str, Any] = {
            "at": now,
            "failed": sorted(self.dead),
            "remap": kind,
            "chains": [lay.chains[c].name for c in order],
            "lost": sorted(lost),
            "parked": {lay.chains[c].name: why for c, why in sorted(dep.parked.items())},
            "retried": [],  # steps sent again after STEP_TIMEOUT_S (a lost message)
        }
        dep.recoveries.append(record)
        del dep.recoveries[:-20]
        self._rid += 1
        self._begin(
            Remap(self._rid, now, dep.app.name, order, None, placed, in_set - stays, record)
        )
        dep.recovering = self._rid
        self._remap_next_chain(self._rid, now)

    def _restore(self, dep: Deployment, reloc: Relocation, rid: int, now: float) -> None:
        """Start a replacement for ``reloc.vertex`` on ``reloc.target``: its surviving
        producers replay what it had not passed on, its consumers say where they stand."""
        if not reloc.restore:
            reloc.as_restore()
            self._effects.append(SetTimer(Deadline(rid), reloc.deadline))
        edges = dep.app.edges
        lost = self._lost(dep)
        reloc.resumes = [
            [i, True] for i, e in enumerate(edges) if e.dst == reloc.vertex and e.src not in lost
        ] + [[i, False] for i, e in enumerate(edges) if e.src == reloc.vertex and e.dst not in lost]
        reloc.attempts += 1
        prepare = m.Prepare(dep.app.name, reloc.vertex, rid, True, reloc.resumes)
        self._send(reloc.target, prepare)
        self._effects.append(SetTimer(Retry(rid, reloc.attempts), now + STEP_TIMEOUT_S))

    def _step_timeout(self, rid: int, now: float) -> None:
        reloc = self._reloc(rid)
        if reloc is None or not reloc.restore:
            return
        dep = self.apps.get(reloc.app)
        if dep is None:
            return
        if reloc.attempts >= STEP_ATTEMPTS or reloc.target in self.dead:
            why = f"restoring {reloc.vertex!r} on {reloc.target} did not complete"
            self._reloc_failed(reloc, why, now)
            return
        reloc.on("retry")
        remap = self._remap(reloc.remap)
        if remap is not None and remap.recovery is not None:
            remap.recovery["retried"].append(f"restore {reloc.vertex} on {reloc.target}")
        self._restore(dep, reloc, rid, now)  # idempotent at every end: just ask again

    def _on_rewire(self, msg: m.Rewire, now: float) -> None:
        """At a surviving end of an edge whose other end is being replaced on ``msg.to``."""
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            return
        edge = dep.app.edges[msg.edge]
        if msg.producer:  # we produce: say where we stand, then replay what is unacked
            dep.placed[edge.dst] = msg.to
            self._outbox.pop((msg.app, msg.edge), None)  # those events are in the replay
            out = self._out(dep, msg.edge)
            self._send(
                msg.to,
                m.Resume(msg.app, msg.edge, msg.rid, True, out.acked, dict(out.positions)),
            )
            first, events = out.unacked()
            if events:
                data = m.Data(msg.app, msg.edge, dep.epoch, first, events, now)
                if msg.to == self.id:
                    self._work.append((self.id, "", data))
                else:
                    self._effects.append(Send(msg.to, data))
            out.waiting_since = now
        else:  # we consume: say which event we expect next
            dep.placed[edge.src] = msg.to
            inc = dep.inc.get(msg.edge)
            start = inc.expected if inc is not None else 0
            self._send(msg.to, m.Resume(msg.app, msg.edge, msg.rid, False, start))

    def _on_resume(self, msg: m.Resume, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            return
        edge = dep.app.edges[msg.edge]
        vertex = edge.dst if msg.producer else edge.src
        restoring = dep.restoring.get(vertex)
        if restoring is None or restoring.rid != msg.rid:
            return
        if msg.producer:
            gated = bool(dep.out_edges.get(vertex))
            dep.inc[msg.edge] = InChannel(
                expected=msg.start,
                processed=msg.start,
                _acked=msg.start,
                released=msg.start if gated else None,
            )
            for o, pos in msg.positions.items():
                restoring.positions[o] = max(restoring.positions.get(o, 0), pos)
        else:
            restoring.consumer_start[msg.edge] = msg.start
        restoring.pending.discard((msg.edge, msg.producer))
        if not restoring.pending:
            self._activate(dep, vertex)

    def _activate(self, dep: Deployment, vertex: str) -> None:
        """Every surviving end has resumed: the replacement runs. Its output is numbered from
        the positions of the last ack its producers got, so what it regenerates by replay
        carries the numbers it had and consumers drop it as duplicates."""
        restoring = dep.restoring.pop(vertex)
        h = dep.awaiting.pop(vertex)
        dep.moved[vertex] = (self._now, dep.placed[vertex])
        dep.stones[vertex] = h
        dep.placed[vertex] = self.id
        for o in dep.out_edges.get(vertex, []):
            base = restoring.positions.get(o, restoring.consumer_start.get(o, 0))
            dep.out[o] = OutChannel(
                window=self.window, next_seq=base, acked=base, waiting_since=self._now
            )
        for i, e in enumerate(dep.app.edges):  # what arrived early, in order
            if e.dst == vertex:
                for seq, events in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                    self._deliver(dep, i, seq, events)
        self._broadcast(m.Moved(dep.app.name, vertex, self.id))
        self._handover_to.pop(restoring.rid, None)
        self._send(restoring.coordinator, m.HandoverDone(dep.app.name, vertex, restoring.rid))
        if h.kind == "source":
            self._start_source(dep, vertex, self._now)

    # -- status -----------------------------------------------------------------------------
    def status(self, now: float) -> dict[str, Any]:
        apps: dict[str, Any] = {}
        for name, dep in self.apps.items():
            up = max(now - dep.started_at, 1e-9) if dep.running else 0.0
            edges = {}
            for i, e in enumerate(dep.app.edges):
                if i in dep.out or i in dep.inc:
                    inc = dep.inc.get(i)
                    out = dep.out.get(i)
                    sent = out.next_seq if out else 0
                    edges[f"{e.src}->{e.dst}"] = {
                        "sent": sent,
                        "delivered": inc.expected if inc else 0,
                        "duplicates": inc.duplicates if inc else 0,
                        "in_flight": out.in_flight if out else 0,
                        "events_per_s": (sent / up) if up else 0.0,
                    }
            apps[name] = {
                "running": dep.running,
                "parked": {dep.layout.chains[c].name: why for c, why in dep.parked.items()},
                "recoveries": list(dep.recoveries),
                "dropped_parked": {
                    f"{dep.app.edges[e].src}->{dep.app.edges[e].dst}": n
                    for e, n in sorted(dep.dropped.items())
                },
                "chain_delay_ms": {
                    dep.layout.chains[c].name: round(ms, 3) for c, ms in sorted(dep.delays.items())
                },
                "slo_ms": dep.app.slo_ms,
                "origin": dep.origin,
                "placement": dict(dep.placed),
                "chains": [list(c.vertices) for c in dep.layout.chains],
                "vertices": {
                    vid: {
                        "kind": h.kind,
                        "state": h.state(now),
                        "busy_s": round(now - h.busy_since, 3) if h.busy_since else 0.0,
                        "queued": h.queued
                        + sum(len(p[1]) for p in h.pending if not isinstance(p, m.Marker)),
                        "processed": h.processed,
                        "emitted": h.emitted,
                        "calls": h.calls,
                        "errors": h.errors,
                        "cpu_s": h.cpu_s,
                        "last_error": h.last_error,
                        "stats": h.stats,
                    }
                    for vid, h in dep.stones.items()
                },
                "edges": edges,
            }
        extra = self.status_hook() if self.status_hook is not None else {}
        self._sample(now)
        return extra | {
            "node": self.id,
            "monitor": self.monitor.snapshot() | {"work_ms": self.work_ms, "cpu_ms": self.cpu_ms},
            "routes": {d: list(r) for d, r in sorted(self.routes.items())},
            "neighbours": sorted(n for n, (hop, _) in self.routes.items() if hop == n),
            "apps": apps,
            "dropped_messages": self.dropped_messages,
            "illegal_transitions": self.illegal_transitions,
            "handler_errors": self.handler_errors,
            "last_handler_error": self.last_handler_error,
            "procedures": self.open_procedures(now),
            "failed_nodes": sorted(self.dead),
            "incarnation": self.incarnation,
            "management": self.manager.status(),
            "failures": list(self.failures),
            "rejoins": list(self.rejoins),
            "liveness": self.liveness.stats(),
            "heard": {
                n: {"at": t, "load": b.load, "drain_w": b.drain_w, "lifetime_s": b.lifetime_s}
                for n, (t, b) in sorted(self.liveness.heard.items())
            },
        }

    def _status_request(self, client: int, req: m.StatusRequest, now: float) -> None:
        mine = {self.id: self.status(now)}
        others = [n for n in self.known_nodes() if n != self.id]
        if not req.everywhere or not others:
            self._effects.append(Reply(client, m.StatusReply(req.req, mine)))
            return
        self._rid += 1
        fanout = StatusFanout(self._rid, now, client, mine, others)
        self._begin(fanout)
        fanout.start(self)

    def _on_status_reply(self, msg: m.StatusReply) -> None:
        fanout = self.procedures.get(msg.req)
        if isinstance(fanout, StatusFanout):
            fanout.receive(self, msg)
            if fanout.done:
                self._end(fanout.pid)


def _failed_reply(app: str, reason: str) -> m.DeployReply:
    return m.DeployReply(app=app, ok=False, placement={}, elapsed_ms=0.0, error=reason)
