"""Taps: copies of a running edge's events for someone looking at it (``mso echo``, ``mso hz``,
``mso record``). Sans-IO, a component of the data plane.

A client sends :class:`~mso.protocol.tapwire.Tap` to any node. The node hosting the edge's
consumer *serves* the tap: as events of the edge reach the consumer (fresh ones, in order) it
counts them, notes how long each batch had been in its chain, and keeps copies, at most
``rate`` a second in a bounded queue (events and bytes); every :data:`FLUSH_S` it sends what it
has as :class:`~mso.protocol.tapwire.TapEvents`. A copy that does not fit is dropped and
counted for the tap alone: the edge's own events are never held, delayed or lost for a tap
(the copies are references to the same bytes, taken after the events were accepted).

Any other node asked *relays*: it asks the consumer's host with its own tap id, forwards what
comes back to its client, and follows the consumer when it moves (the host answers
``ended: moved`` with where to; a relocation hands the tap over before the consumer's state,
so the new host serves it from its first event). Copies that cross the overlay travel as data
(control overtakes them) and at most :data:`RELAYED_BYTES_S` a second.

Every tap has a lease (``lease_s``): the client asks again to keep it, the relay renews the
host's lease only then, so a client that goes away ends its tap everywhere within the lease.

States, per served tap and per relay (keyed by typed inputs)::

    (none)  --Tap-->            serving / relaying    (renewed by each Tap)
    serving --TapTick, lease over-->            gone (silently: nobody listens)
    serving --consumer handed over (hand_over)-->   gone; the new host asked first, so it
                                                 serves from the first event it takes
    serving --TapTick, app stopped or consumer moved--> gone, ended told
    relaying --TapEvents ended=moved, host-->   relaying to the new host (or serving here)
    relaying --TapEvents ended / lease over-->  gone
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec

from mso.model.app import App
from mso.protocol.context import NodeContext
from mso.protocol.state import AppState
from mso.protocol.tapwire import Tap, TapEvents

FLUSH_S = 0.1  # a served tap sends what it has this often
QUIET_S = 1.0  # an idle tap still reports this often (so a rate of 0 shows)
MIN_LEASE_S, MAX_LEASE_S = 0.5, 30.0
MAX_RATE = 10_000.0  # copies a second, at most
MAX_SERVED = 16  # taps served by one node at once
MAX_RELAYS = 16  # taps relayed by one node at once
QUEUE_EVENTS = 256  # copies a served tap holds between two flushes, at most
QUEUE_BYTES = 4 << 20  # and their bytes
RELAYED_BYTES_S = 1 << 20  # copies sent across the overlay, bytes a second per tap
MAX_DELAYS = 256  # delays noted between two flushes
MOVED = "moved"
_NAMES_SHOWN = 12


@dataclass(frozen=True)
class TapTick:
    """Flush the served taps, end those whose lease is over or whose consumer left."""


def find_edge(app: App, name: str) -> int | str:
    """The index of the edge ``name`` (``src->dst``, ``src:dst``, or a vertex with one output
    edge) in ``app``, or why there is none."""
    edges = app.edges
    names = [f"{e.src}->{e.dst}" for e in edges]
    listed = ", ".join(names[:_NAMES_SHOWN]) + (", ..." if len(names) > _NAMES_SHOWN else "")
    src, sep, dst = name.partition("->")
    if not sep:
        src, sep, dst = name.partition(":")
    src, dst = src.strip(), dst.strip()
    if sep:
        for i, e in enumerate(edges):
            if e.src == src and e.dst == dst:
                return i
        return f"app {app.name!r} has no edge {name!r} (edges: {listed})"
    outs = [i for i, e in enumerate(edges) if e.src == src]
    if len(outs) == 1:
        return outs[0]
    if outs:
        many = ", ".join(names[i] for i in outs)
        return f"vertex {src!r} has {len(outs)} output edges; name one: {many}"
    if src in app.vertices:
        return f"vertex {src!r} of app {app.name!r} has no output edge (edges: {listed})"
    return f"app {app.name!r} has no vertex or edge {name!r} (edges: {listed})"


def format_of(app: App, edge: int) -> tuple[str, list[str]]:
    """How to read the edge's events: its format's import path, and a positional (array-like)
    format's field names (a reader decodes the msgpack without importing anything)."""
    fmt = app.edge_format(app.edges[edge])
    if fmt is None:
        return "", []
    fields: list[str] = []
    if fmt.__struct_config__.array_like:
        fields = [f.name for f in msgspec.structs.fields(fmt)]
    return f"{fmt.__module__}:{fmt.__qualname__}", fields


def _lease(value: float) -> float:
    return min(MAX_LEASE_S, max(MIN_LEASE_S, value)) if math.isfinite(value) else MIN_LEASE_S


def _rate(value: float) -> float | None:
    return value if math.isfinite(value) and 0 <= value <= MAX_RATE else None


@dataclass
class Served:
    """A tap served here: copies of one edge for a client here (``origin`` '') or a relay."""

    origin: str
    client: int  # the client's connection here, or the relay's tap id
    app: str
    edge: int
    name: str
    rate: float
    expires: float
    filled: float
    tokens: float = 1.0
    byte_tokens: float = float(RELAYED_BYTES_S)
    seen: int = 0
    dropped: int = 0
    seqs: list[int] = field(default_factory=list)
    events: list[bytes] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    queued_bytes: int = 0
    delays: list[float] = field(default_factory=list)
    last_sent: float = -math.inf

    def take(self, first_seq: int, events: list[bytes], ts: float, now: float) -> None:
        """Events of the edge reached the consumer: count them, copy what the bounds allow."""
        if ts > 0 and len(self.delays) < MAX_DELAYS:
            self.delays.append(round((now - ts) * 1e3, 3))
        if self.rate > 0:
            cap = max(1.0, self.rate * 0.2)
            self.tokens = min(cap, self.tokens + (now - self.filled) * self.rate)
            self.byte_tokens = min(
                float(RELAYED_BYTES_S), self.byte_tokens + (now - self.filled) * RELAYED_BYTES_S
            )
            self.filled = now
        for i, ev in enumerate(events):
            if not ev:  # the end of the stream, not an event
                continue
            self.seen += 1
            if self.rate <= 0:
                continue
            size = len(ev)
            if (
                self.tokens < 1
                or len(self.events) >= QUEUE_EVENTS
                or self.queued_bytes + size > QUEUE_BYTES
                or (self.origin and size > self.byte_tokens)
            ):
                self.dropped += 1
                continue
            self.tokens -= 1
            if self.origin:
                self.byte_tokens -= size
            self.seqs.append(first_seq + i)
            self.events.append(ev)
            self.stamps.append(now)
            self.queued_bytes += size


@dataclass
class Relay:
    """A client's tap relayed here to the consumer's host."""

    client: int
    app: str
    edge: int
    name: str
    rate: float
    lease_s: float
    host: str
    expires: float


class Taps:
    """The taps a node serves and relays (see the module docstring)."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        self.served: dict[tuple[str, int, str, int], Served] = {}
        self.watched: dict[tuple[str, int], list[Served]] = {}  # (app, edge) -> its taps
        self.relays: dict[int, Relay] = {}
        self.relayed: dict[tuple[int, str, int], int] = {}  # (client, app, edge) -> tap id
        self._next_tap = 0
        self._armed = False
        self.refused = 0  # taps refused: too many, bad rate, unknown edge

    # -- inputs ------------------------------------------------------------------------------
    def on_client(self, client: int, msg: Tap, now: float) -> None:
        """A client asks (or asks again) for a tap."""
        found = self._resolve(msg)
        if isinstance(found, str):
            self._end_client(client, msg, found)
            return
        dep, edge, rate = found
        dst = dep.app.edges[edge].dst
        host = dep.placed.get(dst, "")
        lease = _lease(msg.lease_s)
        known = self.relayed.get((client, dep.app.name, edge))
        if host == self.ctx.id:
            if known is not None:  # (restored here: the relay has nobody to ask)
                self._drop_relay(known)
            self._serve("", client, dep.app, edge, rate, now + lease, now)
            return
        if not host:
            self._end_client(client, msg, f"no node runs {dst!r} now")
            return
        tid = self._relay(client, dep.app.name, edge, msg.edge, host)
        if tid is None:
            self._end_client(client, msg, f"{self.ctx.id} relays {MAX_RELAYS} taps already")
            return
        relay = self.relays[tid]
        if relay.host in self.ctx.failed:  # its node failed: ask where it was restored
            relay.host = host
        relay.rate, relay.lease_s, relay.expires = rate, lease, now + lease
        self.ctx.send(relay.host, Tap(relay.app, relay.name, rate, lease, tid))
        self._arm(now)

    def on_peer(self, src: str, msg: Tap, now: float) -> None:
        """A relay asks (or asks again) this node to serve a tap; or the consumer's old host
        hands one over with the consumer, for the relay named in ``to``."""
        origin = msg.to or src
        found = self._resolve(msg)
        if isinstance(found, str):
            self._tell(origin, msg.tap, msg, found)
            return
        dep, edge, rate = found
        dst = dep.app.edges[edge].dst
        if dst not in dep.instances and dst not in dep.awaiting:
            self._tell(origin, msg.tap, msg, MOVED, host=dep.placed.get(dst, ""))
            return
        self._serve(origin, msg.tap, dep.app, edge, rate, now + _lease(msg.lease_s), now)

    def hand_over(self, app: str, vertex: str, to: str, now: float) -> None:
        """``vertex`` leaves for ``to`` (its state goes next): the taps of its input edges are
        asked of ``to`` first, so it serves them from the first event its instance takes there
        (those that wait for the handover included) and no copy falls between the two hosts.
        What was kept here goes out now, with ``host``; a client here is relayed to ``to``
        from now on, a relay elsewhere is told (``moved``) and served by ``to`` already."""
        for key, tap in list(self.served.items()):
            dep = self.ctx.apps.get(tap.app)
            if tap.app != app or dep is None or dep.app.edges[tap.edge].dst != vertex:
                continue
            self._flush(tap, now, ended=MOVED if tap.origin else "", host=to)
            self._unserve(key)
            lease = max(MIN_LEASE_S, tap.expires - now)
            if not tap.origin:  # a client of this node: relayed from here from now on
                tid = self._relay(tap.client, app, tap.edge, tap.name, to)
                if tid is None:  # (no room: the client's next ask relays it, with a gap)
                    continue
                relay = self.relays[tid]
                relay.rate, relay.lease_s, relay.expires = tap.rate, lease, tap.expires
                self.ctx.send(to, Tap(app, tap.name, tap.rate, lease, tid))
            elif tap.origin != to:  # (a relay on ``to`` itself serves it when told moved)
                self.ctx.send(to, Tap(app, tap.name, tap.rate, lease, tap.client, to=tap.origin))
        self._arm(now)

    def on_events(self, src: str, msg: TapEvents, now: float) -> None:
        """What a host sent for a tap relayed here: on to the client (following a move)."""
        relay = self.relays.get(msg.tap)
        if relay is None or relay.host != src:
            self.ctx.dropped()
            return
        if msg.ended == MOVED and msg.host and msg.host != src:
            relay.host = msg.host
            # the old host's last word goes to the client before anything of the new host's
            self.ctx.reply(relay.client, msgspec.structs.replace(msg, tap=0, ended=""))
            if msg.host == self.ctx.id:  # moved here: served here from now on
                self._drop_relay(msg.tap)
                dep = self.ctx.apps.get(relay.app)
                if dep is not None:
                    self._serve(
                        "", relay.client, dep.app, relay.edge, relay.rate, relay.expires, now
                    )  # fmt: skip
            else:
                tap = Tap(relay.app, relay.name, relay.rate, relay.lease_s, msg.tap)
                self.ctx.send(msg.host, tap)
            return
        if msg.ended:
            self._drop_relay(msg.tap)
        self.ctx.reply(relay.client, msgspec.structs.replace(msg, tap=0))

    def saw(self, app: str, edge: int, first_seq: int, events: list[bytes], ts: float) -> None:
        """Events of an edge reached its consumer here (the data plane calls this only for
        edges in :attr:`watched`)."""
        for tap in self.watched.get((app, edge), ()):
            tap.take(first_seq, events, ts, self.ctx.now)

    def tick(self, _key: TapTick, now: float) -> None:
        self._armed = False
        for key, tap in list(self.served.items()):
            if tap.expires < now:  # nobody asked again: the client went away
                self._unserve(key)
                continue
            dep = self.ctx.apps.get(tap.app)
            if dep is None or tap.edge >= len(dep.app.edges):
                self._flush(tap, now, ended=f"app {tap.app!r} stopped")
                self._unserve(key)
                continue
            dst = dep.app.edges[tap.edge].dst
            if dst not in dep.instances and dst not in dep.awaiting:
                self._flush(tap, now, ended=MOVED, host=dep.placed.get(dst, ""))
                self._unserve(key)
                continue
            if tap.events or tap.delays or now - tap.last_sent >= QUIET_S:
                self._flush(tap, now)
        for tid, relay in list(self.relays.items()):
            if relay.expires < now:
                self._drop_relay(tid)
        self._arm(now)

    # -- helpers -----------------------------------------------------------------------------
    def _resolve(self, msg: Tap) -> tuple[AppState, int, float] | str:
        rate = _rate(msg.rate)
        if rate is None:
            self.refused += 1
            return f"rate: expected copies a second from 0 to {MAX_RATE:g}, got {msg.rate!r}"
        dep = self.ctx.apps.get(msg.app)
        if dep is None:
            self.refused += 1
            return f"no running app named {msg.app!r} (as {self.ctx.id} knows)"
        edge = find_edge(dep.app, msg.edge)
        if isinstance(edge, str):
            self.refused += 1
            return edge
        return dep, edge, rate

    def _serve(
        self,
        origin: str,
        client: int,
        app: App,
        edge: int,
        rate: float,
        expires: float,
        now: float,
    ) -> None:
        key = (origin, client, app.name, edge)
        name = f"{app.edges[edge].src}->{app.edges[edge].dst}"  # as status names it
        tap = self.served.get(key)
        if tap is None:
            if len(self.served) >= MAX_SERVED:
                self.refused += 1
                why = f"{self.ctx.id} serves {MAX_SERVED} taps already"
                probe = Served(origin, client, app.name, edge, name, rate, expires, now)
                self._flush(probe, now, ended=why)
                return
            tap = Served(origin, client, app.name, edge, name, rate, expires, now)
            self.served[key] = tap
            self.watched.setdefault((app.name, edge), []).append(tap)
            self._flush(tap, now)  # at once: the client knows it is served, and how to read
        tap.rate, tap.expires = rate, max(tap.expires, expires)
        self._arm(now)

    def _unserve(self, key: tuple[str, int, str, int]) -> None:
        tap = self.served.pop(key)
        taps = self.watched.get((tap.app, tap.edge), [])
        if tap in taps:
            taps.remove(tap)
        if not taps:
            self.watched.pop((tap.app, tap.edge), None)

    def _relay(self, client: int, app: str, edge: int, name: str, host: str) -> int | None:
        """The id of the relay of ``client``'s tap of ``edge`` (made now, to ``host``), or
        None when this node relays MAX_RELAYS taps already."""
        tid = self.relayed.get((client, app, edge))
        if tid is not None:
            return tid
        if len(self.relays) >= MAX_RELAYS:
            return None
        self._next_tap += 1
        tid = self._next_tap
        self.relays[tid] = Relay(client, app, edge, name, 0.0, MIN_LEASE_S, host, -math.inf)
        self.relayed[(client, app, edge)] = tid
        return tid

    def _drop_relay(self, tid: int) -> None:
        relay = self.relays.pop(tid, None)
        if relay is not None:
            self.relayed.pop((relay.client, relay.app, relay.edge), None)

    def _flush(self, tap: Served, now: float, ended: str = "", host: str = "") -> None:
        dep = self.ctx.apps.get(tap.app)
        fmt, fields = format_of(dep.app, tap.edge) if dep is not None else ("", [])
        msg = TapEvents(
            tap.client if tap.origin else 0, tap.app, tap.name, self.ctx.id, now, tap.seen,
            tap.dropped, tap.seqs, tap.events, tap.stamps, tap.delays, fmt, fields, ended, host,
        )  # fmt: skip
        tap.seqs, tap.events, tap.stamps, tap.delays, tap.queued_bytes = [], [], [], [], 0
        tap.last_sent = now
        if tap.origin:
            self.ctx.send(tap.origin, msg)
        else:
            self.ctx.reply(tap.client, msg)

    def _tell(self, dst: str, tid: int, msg: Tap, why: str, host: str = "") -> None:
        self.ctx.send(dst, TapEvents(tid, msg.app, msg.edge, self.ctx.id, self.ctx.now, 0, 0,
                                     ended=why, host=host))  # fmt: skip

    def _end_client(self, client: int, msg: Tap, why: str) -> None:
        reply = TapEvents(0, msg.app, msg.edge, self.ctx.id, self.ctx.now, 0, 0, ended=why)
        self.ctx.reply(client, reply)

    def _arm(self, now: float) -> None:
        if not self._armed and (self.served or self.relays):
            self._armed = True
            self.ctx.set_timer(TapTick(), now + FLUSH_S)
