"""The node core: a router over one node's components. Sans-IO.

Fed ``(message, now)``, ``(timer, now)``, a client request, a routing view or an executor
result; returns effects (send a message to a node, reply to a client, set or cancel a timer,
start, feed or stop a vertex instance). It never reads a socket and never runs user code: the
asyncio driver (``mso.node.driver``) supplies real time, connections and the executor; the
simulator supplies virtual ones.

The core owns the node's shared tables (its apps, routes and open procedures) and composes the
components that act on them, each through the narrow
:class:`~mso.protocol.context.NodeContext` the core implements:

- the data plane (:mod:`mso.protocol.dataplane`): instances, edges, acks, backpressure;
- one component per distributed procedure, every role of it in one module
  (:mod:`mso.protocol.procedures`): deploy, relocation, restore, remap and recovery,
  membership;
- the management loop (:mod:`mso.node.manager`): a view in, actions out.

One routing table covers wire messages, client requests, timer keys and the deadlines of the
procedures open here; internal events (:mod:`mso.protocol.events`) go to the components
subscribed to their type. Components never call each other through the core.
"""

from __future__ import annotations

import math
import zlib
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from typing import Any, TypeVar

from mso.errors import MsoError
from mso.management import Action, Relocate, RemapChain, RemapChains, RuleSettings
from mso.model.network import PowerModel
from mso.node.early import EarlyLimits, EarlyMessages
from mso.node.manager import Manager
from mso.node.monitor import Monitor
from mso.node.moves import MoveLog
from mso.node.status import LinkStatus, node_status, to_wire
from mso.protocol import effects as fx
from mso.protocol import kept
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.protocol.control_stream import ACK_DELAY_S, RTO_S, UNSEQUENCED, ControlStreams
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import CancelTimer, Effect, Reply, Send, SetTimer
from mso.protocol.events import (
    AppMissing,
    Deadline,
    Happened,
    HeartbeatTick,
    HeldProbesDue,
    InstanceCrashed,
    InstanceFailed,
    InstanceReady,
    InternalEvent,
    MarkerReached,
    MonitorTick,
    NodeReset,
    PeerFailed,
    PeerRejoined,
    PlacementStale,
    RecoverTick,
    RecoveryDue,
    RelocationEnded,
    ReplacementPrepared,
    ReplicationTick,
    Retransmit,
    Retry,
    RoutesChanged,
    SnapshotAligned,
    Snapshotted,
    SourceTick,
    StreamTick,
    Superseded,
)
from mso.protocol.procedures import placement
from mso.protocol.procedures.base import IllegalTransition, Procedure
from mso.protocol.procedures.deploy import Deploy, Deployer
from mso.protocol.procedures.lookup import Lookup, Lookups
from mso.protocol.procedures.membership.detector import Suspicion, Vouch
from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, Liveness
from mso.protocol.procedures.membership.peers import MONITOR_PERIOD_S, Membership
from mso.protocol.procedures.relocation import Relocation, Relocator
from mso.protocol.procedures.remap import Remap, Remapper
from mso.protocol.procedures.replication import Replicator
from mso.protocol.procedures.restore import Restorer
from mso.protocol.procedures.status import StatusFanout
from mso.protocol.spill import MemorySpill, SpillStore
from mso.protocol.state import Apps, AppState, HostedInstance
from mso.protocol.taps import TapTick

__all__ = ["AppState", "Effect", "HostedInstance", "NodeCore", "Reply", "Send", "SetTimer"]

E = TypeVar("E")
# an app this node took no part in for this long is let go (checked every monitor period, so
# within LET_GO_S + MONITOR_PERIOD_S of its last part: a handover's steps are over by then)
LET_GO_S = 1.0
MAX_HAPPENED = 256  # what happened, kept for the driver to log
ROUTE_VALUES_KEPT = 4096  # distinct (next hop, hops) route values shared, at the most
Handler = Callable[[str, Any, float], None]


class NodeCore:
    """One node's state machine: the router over its components (see the module docstring)."""

    # an illegal transition raises (tests set this) instead of only being counted
    strict = False
    # a beat with no news only refreshes its sender's liveness clock (Membership.quiet_beat);
    # off, every beat goes the whole way (a test compares the two)
    quiet_beats = True
    # messages that may overtake the announcement of their app: held until it arrives
    EARLY = (m.ChainPlaced, m.BuildChain, m.ChainPartReady, m.ChainBuilt, m.StartApp)

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
        clock: Callable[[], float] | None = None,
        early: EarlyLimits | None = None,
        spill: SpillStore | None = None,
        capabilities: dict[str, float] | None = None,
        link_rates: Callable[[str], float | None] | None = None,
    ) -> None:
        self.id = node_id
        self.capabilities = dict(capabilities or {})  # what it offers besides CPU (§3.3)
        # the rate (Mb/s) of the link to a neighbour, as the driver knows it (a lookup into
        # the driver's view, like ``clock``; the driver may set it once its view exists)
        self.link_rates: Callable[[str], float | None] = link_rates or (lambda _: None)
        # where edges spill what they cannot deliver yet, and positions kept across restarts
        # (the driver's: a file under the daemon's state directory; in memory otherwise)
        self.spill: SpillStore = spill if spill is not None else MemorySpill()
        self.capacity = capacity
        self.window = window
        self.power = power or PowerModel()
        self.monitor = Monitor(power or PowerModel(), battery_wh, cpu_speed=capacity)
        # read only to report how long a request took (a whole deployment can finish inside
        # one synchronous run); None in simulation, where ``now`` is exact
        self.clock = clock
        # the driver's inputs: cumulative bytes (sent, received), its links for status
        self._traffic: Sequence[int] = (0, 0)
        self._links: LinkStatus | None = None
        # operator keys and the undeploys they signed; open (no keys) unless the driver shares
        # its own (``mso node --operator-key``), which the transport checks frames with too
        self.authority = Authority()
        self.routes: dict[str, tuple[str, int]] = {}  # destination -> (next hop, hops)
        # one (next hop, hops) tuple per distinct value: a table of N routes holds about
        # degree x diameter of them, not one per destination (45 KB a node at 1,000 nodes)
        self._route_values: dict[tuple[str, int], tuple[str, int]] = {}
        self._route_hops: tuple[dict[str, tuple[str, int]], dict[str, int]] | None = None
        # the hops the last figures carried: of which routing table, for which app partners
        self._beat_hops: tuple[dict[str, tuple[str, int]], frozenset[str], dict[str, int]] | None
        self._beat_hops = None
        self.apps = Apps(node_id)
        self._idle: dict[str, float] = {}  # app -> since when this node takes no part in it
        self._kept: dict[str, int] = {}  # app -> the fingerprint of its record in the store
        self.procedures: dict[int, Procedure] = {}  # the procedures this node coordinates
        self._status_pid = -1  # the status fan-out gathering now, if any (one at a time)
        self.dropped_messages = 0
        # well-typed messages refused for their meaning (a vertex, edge or procedure that is
        # not there; a member's command that needs an operator), by reason; each is also one
        # of ``dropped_messages``
        self.refusals: dict[str, int] = {}
        self.illegal_transitions = 0
        self.handler_errors = 0  # messages whose handling raised (a bug), and the last one
        self.last_handler_error = ""
        self._now = 0.0
        self._effects: list[Effect] = []
        self._work: deque[tuple[str, m.Message]] = deque()
        # every control message to a peer numbered, kept until acknowledged, sent again
        self.streams = ControlStreams()
        self._stream_at: float | None = None  # when the streams' timer is set for
        # ids of procedures this node coordinates: distinct per node, small enough for msgpack
        self._rid = self._rid_base = (zlib.crc32(node_id.encode()) & 0xFFFFFF) << 20
        # messages for an app whose announcement has not arrived yet (another path overtook
        # it): bounded per peer and in total, by count and bytes, and in time
        self.early = EarlyMessages(early)
        self._subscribers: dict[type, list[Callable[[Any], None]]] = {}
        # what the driver logs (it drains them); bounded, as a simulation never drains
        self._happened: deque[Happened] = deque(maxlen=MAX_HAPPENED)

        # the components, lowest first; each gets this core as its context
        self.dataplane = dp = DataPlane(self)
        # management rules and policies (§3.5); the node policy is checked here, at start
        self.manager = Manager(self, policy, rules, enabled=manage)
        self.deployer = Deployer(self, dp, self.manager)
        self.relocator = Relocator(self, dp)
        self.restorer = Restorer(self, dp, self.relocator)
        self.replicator = Replicator(self, dp)
        self.remapper = Remapper(self, dp, self.relocator)
        self.lookups = Lookups(self, self.relocator, self.remapper, dp.taps.on_client)
        liveness = Liveness(heartbeat_s, dead_after_s)
        self.membership = Membership(self, dp, self.deployer, self.remapper, liveness, incarnation)

        # internal events: who hears what, in this order
        self._subscribe(InstanceReady, self.relocator.on_instance_ready)
        self._subscribe(InstanceReady, self.deployer.on_instance_ready)
        self._subscribe(InstanceFailed, self.relocator.on_instance_failed)
        self._subscribe(InstanceFailed, self.deployer.on_instance_failed)
        self._subscribe(InstanceCrashed, self.restorer.on_instance_crashed)
        self._subscribe(Superseded, self.restorer.on_superseded)
        self._subscribe(InstanceReady, self.replicator.on_instance_ready)
        # (the replacement's state is asked for before it is judged ready to run)
        self._subscribe(ReplacementPrepared, self.replicator.on_replacement_prepared)
        self._subscribe(ReplacementPrepared, self.restorer.on_replacement_prepared)
        self._subscribe(MarkerReached, self.relocator.on_marker_reached)
        self._subscribe(Snapshotted, self.relocator.on_snapshotted)
        self._subscribe(Snapshotted, self.replicator.on_snapshotted)
        self._subscribe(SnapshotAligned, self.replicator.on_aligned)
        self._subscribe(PeerFailed, self.replicator.on_peer_failed)
        self._subscribe(NodeReset, lambda ev: self.replicator.on_reset())
        self._subscribe(RelocationEnded, self.restorer.on_relocation_ended)
        self._subscribe(RelocationEnded, self.remapper.on_relocation_ended)
        self._subscribe(PeerFailed, self.relocator.on_peer_failed)
        self._subscribe(PeerFailed, self.restorer.on_peer_failed)
        self._subscribe(PeerFailed, self.remapper.on_peer_failed)
        self._subscribe(PeerFailed, self.deployer.on_peer_failed)
        self._subscribe(PeerRejoined, self.deployer.on_peer_rejoined)
        self._subscribe(PeerRejoined, self.lookups.on_peer_rejoined)
        self._subscribe(PeerRejoined, self.relocator.on_peer_rejoined)
        self._subscribe(PeerRejoined, self.restorer.on_peer_rejoined)
        self._subscribe(RoutesChanged, self.membership.on_routes_changed)
        self._subscribe(RoutesChanged, self.deployer.on_routes_changed)
        self._subscribe(RoutesChanged, self.remapper.on_routes_changed)
        self._subscribe(RoutesChanged, self.replicator.on_routes_changed)
        self._subscribe(RoutesChanged, self.relocator.on_routes_changed)
        self._subscribe(RecoveryDue, self.remapper.on_recovery_due)
        self._subscribe(
            PlacementStale, lambda ev: self.lookups.on_stale(ev.app, ev.wide, ev.sync, ev.also)
        )
        self._subscribe(AppMissing, self.membership.on_app_missing)
        self._subscribe(NodeReset, lambda ev: self.deployer.on_reset())
        self._subscribe(NodeReset, lambda ev: self.relocator.on_reset())
        self._subscribe(NodeReset, lambda ev: self.early.clear())
        self._subscribe(PeerFailed, self._drop_early_of)
        self._subscribe(PeerFailed, lambda ev: self.streams.forget(ev.node))
        self._subscribe(PeerRejoined, self._on_peer_rejoined)
        self._subscribe(NodeReset, lambda ev: self.streams.reset())
        self._subscribe(RoutesChanged, self._on_routes_changed)
        self.movelog = MoveLog()
        self._subscribe(
            Happened, lambda h: self._happened.append(self.movelog.happened(h, self._now))
        )

        # the router: message type -> the role of the procedure it belongs to
        dep, rel, res, rem, mem = (
            self.deployer,
            self.relocator,
            self.restorer,
            self.remapper,
            self.membership,
        )
        self._messages: dict[type, Handler] = {
            m.Data: lambda src, msg, now: (
                dp.on_data(msg, src) if placement.from_member(self, src, msg.app) else None
            ),
            m.Ack: lambda src, msg, now: (
                dp.on_ack(msg, now) if placement.from_member(self, src, msg.app) else None
            ),
            m.ChainDelay: lambda src, msg, now: dp.on_chain_delay(msg, now),
            m.Marker: rel.on_marker,
            m.AppAnnounce: self._on_announce,
            m.CapabilityQuery: dep.on_capability_query,
            m.CapabilityReply: lambda src, msg, now: dep.on_capability_reply(src, msg),
            m.Probe: lambda src, msg, now: dep.on_probe(msg),
            m.ProbeReply: lambda src, msg, now: (
                rem.on_probe_reply(msg) if msg.chain < 0 else dep.on_probe_reply(msg)
            ),  # chain -1 marks a remap's probe
            m.ChainPlaced: lambda src, msg, now: dep.on_placed(msg),
            m.BuildChain: lambda src, msg, now: dep.on_build(src, msg),
            m.ChainPartReady: lambda src, msg, now: dep.on_part_ready(msg),
            m.ChainBuilt: lambda src, msg, now: dep.on_built(msg, now),
            m.StartApp: lambda src, msg, now: dep.on_start(msg, now),
            m.StopApp: self._on_stop_app,
            m.DeployFailed: lambda src, msg, now: dep.on_deploy_failed(msg, now),
            m.RelocateRequest: lambda src, msg, now: rel.on_relocate_request(msg, now),
            m.PlacementQuery: lambda src, msg, now: placement.reply(self, src, msg),
            m.PlacementReply: self.lookups.on_reply,
            m.Prepare: lambda src, msg, now: rel.on_prepare(src, msg),
            m.Prepared: rel.on_prepared,
            m.Unprepare: rel.on_unprepare,
            m.Moving: rel.on_moving,
            m.Switch: lambda src, msg, now: rel.on_switch(src, msg),
            m.Handover: lambda src, msg, now: rel.on_handover(src, msg, now),
            m.HandoverEvents: lambda src, msg, now: rel.on_handover_events(src, msg, now),
            m.HandoverDone: rel.on_handover_done,
            m.Moved: lambda src, msg, now: placement.on_moved(self, src, msg, now),
            m.Rewire: res.on_rewire,
            m.Resume: res.on_resume,
            m.Replicate: lambda src, msg, now: self.replicator.on_replicate(src, msg),
            m.ReplicaAck: lambda src, msg, now: self.replicator.on_replica_ack(src, msg),
            m.Release: lambda src, msg, now: self.replicator.on_release(msg),
            m.Replay: lambda src, msg, now: self.replicator.on_replay(msg),
            m.ReplicaSet: lambda src, msg, now: self.replicator.on_replica_set(src, msg),
            m.FetchReplica: lambda src, msg, now: self.replicator.on_fetch(src, msg),
            m.Heartbeat: mem.on_heartbeat,
            m.NodeDown: lambda src, msg, now: mem.on_node_down(
                msg.node, msg.detector, now, msg.incarnation, msg.witness
            ),
            m.NodeUp: lambda src, msg, now: mem.on_node_up(msg, now),
            m.Suspect: mem.on_suspect,
            m.Hears: mem.on_hears,
            m.AppSync: mem.on_app_sync,
            m.StatusRequest: lambda src, msg, now: self.send(
                src, m.StatusReply(req=msg.req, nodes={self.id: self.status(now)})
            ),
            m.StatusReply: lambda src, msg, now: self._on_status_reply(msg),
            m.Tap: dp.taps.on_peer,
            m.TapEvents: dp.taps.on_events,
        }
        # client requests (CLI, API, emulator controller)
        self._requests: dict[type, Callable[[int, Any, float], None]] = {
            m.DeployRequest: dep.deploy_request,
            m.StopApp: self._undeploy_request,
            m.RelocateRequest: self._relocate_request,
            m.RemapRequest: lambda client, msg, now: self.lookups.remap(client, msg, now),
            m.StatusRequest: self._status_request,
            m.Tap: self.lookups.tap_request,
        }
        # timer keys
        self._timers: dict[type, Callable[[Any, float], None]] = {
            Deadline: self._on_deadline,
            Retry: self._on_retry,
            SourceTick: lambda key, now: dp.source_tick(key.app, key.vertex, now),
            Retransmit: lambda key, now: dp.sf.retransmit(key.app, now),
            MonitorTick: self._on_monitor_tick,
            HeartbeatTick: lambda key, now: mem.heartbeat(now),
            RecoverTick: rem.on_recover_tick,
            HeldProbesDue: lambda key, now: dep.on_held_probes_due(now),
            ReplicationTick: self.replicator.tick,
            TapTick: dp.taps.tick,
            StreamTick: self._on_stream_tick,
        }
        # a procedure's step not answered in time: asked again (or given up)
        self._retries: dict[type, Callable[[Retry, float], None]] = {
            Relocation: rel.on_retry,
            Remap: rem.on_retry,
            Deploy: dep.on_retry,  # the capability answers are all in
        }
        # a procedure whose deadline passed: its defined failure, told to whoever waits
        self._expiries: dict[type, Callable[[Any, float], None]] = {
            Relocation: rel.expire,
            Remap: rem.expire,
            Deploy: dep.expire,
            Lookup: self.lookups.expire,
            Suspicion: mem.suspicion_expired,
            Vouch: lambda proc, now: mem.vouch_expired(proc),
        }

    # -- the driver's entry points ---------------------------------------------------------
    def start(self, now: float, recalled: list[m.AppSync] | None = None) -> list[Effect]:
        """Begin monitoring; drivers call this once when the node starts. ``recalled``: the
        apps kept in its store (:func:`mso.protocol.kept.recall`), if the driver read them
        already (to warm their imports first); else read here."""
        self._sample(now)
        self._effects.append(SetTimer(MonitorTick(), now + MONITOR_PERIOD_S))
        self.membership.start(now)
        if recalled is None:
            recalled = kept.recall(self.spill)
        for sync in recalled:  # the apps its last process held (a restart)
            self.send(self.id, sync)
            self._kept[sync.app] = 0  # (kept again at the first period, or forgotten)
        return self._run(now)

    def observe(
        self,
        now: float,
        bytes_out: int,
        bytes_in: int,
        *,
        links: LinkStatus | None = None,
        device: dict[str, Any] | None = None,
    ) -> None:
        """What the driver measures, as inputs: its cumulative bytes sent and received
        (relayed included); for a status, the state of its links and connections; on a
        device, what the OS reads (battery, CPU time, interface bytes: ``DeviceProbe.read``)."""
        self._traffic = (bytes_out, bytes_in)
        if links is not None:
            self._links = links
        if device is not None:
            self.monitor.observe(now, device)

    def count_traffic(self, counters: Sequence[int]) -> None:
        """The driver's cumulative byte counters (sent, received) as a live sequence it keeps
        up to date, read when the node samples them: the simulator's, whose counters change
        only between the core's calls, so this reads what an :meth:`observe` before every
        call would have given, without the call per message."""
        self._traffic = counters

    def set_routes(self, routes: dict[str, tuple[str, int]], now: float = 0.0) -> list[Effect]:
        """Take the routing view's current routes; returns effects (a recovery waiting for
        routes around a failed node may start)."""
        self._now = now
        kept = self._kept_routes()
        new = {d: kept.setdefault(r, r) for d, r in routes.items() if d != self.id}
        old, self.routes = self.routes, new
        changed = {d for d in set(old) | set(self.routes) if old.get(d) != self.routes.get(d)}
        return self._routes_changed(changed, set(self.routes) - set(old), now)

    def change_routes(
        self, delta: Mapping[str, tuple[str, int] | None], now: float = 0.0
    ) -> list[Effect]:
        """Take the routes that changed (a destination -> its new route, None: unreachable),
        for a routing view that knows what changed: the same as :meth:`set_routes` with the
        whole table, without the O(N) comparison per node per link change."""
        self._now = now
        routes = dict(self.routes)  # a new table, as set_routes makes: no one sees it change
        kept = self._kept_routes()
        changed, appeared = set(), set()
        for d, r in delta.items():
            was = routes.get(d)
            if d == self.id or was == r:
                continue
            changed.add(d)
            if r is None:
                del routes[d]
            else:
                routes[d] = kept.setdefault(r, r)
                if was is None:
                    appeared.add(d)
        self.routes = routes
        return self._routes_changed(changed, appeared, now)

    def _kept_routes(self) -> dict[tuple[str, int], tuple[str, int]]:
        """The distinct route values, bounded: started afresh past a bound that a node's
        neighbours times its routes' lengths stays under (mobility makes new ones)."""
        if len(self._route_values) > ROUTE_VALUES_KEPT:
            self._route_values = {}
        return self._route_values

    def _routes_changed(self, changed: set[str], appeared: set[str], now: float) -> list[Effect]:
        self.monitor.note_routes(now, self.routes)
        event = RoutesChanged(frozenset(changed), frozenset(appeared))
        self._guarded("routes", self.publish, event)
        return self._run(now)

    def on_vertex(self, res: fx.VertexResult, now: float) -> list[Effect]:
        """A result from the executor (drivers call this, like ``receive``)."""
        self._now = now
        self._guarded(type(res).__name__, self.dataplane.on_vertex, res, now)
        return self._run(now)

    def on_spill(self, key: str, now: float) -> list[Effect]:
        """The spill store read ahead events of ``key`` a drain waited for (drivers call
        this when a store reads off the loop, ``mso.daemon.spill``)."""
        self._now = now
        self._guarded("spill", self.dataplane.sf.spill_ready, key)
        return self._run(now)

    def receive(self, src: str, msg: m.Message, now: float) -> list[Effect]:
        """A message from another node (or relayed by one)."""
        self._now = now
        if type(msg) is m.Sequenced:
            return self._receive_frame(src, msg, now)
        if type(msg) is m.Got:
            self.streams.on_got(src, msg.inc, msg.upto, now)
            return self._run(now)
        if src in self.membership.failed:  # a node declared failed is heard only to rejoin
            if not isinstance(msg, m.Heartbeat):
                self.dropped_messages += 1
                return []
            self._guarded("heard", self.membership.on_failed_heartbeat, src, msg, now)
        elif (
            self.quiet_beats
            and isinstance(msg, m.Heartbeat)
            and not self._work
            and not self._effects
            and not self.dataplane.outbox
            and not self.dataplane.touched
            and self.membership.quiet_beat(src, msg, now)
        ):
            return []  # a beat with no news: the sender's liveness clock, nothing else
        else:
            self._guarded("heard", self.membership.heard, src, now)
            self._work.append((src, msg))
        return self._run(now)

    def _receive_frame(self, src: str, frame: m.Sequenced, now: float) -> list[Effect]:
        """A frame of ``src``'s control stream: its messages, in order and once. A node held
        failed is heard only to rejoin: its frames are taken (acknowledged) and dropped."""
        ready = self.streams.receive(src, frame, now, self.incarnation)
        self._stream_wake(now + ACK_DELAY_S)
        if src in self.membership.failed:
            self.dropped_messages += len(ready)
            return self._run(now)
        if ready:
            self._guarded("heard", self.membership.heard, src, now)
        for msg in ready:
            if type(msg) in (m.Sequenced, m.Got):
                self.dropped_messages += 1  # (nested: never sent so)
            else:
                self._work.append((src, msg))
        return self._run(now)

    def request(self, client: int, msg: m.Message, now: float) -> list[Effect]:
        """A request from a client connection (CLI, API, emulator controller)."""
        self._now = now
        handle = self._requests.get(type(msg))
        if handle is None:
            self.dropped_messages += 1
        else:
            handle(client, msg, now)
        return self._run(now)

    def _let_go_idle(self, now: float) -> None:
        """Only the nodes that take part in an app hold it (issue 24.1): an app this node
        has taken no part in, first-hand, for ``LET_GO_S`` (checked every monitor period) is
        let go. Its own view of the placement is not trusted for this: it may be out of date
        (a move or a restore it was not told of, a sync from a node behind), while what it
        runs, restores, builds, coordinates or keeps a replica of here is known here."""
        for name, dep in list(self.apps.items()):
            if self.takes_part(dep):
                self._idle.pop(name, None)
                if not self.takes_part(dep, copies=False):
                    self.replicator.ask_if_replica(dep, now, LET_GO_S)
                continue
            since = self._idle.setdefault(name, now)
            if now - since >= LET_GO_S:
                del self._idle[name]
                del self.apps[name]
                self.dataplane.stop_app(dep, "let go")
                self.deployer.policies.forget(name)

    def _keep_held(self) -> None:
        """The apps this node holds, kept in its store as their placement changes (checked
        every monitor period), and forgotten there once let go or undeployed: a restarted
        daemon takes them back (:mod:`mso.protocol.kept`)."""
        for name in [n for n in self._kept if n not in self.apps]:
            del self._kept[name]
            kept.forget(self.spill, name)
        for name, dep in self.apps.items():
            if not dep.running:
                continue
            hosts = set(dep.placed.values()) - {self.id}
            incs = {n: i for n in sorted(hosts) if (i := self.incarnation_of(n, -1)) >= 0}
            if self._kept.get(name) != (mark := kept.fingerprint(dep, incs)):
                kept.keep(self.spill, dep, incs)
                self._kept[name] = mark

    def takes_part(self, dep: AppState, copies: bool = True) -> bool:
        """First-hand: its origin, an instance here (running, starting, handed over to
        here, restoring, crashed), a chain being built or a deploy not yet started that
        places a vertex here, a replica's snapshot, a recovery coordinated here, a vertex
        handed over from here while a host is out of reach, or any procedure of the app
        open here."""
        me = self.id
        if dep.origin == me or dep.hosts_part() or dep.preparing or dep.building:
            return True
        if copies and (dep.held or any(me in ns for ns in dep.replica_nodes.values())):
            return True  # a replica's copy, or named a replica (ask_if_replica settles it)
        if dep.recovering is not None or dep.stash:
            return True
        if dep.handed and any(
            n != me and n not in self.routes and n not in self.failed for n in dep.placed.values()
        ):  # news of a move to tell a member out of reach, once back (Membership._claim_to):
            return True  # none else may have it (seed 89096: the new host died meanwhile)
        if not dep.running and me in dep.placed.values():
            return True
        name = dep.app.name
        if any(relay.app == name for relay in self.dataplane.taps.relays.values()):
            return True  # a client's tap relayed here
        return any(getattr(p, "app", None) == name for p in self.procedures.values())

    def on_timer(self, key: Any, now: float) -> list[Effect]:
        self._now = now
        handle = self._timers.get(type(key))
        if handle is not None:
            self._guarded("timer", handle, key, now)
        return self._run(now)

    # -- the context the components act through ---------------------------------------------
    @property
    def now(self) -> float:
        return self._now

    @property
    def failed(self) -> set[str]:
        """The nodes this node holds failed (membership's one set)."""
        return self.membership.failed

    @property
    def incarnation(self) -> int:
        return self.membership.incarnation

    def send(self, dst: str, msg: m.Message) -> None:
        if dst == self.id:
            self._work.append((self.id, msg))
        elif type(msg) in UNSEQUENCED:
            self._effects.append(Send(dst, msg))
        else:
            to = max(self.incarnation_of(dst, -1), self.streams.incarnation_of(dst))
            frame = self.streams.wrap(dst, msg, self.incarnation, self._now, to)
            self._effects.append(Send(dst, frame))
            self._stream_wake(self._now + RTO_S)

    def _stream_wake(self, at: float) -> None:
        """The streams' timer at ``at`` unless set for earlier (an early wake finds nothing
        due and sets the timer for what is)."""
        if self._stream_at is None or at < self._stream_at:
            self._stream_at = at
            self._effects.append(SetTimer(StreamTick(), at))

    def _on_stream_tick(self, key: StreamTick, now: float) -> None:
        self._stream_at = None
        sends, then = self.streams.due(now, self.routes)
        self._effects.extend(Send(dst, msg) for dst, msg in sends)
        if then is not None:
            self._stream_wake(then)

    def _on_peer_rejoined(self, ev: PeerRejoined) -> None:
        if ev.restarted:  # a new process: what its predecessor was not sent is not for it
            self.streams.forget(ev.node)
        self.streams.heard_of(ev.node, self.incarnation_of(ev.node, -1))  # (or reset)

    def _on_routes_changed(self, ev: RoutesChanged) -> None:
        for node in ev.appeared:
            if self.streams.reachable(node, self._now):
                self._stream_wake(self._now)

    def broadcast(self, msg: m.Message) -> None:
        """To every node not held failed, including those heard of but out of reach right
        now: a partition shorter than failure detection declares nobody failed, so no rejoin
        would ever tell them what they missed; the driver holds the frame until routes come
        back (``mso.net.forwarding``), and a longer cut ends in a rejoin, which syncs."""
        for n in sorted({*self.known_nodes(), *self.membership.heard_of()}):
            if n not in self.failed:
                self.send(n, msg)

    def reply(self, client: int, msg: m.Message) -> None:
        self._effects.append(Reply(client, msg))

    def emit(self, effect: Effect) -> None:
        self._effects.append(effect)

    def emit_all(self, effects: Iterable[Effect]) -> None:
        self._effects.extend(effects)

    def set_timer(self, key: Hashable, at: float) -> None:
        self._effects.append(SetTimer(key, at))

    def loop_back(self, src: str, msg: m.Message) -> None:
        self._work.append((src, msg))

    def new_pid(self) -> int:
        self._rid += 1
        return self._rid

    def ours(self, pid: int) -> bool:
        return self._rid_base < pid <= self._rid

    def begin(self, proc: Procedure) -> None:
        self.procedures[proc.pid] = proc
        self._effects.append(SetTimer(Deadline(proc.pid), proc.deadline))

    def end(self, pid: int) -> None:
        if self.procedures.pop(pid, None) is not None:
            self._effects.append(CancelTimer(Deadline(pid)))

    def procedure(self, pid: int | None) -> Procedure | None:
        return self.procedures.get(pid) if pid is not None else None

    def open(self) -> list[Procedure]:
        return list(self.procedures.values())

    def publish(self, event: InternalEvent) -> None:
        for handle in self._subscribers.get(type(event), ()):
            handle(event)

    def refusal(self, reason: str) -> None:
        self.dropped_messages += 1
        if reason in self.refusals or len(self.refusals) < 64:
            self.refusals[reason] = self.refusals.get(reason, 0) + 1

    def dropped(self) -> None:
        self.dropped_messages += 1

    def note_event(self, now: float, what: str) -> None:
        self.monitor.note_event(now, what)

    def note_start(self, now: float) -> None:
        self.monitor.note_start(now)

    def elapsed_ms(self, since: float) -> float:
        """Time since a request, for the replies that report it: the clock when the driver
        gave one, else ``now``."""
        end = self.clock() if self.clock is not None else self._now
        return max(0.0, end - since) * 1e3

    def incarnation_of(self, node: str, default: int) -> int:
        return self.membership.incarnation_of(node, default)

    def learn_incarnations(self, incarnations: Mapping[str, int]) -> None:
        self.membership.learn_incarnations(incarnations)

    def figures(self) -> m.Figures:
        """This node's monitored figures, as its heartbeats carry them."""
        mon, pw = self.monitor, self.power
        power = (pw.idle_w, pw.cpu_w, pw.tx_uj_per_byte, pw.rx_uj_per_byte)
        return m.Figures(
            self.capacity,
            mon.load,
            mon.drain_w,
            mon.remaining_j,
            mon.lifetime_s,
            power,
            self.beat_hops(),
        )

    def known_nodes(self) -> list[str]:
        return sorted({self.id, *self.routes})

    def route_hops(self) -> dict[str, int]:
        """Hops to each node this node routes to (itself not included): kept until the
        routing table changes (a new one on every change), not made again every monitor
        period (an N-entry dict a second per node running an app)."""
        kept = self._route_hops
        if kept is not None and kept[0] is self.routes:
            return kept[1]
        hops = {n: h for n, (_, h) in self.routes.items()}
        self._route_hops = (self.routes, hops)
        return hops

    def beat_hops(self) -> dict[str, int]:
        """The hops a beat's figures carry: to the nodes within two hops (a neighbour's
        relays, and the suspect's neighbours a detector asks) and to those of the apps this
        node runs part of (a move's radio cost at the relays) — never all N, so a beat's
        size does not grow with the network."""
        partners = {
            n for dep in self.apps.engaged_apps() if dep.instances for n in dep.placed.values()
        }
        kept = self._beat_hops
        if kept is not None and kept[0] is self.routes and kept[1] == partners:
            return kept[2]  # the same routing table (a new one on every change): the same hops
        hops = {n: h for n, (_, h) in self.routes.items() if h <= 2 or n in partners}
        self._beat_hops = (self.routes, frozenset(partners), hops)
        return hops

    def distances(self) -> dict[str, int]:
        return {**self.route_hops(), self.id: 0}

    # -- what the management loop and tests read: the inspection API ---------------------------
    def relocation_target(self, dep: AppState, vertex: str, direction: str = "") -> str:
        return self.relocator.relocation_target(dep, vertex, direction)

    def placement(self, app: str) -> dict[str, str]:
        """Where this node holds each vertex of ``app`` to run (empty: no such app here)."""
        dep = self.apps.get(app)
        return dict(dep.placed) if dep is not None else {}

    def instances(self, app: str) -> dict[str, HostedInstance]:
        """The instances of ``app`` running here, by vertex (a view: do not change them)."""
        dep = self.apps.get(app)
        return dict(dep.instances) if dep is not None else {}

    def peer_state(self, node: str) -> str:
        """How this node holds ``node``: ALIVE, SUSPECT or FAILED (by its peer table)."""
        peer = self.membership.peers.get(node)
        return peer.state.name if peer is not None else "ALIVE"

    def open_procedures(self, now: float) -> list[dict[str, Any]]:
        """Procedures still running here, with their deadlines (overdue ones flagged)."""
        return [
            p.describe() | {"id": pid, "overdue": now > p.deadline}
            for pid, p in sorted(self.procedures.items())
        ]

    def status(self, now: float) -> dict[str, Any]:
        """This node's status as the wire carries it: the typed record
        (:class:`~mso.node.status.NodeStatus`, composed from the components' own) made plain
        in one place; :func:`mso.node.status.from_wire` types it again."""
        self._sample(now)
        return to_wire(node_status(self, now))

    @property
    def failures(self) -> list[dict[str, Any]]:
        """Nodes this node declared or heard declared failed: who, when, by whom (recent)."""
        return self.membership.failures

    @property
    def rejoins(self) -> list[dict[str, Any]]:
        """Nodes back as a new incarnation: who, when (recent)."""
        return self.membership.rejoins

    @property
    def liveness(self) -> Liveness:
        """The failure detector's view of the neighbours (heartbeats heard, the window)."""
        return self.membership.liveness

    @property
    def heard(self) -> dict[str, tuple[float, m.Figures]]:
        """What each neighbour's last beat said of its figures, and when."""
        return self.membership.liveness.heard

    def link_rate(self, neighbour: str) -> float | None:
        """The rate of the link to ``neighbour`` (Mb/s; None: not known): a probe carries it."""
        rate = self.link_rates(neighbour)
        return rate if rate is not None and math.isfinite(rate) and rate > 0 else None

    @property
    def links(self) -> LinkStatus | None:
        """What the driver last said of its links (None in simulation)."""
        return self._links

    # -- the router's own handlers ------------------------------------------------------------
    def drain_happened(self) -> list[Happened]:
        """What happened since the last call, oldest first: the driver logs it."""
        if not self._happened:
            return []
        out = list(self._happened)
        self._happened.clear()
        return out

    def subscribe(self, kind: type[E], handle: Callable[[E], None]) -> None:
        """Hear internal events of ``kind`` too (a simulator keeping what happened, a test);
        called as the components' handlers are, after them."""
        self._subscribe(kind, handle)

    def _subscribe(self, kind: type[E], handle: Callable[[E], None]) -> None:
        self._subscribers.setdefault(kind, []).append(handle)

    def _run(self, now: float) -> list[Effect]:
        self._now = now
        while self._work:
            src, msg = self._work.popleft()
            self._guarded(type(msg).__name__, self._dispatch, src, msg, now)
        self.dataplane.flush()
        out, self._effects = self._effects, []
        return out

    def _guarded(self, what: str, handle: Callable[..., None], *args: Any) -> None:
        """Handle one message, timer or executor result. An event at the wrong moment is an
        illegal transition, counted; a bug costs that one event, never the link or the node.
        Tests run strict, where both raise."""
        try:
            handle(*args)
        except MsoError:
            self.dropped_messages += 1
        except IllegalTransition:
            self.illegal_transitions += 1
            if self.strict:
                raise
        except Exception as exc:
            self.handler_errors += 1
            self.last_handler_error = f"{what}: {type(exc).__name__}: {exc}"
            if self.strict:
                raise

    def _dispatch(self, src: str, msg: m.Message, now: float) -> None:
        if isinstance(msg, self.EARLY) and msg.app not in self.apps:
            # replayed when the app's announcement arrives (or refused, counted)
            for reason in self.early.hold(src, msg.app, msg, now):
                self.refusal(reason)
            return
        handler = self._messages.get(type(msg))
        if handler is None:
            self.dropped_messages += 1  # a client's request, or a link message, from a node
            return
        app = getattr(msg, "app", None)
        if app is not None:  # its channels may change: the flush looks at this app's
            self.dataplane.touch(app)
        handler(src, msg, now)

    def _on_announce(self, src: str, msg: m.AppAnnounce, now: float) -> None:
        known = msg.app in self.apps
        self.deployer.on_announce(src, msg, now)
        if msg.app in self.apps:
            self._work.extend(self.early.pop(msg.app))
            if not known:
                self.publish(Happened("deploy", msg.app, by=self.apps[msg.app].origin))

    def _on_stop_app(self, src: str, msg: m.StopApp, now: float) -> None:
        known = msg.app in self.apps
        self.deployer.on_stop_app(msg, now)
        self.early.drop_app(msg.app)
        if known and msg.app not in self.apps:
            self.publish(Happened("undeploy", msg.app, by=src))
            for proc in self.open():  # they run out their deadlines; their clients wait not
                if proc.app == msg.app:
                    proc.refuse_client(
                        self, f"{self.id}: undeployed before the {proc.name} finished"
                    )

    def _relocate_request(self, client: int, msg: m.RelocateRequest, now: float) -> None:
        self.lookups.relocate(client, msg, now)  # (a refusal is told to the client)

    def _undeploy_request(self, client: int, msg: m.StopApp, now: float) -> None:
        why = self.deployer.undeploy_refused(msg)
        if not why and self.authority.signed and self.deployer.undeployed_before(msg):
            why = f"refused: this undeploy of {msg.app!r} is older than its deployment"
        if why:
            self.refusal("stop_app_unauthorized")
            self._effects.append(Reply(client, m.Refused(why)))
            return
        # to every node, held here or not: only the nodes that take part in an app hold it
        # (issue 24.1), and the one asked may be none of them (an operator's rare request)
        self.broadcast(msg)
        self._effects.append(Reply(client, m.StopApp(msg.app)))

    def _on_deadline(self, key: Deadline, now: float) -> None:
        proc = self.procedures.get(key.pid)
        if proc is None or proc.done or now < proc.deadline - 1e-9:
            return  # (a procedure may have pushed its deadline on)
        expire = self._expiries.get(type(proc))
        if expire is not None:
            expire(proc, now)
        else:
            proc.expire(self)
            self.end(proc.pid)

    def _on_retry(self, key: Retry, now: float) -> None:
        proc = self.procedures.get(key.pid)
        retry = self._retries.get(type(proc))
        if retry is not None:
            retry(key, now)

    def _drop_early_of(self, ev: PeerFailed) -> None:
        """A failed peer's early messages go with it (its announcement will not come)."""
        for _ in range(self.early.drop_peer(ev.node)):
            self.refusal("early_peer_failed")

    def _on_monitor_tick(self, key: MonitorTick, now: float) -> None:
        self._sample(now)
        for reason in self.early.expire(now):
            self.refusal(reason)
        self.relocator.expire_held(now)
        self.dataplane.report_delays(now)
        self._let_go_idle(now)
        self._keep_held()
        for action in self.manager.tick(now):  # the rules' decisions, carried out here
            self._carry_out(action, now)
        self._effects.append(SetTimer(MonitorTick(), now + MONITOR_PERIOD_S))

    def _carry_out(self, action: Action, now: float) -> None:
        """A management action, by the same procedures a user's request starts (the move log
        hears which rule asked, and why)."""
        if self.authority.strict_moves and isinstance(action, RemapChain | RemapChains):
            # a chain end's remap is no warrant there: the other hosts would refuse its moves
            self.note_event(now, f"no remap of {action.app} by the rules: strict moves")
            return
        asked = self.manager.asked(action)
        self.movelog.asking(
            action.app, action.vertex if isinstance(action, Relocate) else "", asked
        )
        if isinstance(action, Relocate):
            req = m.RelocateRequest(action.app, action.vertex, target=action.target)
            self.relocator.request(None, req, now)
        elif isinstance(action, RemapChain):
            self.remapper.remap(m.RemapRequest(action.app, [action.chain]), now)
        elif isinstance(action, RemapChains):
            req2 = m.RemapRequest(action.app, list(action.chains))
            self.remapper.remap(req2, now, weights=dict(action.weights), place=dict(action.place))

    def _sample(self, now: float) -> None:
        out, inc = self._traffic
        self.monitor.sample(now, self.dataplane.work_ms, out, inc, self.dataplane.cpu_ms)

    def _status_request(self, client: int, req: m.StatusRequest, now: float) -> None:
        gathering = self.procedures.get(self._status_pid)
        if req.everywhere and isinstance(gathering, StatusFanout) and gathering.join(client):
            return  # one fan-out at a time: it answers this client too
        mine = {self.id: self.status(now)}
        others = [n for n in self.known_nodes() if n != self.id]
        if not req.everywhere or not others or gathering is not None:
            self._effects.append(Reply(client, m.StatusReply(req.req, mine)))
            return
        fanout = StatusFanout(self.new_pid(), now, client, mine, others)
        self._status_pid = fanout.pid
        self.begin(fanout)
        fanout.start(self)

    def _on_status_reply(self, msg: m.StatusReply) -> None:
        fanout = self.procedures.get(msg.req)
        if isinstance(fanout, StatusFanout):
            fanout.receive(self, msg)
            if fanout.done:
                self.end(fanout.pid)
