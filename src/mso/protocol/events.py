"""Typed timer keys and internal events: how a node's components hear of each other. Sans-IO.

A *timer key* names what a timer is for; the driver keeps one timer per key (setting a key again
moves it) and hands the key back to the core when it fires. An *internal event* is something one
component of the node core learnt that others act on: membership declares a peer failed, the data
plane has an instance ready or a marker reached, a relocation ended. The core delivers each event
to the components subscribed to its type, in the order they subscribed, at once (a component's
handler runs before the publisher goes on, as a direct call would). Both are frozen dataclasses,
so a typo in a key or an event is a type error, not a silent miss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mso.protocol import messages as m
    from mso.protocol.effects import VertexSnapshot


# -- timer keys ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Deadline:
    """Procedure ``pid``'s deadline."""

    pid: int


@dataclass(frozen=True)
class Retry:
    """Procedure ``pid``'s step ``attempt`` was not answered in time."""

    pid: int
    attempt: int


@dataclass(frozen=True)
class SourceTick:
    """A rated source of ``app`` is due to be called again."""

    app: str
    vertex: str


@dataclass(frozen=True)
class Retransmit:
    """Go-back-N for ``app``'s edges: resend what waited a whole period without an ack."""

    app: str


@dataclass(frozen=True)
class MonitorTick:
    """Sample the monitor, report chain delays, run the management rules."""


@dataclass(frozen=True)
class HeartbeatTick:
    """Beat to the neighbours; judge the silent and the unreachable."""


@dataclass(frozen=True)
class RecoverTick:
    """Try ``app``'s failure recovery again (an earlier attempt failed)."""

    app: str


@dataclass(frozen=True)
class HeldProbesDue:
    """Probes held at this hop for routes around a failed next hop have waited long enough:
    they skip it (its daemon is gone; its machine may still route, as a router whose mso
    crashed does, and then the routes never change)."""


@dataclass(frozen=True)
class ReplicationTick:
    """Chain replication of ``app``'s vertices hosted here: snapshots due by time, replicas
    that did not acknowledge in time."""

    app: str


@dataclass(frozen=True)
class StreamTick:
    """Control streams (:mod:`mso.protocol.control_stream`): frames not acknowledged in time
    are sent again, acknowledgements held for a piggyback go out on their own."""


TimerKey = (
    Deadline
    | Retry
    | SourceTick
    | Retransmit
    | MonitorTick
    | HeartbeatTick
    | RecoverTick
    | HeldProbesDue
    | ReplicationTick
    | StreamTick
)


# -- internal events -------------------------------------------------------------------------
@dataclass(frozen=True)
class PeerFailed:
    """Membership declared ``node`` failed (fail-stop): its instances are gone."""

    node: str


@dataclass(frozen=True)
class PeerRejoined:
    """Membership took ``node`` back (a restart, a healed partition): it is a member again, so
    what waited for it (a deployment pinning a vertex there) may go on. ``restarted``: heard
    first in a later incarnation, never held failed here, so nothing here took its instances
    for gone (its moves: :meth:`~mso.protocol.procedures.relocation.Relocator.on_peer_rejoined`)."""

    node: str
    restarted: bool = False


@dataclass(frozen=True)
class RoutesChanged:
    """The routing view changed: ``changed`` are the destinations whose route differs,
    ``appeared`` those newly reachable."""

    changed: frozenset[str]
    appeared: frozenset[str]


@dataclass(frozen=True)
class RecoveryDue:
    """Something a failure recovery waits on may have changed (a beat, a rejoin, a sync):
    check ``app`` (every app when None)."""

    app: str | None = None


@dataclass(frozen=True)
class PlacementStale:
    """A recovery of ``app`` this node would coordinate rests on a view it was not kept up to
    date on (it hosts no part of the app): look the placement up first (``wide``: every node
    it reaches, not only those its view names). ``sync``: the app just came with a sync from
    a node that may not have been kept up to date either (issue 24.1: a move's coordinator
    that holds it for the move alone): ask the nodes it names, nothing waiting on it.
    ``also``: nodes to ask besides (one the view placed a vertex on until just now)."""

    app: str
    wide: bool = True
    sync: bool = False
    also: tuple[str, ...] = ()


@dataclass(frozen=True)
class Superseded:
    """News that ``vertex``, which runs here, runs on ``node`` as a later move (``version``):
    two coordinators restored it where each saw it lost (a partition, a reset, views that
    disagreed), and the ends of its edges follow the later one. This instance is a twin.
    ``incarnation``: the one ``node`` said it runs the vertex in."""

    app: str
    vertex: str
    node: str
    version: int
    incarnation: int = -1


@dataclass(frozen=True)
class InstanceReady:
    """An instance's code was constructed (``open()`` ran): a build or a move goes on."""

    app: str
    vertex: str


@dataclass(frozen=True)
class InstanceFailed:
    """An instance's code failed at construction (or its process died starting)."""

    app: str
    vertex: str
    error: str


@dataclass(frozen=True)
class InstanceCrashed:
    """A started instance's process died unasked (counted already): restore it in place."""

    app: str
    vertex: str
    instance: int


@dataclass(frozen=True)
class MarkerReached:
    """A relocation's marker reached an instance, behind every event sent before it."""

    app: str
    marker: m.Marker


@dataclass(frozen=True)
class Snapshotted:
    """An instance's state was taken for the relocation it is handing over in."""

    app: str
    vertex: str
    result: VertexSnapshot


@dataclass(frozen=True)
class SnapshotAligned:
    """A replicated instance has processed everything fed to it before a snapshot was asked
    for and nothing after: its state and its channel positions agree, take them now."""

    app: str
    vertex: str


@dataclass(frozen=True)
class RelocationEnded:
    """A relocation or restore this node coordinated ended (``error`` empty: it succeeded,
    ``vertex`` runs on ``target``); whoever started it (a remap, a crash restore) goes on."""

    pid: int
    app: str
    vertex: str
    target: str
    remap: int | None
    error: str


@dataclass(frozen=True)
class ReplacementPrepared:
    """A restore's replacement instance of ``vertex`` started at this node (its coordinator
    is told): it runs as soon as every surviving end of its edges has resumed it, at once if
    it has none."""

    app: str
    vertex: str


@dataclass(frozen=True)
class AppMissing:
    """``node``, asked to host a vertex of ``app``, does not hold the app (its sync was lost).
    ``ahead``: it may hold none of it, as it takes no part yet (issue 24.1), and is sent it
    ahead of a request that carries the sender's view anyway (a ``Prepare``, a snapshot, a
    lookup's answer): sent even while the sender's view is in dispute."""

    app: str
    node: str
    ahead: bool = False


@dataclass(frozen=True)
class NodeReset:
    """This node was declared failed by a side that outranks it: it drops every app and the
    procedures and waits that went with them, and rejoins as its next incarnation."""


@dataclass(frozen=True)
class Happened:
    """Something an operator wants one log line about: an app deployed or undeployed here, a
    move this node coordinated or now hosts, a peer declared failed or back. Published by the
    component that saw it; the core keeps the last few for its driver to drain and log
    (``NodeCore.drain_happened``), as the core itself never logs."""

    what: str  # deploy, undeploy, relocation, restore, hosted, remap, recovery, peer_failed, ...
    app: str = ""
    subject: str = ""  # the vertex moved, the peer failed
    detail: str = ""  # where it went: "N1 -> N2", "a->N2 b->N3"
    by: str = ""  # who asked: operator, rule, remap, recovery, crash, a node's id
    took_ms: float | None = None
    error: str = ""
    asked: str = ""  # who asked, in words (the core's move log fills it: mso.node.moves)


InternalEvent = (
    PeerFailed
    | RoutesChanged
    | RecoveryDue
    | PlacementStale
    | Superseded
    | InstanceReady
    | InstanceFailed
    | InstanceCrashed
    | MarkerReached
    | Snapshotted
    | SnapshotAligned
    | RelocationEnded
    | ReplacementPrepared
    | AppMissing
    | PeerRejoined
    | NodeReset
    | Happened
)
