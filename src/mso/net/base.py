"""The two interfaces every network under a node provides: a transport and a routing view.

A driver (asyncio daemon, simulator) builds one of each and feeds the node core from them, so the
core's procedures run unchanged over TCP on loopback, an emulated MANET, an in-memory network or
(later) a kernel-routed radio network. Both are :class:`typing.Protocol`\\ s: implementations
need not inherit, only match.

- :class:`Transport` moves *frames* between node ids. A frame is an encoded
  :class:`~mso.protocol.messages.Envelope` (``m.wrap``) plus its kind, because the kind decides
  how a link treats it (control overtakes data, only data may be dropped by emulated loss,
  markers keep their place among data) and relays must decide that without decoding the body.
- :class:`RoutingView` says what the node currently knows: neighbours (with their address and
  link shape), routes ``destination -> (next hop, hops)``, and when that changes. Route changes
  are events, pushed to subscribers, because the core (recovery, the route rule) and the
  transport (frames waiting for a route) must both react at once. The view also carries the
  byte counters, since "what this node's radio sent, received and relayed" is a property of
  the network under it (a kernel view will read interface counters).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from mso.protocol import messages as m

Kind = int
"""A frame's kind: :data:`CONTROL`, :data:`DATA`, :data:`MARKER` or :data:`HEARTBEAT`
(``Envelope.kind``)."""
CONTROL: Kind = m.CONTROL
DATA: Kind = m.DATA
MARKER: Kind = m.MARKER
HEARTBEAT: Kind = m.HEARTBEAT

Route = tuple[str, int]
"""``(next hop, hops)`` toward a destination, as :meth:`NodeCore.set_routes` takes it."""

Receiver = Callable[[str, m.Message], None]
"""Called with ``(source node, message)`` for every message addressed to this node."""


@dataclass(frozen=True)
class LinkShape:
    """What the sender of an emulated link applies: bandwidth (None: unlimited), delay, loss of
    data frames. All zero/None on a real network, where the radio does the shaping."""

    bandwidth_mbps: float | None = None
    delay_ms: float = 0.0
    loss: float = 0.0

    @property
    def shaped(self) -> bool:
        """Whether frames must be scheduled at all (loss alone needs no timer)."""
        return self.bandwidth_mbps is not None or self.delay_ms > 0


@dataclass(frozen=True)
class Neighbour:
    """A node one hop away: where to reach it and the shape of the link to it."""

    host: str
    port: int
    shape: LinkShape = field(default_factory=LinkShape)


@dataclass(frozen=True)
class RoutesChanged:
    """A routing view's new state, given to every subscriber."""

    routes: Mapping[str, Route]
    neighbours: Mapping[str, Neighbour]


class Counters:
    """Byte and frame counters the monitor and ``mso status`` report.

    ``bytes_out``/``bytes_in`` are what this node sent and received (relayed frames count in
    both), ``bytes_forwarded`` what it relayed for others; the ``frames_*`` counters are frames
    given up on, and why.
    """

    def __init__(self) -> None:
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_forwarded = 0
        self.frames_rejected = 0  # failed authentication
        self.frames_malformed = 0  # did not decode or validate
        self.frames_dropped_loss = 0  # emulated loss (data frames only)
        self.frames_unroutable = 0  # no next hop in time, data with no route, TTL spent
        self.frames_failed = 0  # handling one raised (a bug): counted, the connection lives on
        self.frames_implausible = 0  # values no genuine node sends (mso.protocol.plausible)
        # a link's queue of that class was full (mso.net.shaping): dropped, not queued
        self.frames_dropped_queue = 0
        # a frame to relay or take whose kind is unknown, not its message's, or whose size
        # its kind does not allow (a bulk frame claiming to be a heartbeat)
        self.frames_bad_kind = 0
        # a frame to relay past the budget of frames its neighbour may have relayed
        self.frames_dropped_rate = 0
        # with node identities: a frame relayed in another node's name without that node's
        # signature, or a message in which its sender speaks for a third node
        # (mso.protocol.origin)
        self.frames_origin_refused = 0
        # with node identities: a data frame relayed to this node whose end-to-end tag is not
        # its source's (altered or injected on the way, or from a source not known or revoked)
        # (mso.protocol.dataseal), and data frames this node sent untagged, its destination's
        # key not known yet (its destination refuses them if relayed; the channel resends)
        self.frames_data_refused = 0
        self.data_untagged = 0

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))


@runtime_checkable
class RoutingView(Protocol):
    """What a node knows of the network around it: neighbours, routes, their changes."""

    counters: Counters

    def routes(self) -> Mapping[str, Route]:
        """Current routes, ``destination -> (next hop, hops)``; never a route to this node."""
        ...

    def neighbours(self) -> Mapping[str, Neighbour]:
        """Nodes currently one hop away."""
        ...

    def next_hop(self, dst: str) -> str | None:
        """The neighbour to hand a frame for ``dst`` to; None when there is no route."""
        ...

    def subscribe(self, callback: Callable[[RoutesChanged], None]) -> Callable[[], None]:
        """Call ``callback`` after every change, in subscription order; returns an unsubscribe
        function. The view does not call it for the state it had when subscribed."""
        ...

    def detour(self, dst: str) -> str | None:
        """Another neighbour that reaches ``dst`` on its own, for when the direct way does not
        work (a neighbour whose connection cannot be made: an asymmetric route); None when
        there is none or the view cannot tell (:mod:`mso.net.routes_kernel` can)."""
        ...


@runtime_checkable
class Transport(Protocol):
    """Sends frames to node ids (hop by hop, along a :class:`RoutingView`) and hands the
    messages addressed to this node to one receiver."""

    @property
    def node_id(self) -> str:
        """This node's id: frames it sends carry it as source."""
        ...

    def send(self, dst: str, payload: bytes, kind: Kind) -> None:
        """Send ``payload`` (an envelope from :func:`encode`) toward ``dst``. Never blocks and
        never raises for an unreachable node: a control or marker frame with no next hop waits
        for the routes to change (:class:`~mso.net.forwarding.RouteWait`), a data frame is
        dropped and counted (acks and replay recover it)."""
        ...

    def set_receiver(self, receiver: Receiver) -> None:
        """Where messages addressed to this node go (the driver feeds them to the core)."""
        ...


def encode(src: str, dst: str, msg: m.Message) -> tuple[bytes, Kind]:
    """The frame and its kind for ``msg`` from ``src`` to ``dst``: the one encoding a
    :class:`Transport` accepts. Raises what msgspec raises for a message that cannot be
    encoded (a bug in the sender)."""
    return m.wrap(src, dst, msg), m.kind_of(msg)
