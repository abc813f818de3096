"""A node's status: what ``mso status``, the dashboard and the metrics endpoint show, composed
from each component's own typed record.

Each component reports its part as a ``msgspec.Struct`` beside the figures it owns: an app's
(:class:`~mso.protocol.state.AppStatus`, with its vertices and edges) in
:mod:`mso.protocol.state`, membership's in :mod:`~mso.protocol.procedures.membership.peers`
(the detector's in ``liveness``), the monitor's in :mod:`mso.node.monitor`, the management
loop's in :mod:`mso.node.manager` (the rule engine's in :mod:`mso.management.engine`), the
authority's in :mod:`mso.protocol.authority`. :func:`node_status` composes them into a
:class:`NodeStatus`; :func:`to_wire` is the one place it becomes the plain dict a
``StatusReply`` carries and every consumer reads, and :func:`from_wire` gives a client the typed
record back.
"""

from __future__ import annotations

import datetime
import decimal
import uuid
from typing import TYPE_CHECKING, Any, Protocol

import msgspec
from msgspec import UNSET, UnsetType

from mso.node.manager import ManagementStatus, Manager
from mso.node.monitor import Monitor, MonitorStatus
from mso.node.moves import MoveLog, MoveRecord
from mso.protocol.authority import AuthorityStatus
from mso.protocol.control_stream import ControlStreams
from mso.protocol.procedures.membership.liveness import LivenessStatus
from mso.protocol.procedures.membership.peers import Membership
from mso.protocol.procedures.membership.status import Heard
from mso.protocol.state import Apps, AppStatus

if TYPE_CHECKING:
    from mso.protocol.dataplane import DataPlane


class Route(msgspec.Struct, frozen=True, array_like=True):
    """A route as status shows it: ``[next hop, hops]``."""

    hop: str
    hops: int


class LinkStatus(msgspec.Struct, frozen=True, kw_only=True):
    """What the asyncio driver says of its links and connections (a simulation has none)."""

    traffic: dict[str, int]  # the transport's frame and byte counters
    connections: dict[str, int]  # connections refused or closed by the limits
    connected: list[str]  # neighbours with an open connection
    tasks: int  # a soak watches these for leaks
    timers: int
    authority: AuthorityStatus


class NodeStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One node's status, as the wire carries it: the driver's links (absent in simulation),
    the node's own figures and each component's part. The links' and membership's fields
    stand at the top level on the wire, so they are declared here again;
    :func:`node_status` fills them from :class:`LinkStatus` and
    :class:`~mso.protocol.procedures.membership.status.MembershipStatus` whole."""

    traffic: dict[str, int] | UnsetType = UNSET
    connections: dict[str, int] | UnsetType = UNSET
    connected: list[str] | UnsetType = UNSET
    tasks: int | UnsetType = UNSET
    timers: int | UnsetType = UNSET
    authority: AuthorityStatus | UnsetType = UNSET
    node: str
    monitor: MonitorStatus
    routes: dict[str, Route]  # by destination
    neighbours: list[str]
    apps: dict[str, AppStatus]
    dropped_messages: int
    refusals: dict[str, int]  # messages refused, by reason
    illegal_transitions: int
    handler_errors: int
    last_handler_error: str
    procedures: list[dict[str, Any]]  # open ones: each procedure describes itself
    management: ManagementStatus
    # membership's (MembershipStatus)
    failed_nodes: list[str]
    suspected_nodes: list[str]
    unreachable_nodes: list[str] = msgspec.field(default_factory=list)  # (older nodes: none)
    incarnation: int
    failures: list[dict[str, Any]]
    rejoins: list[dict[str, Any]]
    liveness: LivenessStatus
    heard: dict[str, Heard]
    # the moves this node coordinated, who asked in words (mso.node.moves), and the node's
    # clock at this status: every time in it (failures, decisions) is on that clock, so a
    # reader places it on its own by its age
    moves: list[MoveRecord] = msgspec.field(default_factory=list)
    clock: float = 0.0
    # the control streams' counters (mso.protocol.control_stream): frames kept unacknowledged
    # now, sent again, given up, taken twice, of an earlier incarnation (older nodes: none)
    control_streams: dict[str, int] = msgspec.field(default_factory=dict)


class StatusSource(Protocol):
    """The core, as status reads it: its tables and its components."""

    id: str
    routes: dict[str, tuple[str, int]]
    apps: Apps
    monitor: Monitor
    dataplane: DataPlane
    membership: Membership
    manager: Manager
    streams: ControlStreams
    movelog: MoveLog
    dropped_messages: int
    refusals: dict[str, int]
    illegal_transitions: int
    handler_errors: int
    last_handler_error: str

    @property
    def links(self) -> LinkStatus | None: ...

    def open_procedures(self, now: float) -> list[dict[str, Any]]: ...


def node_status(core: StatusSource, now: float) -> NodeStatus:
    """The node's status: the driver's links, then each component's part (the monitor as
    last sampled)."""
    links = msgspec.structs.asdict(core.links) if core.links is not None else {}
    return NodeStatus(
        **links,
        node=core.id,
        monitor=core.monitor.status(),
        routes={d: Route(hop, hops) for d, (hop, hops) in sorted(core.routes.items())},
        neighbours=sorted(n for n, (hop, _) in core.routes.items() if hop == n),
        apps={name: dep.status(now) for name, dep in core.apps.items()},
        dropped_messages=core.dropped_messages,
        refusals=dict(sorted(core.refusals.items())),
        illegal_transitions=core.illegal_transitions,
        handler_errors=core.handler_errors,
        last_handler_error=core.last_handler_error,
        procedures=core.open_procedures(now),
        management=core.manager.status(),
        **msgspec.structs.asdict(core.membership.status()),
        moves=core.movelog.status(now),
        clock=round(now, 3),
        control_streams=core.streams.status(),
    )


# what msgpack carries as it is: left so in the free-form figures (a vertex's ``stats``), which
# to_builtins would otherwise turn into strings
_AS_IS = (
    bytes,
    bytearray,
    memoryview,
    datetime.datetime,
    datetime.date,
    datetime.time,
    datetime.timedelta,
    uuid.UUID,
    decimal.Decimal,
)


def to_wire(status: NodeStatus) -> dict[str, Any]:
    """The plain dict a ``StatusReply`` carries and every consumer reads: the one conversion."""
    wire: dict[str, Any] = msgspec.to_builtins(status, builtin_types=_AS_IS)
    return wire


def from_wire(status: dict[str, Any]) -> NodeStatus:
    """A node's status from a ``StatusReply``, typed (fields a newer node adds are ignored)."""
    return msgspec.convert(status, NodeStatus)
