"""The TCP transport: one authenticated connection per neighbour pair, hop-by-hop forwarding.

Frames arrive on TCP connections (neighbours, clients, the emulator controller), are
authenticated by :class:`~mso.protocol.framing.FrameCodec` and decoded; a frame for another
node is forwarded toward it without decoding its body, one for this node goes to the receiver
(from a neighbour) or to the client handler (from a client). Nodes talk only to their current
neighbours, as the :class:`~mso.net.base.RoutingView` says; each neighbour link shapes its
frames in the sender (:mod:`mso.net.shaping`).

Two kinds of waiting, both bounded:

- a frame whose next hop is a neighbour still connecting is *held* for that neighbour and
  sent once the connection is up (after a link appears the connection takes a moment); when
  the connection has not come for :data:`DETOUR_AFTER_S` and the view names another neighbour
  that reaches the node (:meth:`~mso.net.base.RoutingView.detour`: an asymmetric route, where
  this node's kernel routes to the neighbour but the neighbour's replies have no way back),
  the held frames and the next ones go through that neighbour instead, until it connects;
- a control or marker frame with no next hop at all waits for the routes to change
  (:class:`~mso.net.forwarding.RouteWait`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import zlib
from collections import deque
from collections.abc import Callable

import msgspec

from mso.net.admission import Admission
from mso.net.base import DATA, HEARTBEAT, Counters, Kind, Receiver, RoutesChanged, RoutingView
from mso.net.forwarding import RouteWait
from mso.net.limits import DEFAULT_LIMITS, ConnectionCounters, Limits
from mso.net.relaying import RelayBudget
from mso.net.shaping import Link
from mso.net.trust import Trust
from mso.protocol import messages as m
from mso.protocol import origin
from mso.protocol.authority import DOCUMENT_MESSAGES, Authority
from mso.protocol.clients import Admitted
from mso.protocol.framing import FrameCodec, FramingError, WrongKey
from mso.protocol.identity import Identity
from mso.protocol.plausible import implausible

log = logging.getLogger("mso.node")

HIGH_WATER = 1 << 20  # a connection's write buffer limit: beyond it the link stops pumping
MAX_HELD = 10_000  # frames kept per neighbour while its connection is being set up
CONNECT_ATTEMPTS = 20
CONNECT_TIMEOUT_S = 5.0  # a SYN nobody answers (no return route) would wait two minutes
DETOUR_AFTER_S = 0.5
"""How long a neighbour may stay unconnected before its frames go through a detour."""
TELL_REVOCATIONS = 256  # the newest revocations told to a neighbour whose link is proven

ClientHandler = Callable[[int, m.Message], None]
"""Called with ``(client connection id, message)`` for every request from a client."""


class Connection(asyncio.Protocol):
    """One TCP connection: framing, authentication, and who is on the other end."""

    def __init__(self, net: TcpTransport, peer: str | None = None) -> None:
        self.net = net
        self.codec = FrameCodec(
            net.psks, max_frame=net.limits.max_frame, encrypt=net.encrypt, responder=peer is None
        )
        self.transport: asyncio.Transport | None = None
        self.peer = peer  # neighbour node id once known
        self.client: int | None = None
        self.paused = False
        self.link: Link | None = None
        self.address = ""  # the remote host of an accepted connection
        self.opened = self.last_rx = net.loop.time()
        self.outbound = peer is not None
        self.said_hello = False
        self.verified = False  # the peer proved its node identity (when they are required)
        self.key_id = ""  # the id of the node (or client) key it proved it with
        # the client it proved to be, or why it did not (when identities are required)
        self.client_as: Admitted | str | None = None

    @property
    def introduced(self) -> bool:
        """Authenticated and said who it is (a neighbour's or a client's hello)."""
        return self.codec.confirmed and (self.peer in self.net.peers or self.client is not None)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if not self.outbound:
            peername = transport.get_extra_info("peername")
            self.address = str(peername[0]) if peername else ""
            if not self.net.admit(self):
                transport.abort()
                return
        transport.set_write_buffer_limits(high=HIGH_WATER)
        transport.write(self.codec.hello())
        if self.peer is not None and self.net.identity is None:
            self.say_hello()  # (with an identity: once the peer's hello is in, to sign it)

    def say_hello(self) -> None:
        """Tell the peer who this node is, with its identity's proof if it has one."""
        self.said_hello = True
        me, identity = self.net.node_id, self.net.identity
        if identity is None:
            self.send_message(self.peer or "", m.PeerHello(me))
            return
        sig = identity.prove(self.codec.hello(), self.codec.peer_hello)
        cert = msgspec.msgpack.encode(identity.cert)
        self.send_message(self.peer or "", m.PeerHello(me, cert, sig))

    def abort(self) -> None:
        """Close at once, dropping what is unsent (a connection that is refused or evicted)."""
        if self.transport is not None:
            self.transport.abort()

    def send_message(self, dst: str, msg: m.Message) -> None:
        """Write ``msg`` on this connection now, unshaped (hellos and client replies)."""
        self.write_frame(m.wrap(self.net.node_id, dst, msg))

    def write_frame(self, payload: bytes) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        frame = self.codec.seal(payload)
        self.net.counters.bytes_out += len(frame)
        if frame:
            self.transport.write(frame)
            if self.client is not None and self.net.over_backlog(self.transport):
                self.net.connection_counters.over_buffer += 1
                log.warning("closing a client that does not read its replies")
                self.transport.abort()

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        if self.link is not None:
            self.link.pump()

    def data_received(self, data: bytes) -> None:
        counters = self.net.counters
        counters.bytes_in += len(data)
        self.last_rx = self.net.loop.time()
        rejected = self.codec.rejected
        try:
            payloads, flush = self.codec.feed(data)
        except FramingError as exc:
            counters.frames_rejected += 1
            log.warning("closing connection: %s", exc)
            assert self.transport is not None
            if isinstance(exc, WrongKey):  # a plain close: nothing to test guesses against
                self.net.connection_counters.wrong_key += 1
            if not self.outbound:
                self.net.admission.failed(self, self.net.loop.time())
            self.transport.close()
            return
        counters.frames_rejected += self.codec.rejected - rejected
        if flush and self.transport is not None:
            self.transport.write(flush)
        if self.outbound and not self.said_hello and self.codec.ready:
            self.say_hello()
        if not self.net.hold(self, self.codec.buffered):
            assert self.transport is not None
            self.transport.abort()
            return
        for payload in payloads:
            try:
                env = m.unwrap(payload)
            except (msgspec.DecodeError, msgspec.ValidationError):
                counters.frames_malformed += 1
                continue
            try:
                self.net.on_envelope(self, env, len(payload))
            except Exception as exc:  # a bug costs that frame, never the connection
                counters.frames_failed += 1
                log.error(
                    "handling a frame from %s raised %s: %s", env.src, type(exc).__name__, exc
                )
        if payloads:
            self.net.read_done()

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
        if self.transport is not None:
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.net.on_connection_lost(self)


class TcpTransport:
    """A :class:`~mso.net.base.Transport` over TCP along a routing view.

    It serves clients on the same port (CLI, API, the emulator controller): their requests go to
    the client handler and :meth:`reply` answers them. It subscribes to ``view`` when made, so
    on a route change it has already reconnected, reshaped and released waiting frames before
    any later subscriber (the driver, which then tells the core) runs.
    """

    def __init__(
        self,
        node_id: str,
        host: str,
        port: int,
        psk: bytes | list[bytes],
        view: RoutingView,
        limits: Limits = DEFAULT_LIMITS,
        authority: Authority | None = None,
        encrypt: bool = False,
        identity: Identity | None = None,
    ) -> None:
        self._node_id = node_id
        self.identity = identity  # this node's own key and certificate, if it has one
        self.encrypt = encrypt  # ChaCha20-Poly1305 frames (every member must agree)
        self.limits = limits
        self.authority = authority or Authority()
        self.connection_counters = ConnectionCounters()
        self.accepted: set[Connection] = set()  # connections others opened to this node
        self.admission = Admission(limits, self.connection_counters)
        self.relay_budget = RelayBudget(limits.relay_control_per_s, limits.relay_beats_per_s)
        self.trust = Trust(identity, self.authority, view.counters, self.connection_counters)
        self.host = host
        self.port = port
        # the overlay keys: the first seals new connections, all are accepted (key rotation)
        self.psks: list[bytes] = [psk] if isinstance(psk, bytes) else list(psk)
        self.view = view
        self.counters: Counters = view.counters
        self.loop = asyncio.get_running_loop()
        self.peers: dict[str, Connection] = {}
        self.clients: dict[int, Connection] = {}
        # frames per neighbour still connecting: (payload, kind, this node's own frame)
        self.held: dict[str, deque[tuple[bytes, Kind, bool]]] = {}
        self._unconnected: dict[str, float] = {}  # neighbour -> since when it has no link
        self._detour_timers: dict[str, asyncio.TimerHandle] = {}
        self._held_bytes: dict[str, int] = {}
        # frames waiting for a route: (payload, size to count as forwarded once sent)
        self.waiting: RouteWait[tuple[bytes, int]] = RouteWait(
            on_drop=self._unroutable, size=lambda item: len(item[0])
        )
        self.server: asyncio.Server | None = None
        self._client_ids = 0
        self._receiver: Receiver = lambda src, msg: None
        # after the frames of one read are handed over: a driver carries out in the same turn
        # what they made (a cheap vertex's calls), not in a turn of the loop of its own
        self.read_done: Callable[[], None] = lambda: None
        self._on_client: ClientHandler = lambda client, msg: None
        self._closed = False
        self._sweeper: asyncio.TimerHandle | None = None
        self._held: dict[Connection, int] = {}  # partial frames held, by connection
        self._held_total = 0
        view.subscribe(self._routes_changed)

    @property
    def node_id(self) -> str:
        return self._node_id

    def set_receiver(self, receiver: Receiver, read_done: Callable[[], None] | None = None) -> None:
        self._receiver = receiver
        if read_done is not None:
            self.read_done = read_done

    def set_client_handler(self, handler: ClientHandler) -> None:
        self._on_client = handler

    def set_keys(self, keys: list[bytes]) -> None:
        """Rotate the overlay key: new connections seal with ``keys[0]`` and accept any of
        them; connections already open keep theirs, so nothing running is disturbed."""
        if not keys or not all(keys):
            raise ValueError("an overlay key is required")
        self.psks = list(keys)

    def connected(self) -> list[str]:
        """Neighbours with an open connection."""
        return sorted(self.peers)

    async def start(self) -> None:
        """Listen; ``port`` becomes the bound one (0 asks for any free port)."""
        self.server = await self.loop.create_server(
            lambda: Connection(self), self.host, self.port, reuse_address=True
        )
        self.port = self.server.sockets[0].getsockname()[1]
        self._sweeper = self.loop.call_later(self.limits.sweep_s, self._sweep)
        self.routes_changed()

    # -- limits -----------------------------------------------------------------------------
    def admit(self, conn: Connection) -> bool:
        """Take an accepted connection into the pending pool, closing the pending ones
        admission picks to make room (:mod:`mso.net.admission`): never refused for the pool."""
        for victim in self.admission.admit(conn, self.loop.time()):
            log.info("closing a connection from %s still proving the key", victim.address)
            victim.abort()
        self.accepted.add(conn)
        return True

    def _introduced(self, conn: Connection, node: str | None) -> bool:
        """A connection proved the key and said who it is (``node`` for a neighbour's hello):
        it leaves the pending pool. A neighbour the view names is always taken; other
        connections are bounded in number, from the node and from one address."""
        if conn.outbound:
            return True
        self.admission.introduced(conn, self.loop.time())
        if node is not None and node in self.view.neighbours():
            return True
        lim = self.limits
        others = [c for c in self.accepted if c.introduced and c is not conn]
        same = sum(1 for c in others if c.address == conn.address)
        if len(others) < lim.max_connections and same < lim.max_per_address:
            return True
        self.connection_counters.connections_refused += 1
        log.warning("refusing a connection from %s: too many connections", conn.address)
        conn.abort()
        return False

    def hold(self, conn: Connection, held: int) -> bool:
        """Note the partial frame ``conn`` holds; False when it must be closed because every
        connection together holds too much and this one a large share of it."""
        before = self._held.pop(conn, 0)
        self._held_total += held - before
        if held:
            self._held[conn] = held
        lim = self.limits
        if self._held_total > lim.max_buffered and held > lim.max_partial_share:
            self._held_total -= self._held.pop(conn)
            self.connection_counters.over_buffer += 1
            log.warning("closing a connection holding %d bytes of a partial frame", held)
            return False
        return True

    def over_backlog(self, transport: asyncio.Transport) -> bool:
        """Whether a client's unread replies are too many: its own past its bound, or a
        large share while every client's together are past theirs."""
        lim, backlog = self.limits, transport.get_write_buffer_size()
        if backlog > lim.max_client_backlog:
            return True
        if backlog <= lim.max_partial_share:
            return False
        total = sum(
            c.transport.get_write_buffer_size()
            for c in self.clients.values()
            if c.transport is not None
        )
        return total > lim.max_clients_backlog

    def _sweep(self) -> None:
        """Close connections that did not authenticate in time, or fell silent."""
        now = self.loop.time()
        lim, counters = self.limits, self.connection_counters
        for late in self.admission.overdue(now):
            counters.handshake_timeouts += 1
            self.admission.failed(late, now)
            late.abort()
        for conn in [*self.accepted, *self.peers.values()]:
            if conn.transport is None or conn.transport.is_closing():
                continue
            if not conn.introduced:  # (a pending one has its own deadline, above)
                if not self.admission.is_pending(conn) and now - conn.opened > lim.handshake_s:
                    counters.handshake_timeouts += 1
                    conn.transport.abort()
                continue
            idle = lim.client_idle_s if conn.client is not None else lim.peer_idle_s
            if now - conn.last_rx > idle:
                counters.idle_timeouts += 1
                conn.close()
        if not self._closed:
            self._sweeper = self.loop.call_later(lim.sweep_s, self._sweep)

    async def close(self) -> None:
        self._closed = True
        if self._sweeper is not None:
            self._sweeper.cancel()
        for timer in self._detour_timers.values():
            timer.cancel()
        for conn in [*self.peers.values(), *self.clients.values()]:
            conn.close()
        if self.server is not None:
            self.server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.server.wait_closed(), 1.0)

    # -- outbound ---------------------------------------------------------------------------
    def send(self, dst: str, payload: bytes, kind: Kind) -> None:
        if self.identity is not None and self._signs(dst, kind):
            payload = origin.sign(self.identity, payload, time.time_ns() // 1_000_000)
        elif self.identity is not None and kind == DATA and not self._direct(dst):
            payload = self.trust.seal(dst, payload)  # its end-to-end tag (mso.protocol.dataseal)
        if not self._send_toward(dst, payload, kind):
            self.waiting.hold(dst, (payload, 0), kind, self.loop.time())

    def _direct(self, dst: str) -> bool:
        """``dst`` is a neighbour this node's route goes to straight, on a link up now: its
        data frames need no end-to-end tag (the link proves their source). One held or
        detoured meanwhile arrives untagged through a relay, is refused, and its channel
        resends it."""
        conn = self.peers.get(dst)
        return conn is not None and conn.link is not None and self.view.next_hop(dst) == dst

    def _signs(self, dst: str, kind: Kind) -> bool:
        """This node's control and marker frames carry its origin wherever they go (a frame
        for a neighbour may still be detoured), its heartbeats only to a non-neighbour (a
        hello; a neighbour's link proves the rest); data frames never."""
        if kind == HEARTBEAT:
            return dst not in self.view.neighbours()
        return kind in origin.SIGNED_KINDS

    def reply(self, client: int, msg: m.Message) -> None:
        """Answer a client connection (gone clients are ignored)."""
        conn = self.clients.get(client)
        if conn is not None:
            conn.send_message("client", msg)

    def _unroutable(self, _: object = None) -> None:
        self.counters.frames_unroutable += 1

    def _send_toward(
        self, dst: str, payload: bytes, kind: Kind, own: bool = True, via: str | None = None
    ) -> bool:
        """Hand a frame to the next hop toward dst; False when there is no usable next hop.
        Only this node's ``own`` frames take a detour: a relay that detoured what it relays
        could hand it back to the node that detoured it (both routing to a dead node)."""
        hop = self.view.next_hop(dst)
        if hop is None:
            return False
        conn = self.peers.get(hop)
        if conn is not None and conn.link is not None:
            conn.link.send(payload, kind, via)
        elif hop in self.view.neighbours():
            link = self._detour(dst, hop) if own else None
            if link is not None:
                link.send(payload, kind)
            else:
                self._hold(hop, payload, kind, own)
        else:
            return False
        return True

    def _detour(self, dst: str, hop: str, waited: bool = False) -> Link | None:
        """The link to another neighbour that reaches ``dst``, once ``hop`` has been without a
        connection for :data:`DETOUR_AFTER_S` (or ``waited``); what was held for ``hop`` goes
        first."""
        now = self.loop.time()
        if now - self._unconnected.setdefault(hop, now) < DETOUR_AFTER_S and not waited:
            return None
        relay = self.view.detour(dst)
        conn = self.peers.get(relay) if relay is not None else None
        if conn is None or conn.link is None:
            return None
        link = conn.link
        held = self.held.get(hop)
        if hop == dst and held:  # own frames held before it go first; relayed ones stay
            keep: deque[tuple[bytes, Kind, bool]] = deque()
            for item in held:
                if item[2]:
                    link.send(item[0], item[1])
                    self._held_bytes[hop] -= len(item[0])
                else:
                    keep.append(item)
            self.held[hop] = keep
        return link

    def _bad_kind(self, kind: int, size: int) -> bool:
        """A frame's kind is unknown, or it is a heartbeat too large to be one (it would
        overtake every frame on the link): refused and counted, relayed or not."""
        if kind in m.KINDS and (kind != HEARTBEAT or size <= self.limits.max_beat_frame):
            return False
        self.counters.frames_bad_kind += 1
        return True

    def _forward(self, via: str, env: m.Envelope, size: int) -> None:
        """Relay a frame for another node, checked like one of this node's own (its kind, a
        beat's size), within the budget of frames ``via`` (the neighbour that handed it over)
        may have relayed (:mod:`mso.net.relaying`), and queued by its class on the next link,
        where ``via``'s frames take at most a share of each bounded queue."""
        if self._bad_kind(env.kind, size):
            return
        if not self.relay_budget.allow(via, env.kind, self.loop.time()):
            self.counters.frames_dropped_rate += 1
            return
        env.ttl -= 1
        if env.ttl <= 0:
            self._unroutable()
            return
        payload = m.rewrap(env)
        if self._send_toward(env.dst, payload, env.kind, own=False, via=via):
            self.counters.bytes_forwarded += size
        else:
            self.waiting.hold(env.dst, (payload, size), env.kind, self.loop.time())

    def _release(self, dst: str, item: tuple[bytes, int], kind: Kind) -> bool:
        payload, forwarded = item
        if not self._send_toward(dst, payload, kind, own=not forwarded):
            return False
        self.counters.bytes_forwarded += forwarded
        return True

    def _hold(self, node: str, payload: bytes, kind: Kind, own: bool = True) -> None:
        """Keep frames for a neighbour whose connection is still being set up (bounded)."""
        held = self.held.setdefault(node, deque())
        size = self._held_bytes.get(node, 0) + len(payload)
        if len(held) >= MAX_HELD or size > self.limits.max_held_bytes:
            self._unroutable()
            return
        held.append((payload, kind, own))
        self._held_bytes[node] = size
        if own and node not in self._detour_timers and not self._closed:
            self._detour_timers[node] = self.loop.call_later(
                DETOUR_AFTER_S, self._detour_held, node
            )

    def _detour_held(self, node: str) -> None:
        """Frames still held for a neighbour that has not connected: through a detour if the
        view has one, else look again later (while it is a neighbour and frames wait)."""
        del self._detour_timers[node]
        held = self.held.get(node, ())
        if not any(own for *_, own in held) or node not in self.view.neighbours():
            return
        if self._closed:
            return
        if self._detour(node, node, waited=True) is None:
            self._detour_timers[node] = self.loop.call_later(
                DETOUR_AFTER_S, self._detour_held, node
            )

    # -- inbound ----------------------------------------------------------------------------
    @property
    def requires_identity(self) -> bool:
        """Neighbours must prove their names: this node has an identity and operator keys."""
        return self.trust.required

    def on_envelope(self, conn: Connection, env: m.Envelope, size: int) -> None:
        unproved = self.requires_identity and conn.client is None and not conn.verified
        relayed = env.dst != self._node_id and conn.client is None and conn.peer is not None
        if self.requires_identity and env.src == self._node_id and conn.client is None:
            # this node's name on a frame a neighbour handed over: the next node would take
            # it as this node's own word, proven by our link (a captured neighbour's forgery)
            self.counters.frames_origin_refused += 1
            return
        if relayed and not unproved:
            assert conn.peer is not None
            self._forward(conn.peer, env, size)
            return
        try:
            msg = m.decode(env.body)
        except (msgspec.DecodeError, msgspec.ValidationError):
            self.counters.frames_malformed += 1
            return
        if unproved and not isinstance(msg, m.PeerHello | m.ClientHello):
            self.counters.frames_malformed += 1  # a neighbour must prove its name first
            return
        if isinstance(msg, m.PeerHello):
            self._peer_hello(conn, msg)
            return
        if isinstance(msg, m.ClientHello):
            if not self._introduced(conn, None):
                return
            self._client_ids += 1
            conn.client = self._client_ids
            self.clients[conn.client] = conn
            if self.requires_identity:
                who = self.trust.client(
                    msg, conn.codec.peer_hello, conn.codec.hello(), conn.address
                )
                conn.client_as = who
                conn.key_id = "" if isinstance(who, str) else who.key_id
            return
        if conn.client is not None:
            verdict = self.trust.command(conn.client_as, conn.codec.nonce, msg)
            if isinstance(verdict, str):  # counted, told to the client; logged at INFO, so a
                log.info("client %s: %s", conn.address or "?", verdict)  # flood fills no disk
                conn.send_message("client", m.Refused(verdict))
                return
            msg = verdict
            if isinstance(msg, m.RevokeNode):
                why = self._revoke(msg, None)
                conn.send_message("client", m.Refused(why) if why else m.RevokeNode(msg.node_key))
                return
            self._on_client(conn.client, msg)
            return
        if conn.peer is None:
            self.counters.frames_malformed += 1  # a peer must say hello first
            return
        if env.kind != m.kind_of(msg):  # it would have been queued as another class
            self.counters.frames_bad_kind += 1
            return
        # a control stream's frame is judged by what it carries (its number is the core's)
        frame = msg if type(msg) is m.Sequenced else None
        if frame is not None:
            msg = frame.body
        if why := implausible(msg, time.time_ns() // 1_000_000):
            self.counters.frames_implausible += 1
            log.info("from %s: %s: %s", env.src, type(msg).__name__, why)
            return
        if self.requires_identity:
            said = self.trust.origin(conn.peer, env, msg, self.loop.time())
            if said is None:
                return
            msg = said
            if isinstance(msg, m.Hears):  # a member's "I hear it": the suspect's own word
                msg = self.trust.hears(conn.peer, env, msg, self.loop.time())
        elif isinstance(msg, m.Hears) and msg.proof:
            msg = msgspec.structs.replace(msg, proof=b"")  # nothing here checks it
        if isinstance(msg, m.RevokeNode):
            self._revoke(msg, conn.peer)
            return
        if isinstance(msg, DOCUMENT_MESSAGES) and self.authority.operators:
            why = self.authority.document(msg.document, msg.app)
            if why:  # an app no operator granted (or one undeployed since): never loaded here
                log.info("from %s: %s %s: %s", env.src, type(msg).__name__, msg.app, why)
                if frame is not None:  # a genuine node's word, refused: its stream goes on
                    self._receiver(env.src, msgspec.structs.replace(frame, body=m.Refused(why)))
                return
        self._receiver(env.src, msg if frame is None else msgspec.structs.replace(frame, body=msg))

    def _revoke(self, msg: m.RevokeNode, via: str | None) -> str:
        """An operator's revocation (from a client, or a neighbour ``via``): once verified and
        new, links proven with that key are closed and it goes on to every other proven
        neighbour (:mod:`mso.protocol.revocation`). '' or why it was refused."""
        why = self.trust.revoke(msg, via)
        if why is None:
            for node, conn in list(self.peers.items()):
                if conn.key_id == msg.node_key:
                    self.connection_counters.identity_refused += 1
                    conn.abort()
                elif node != via and conn.verified:
                    conn.send_message(node, msg)
            for conn in list(self.clients.values()):
                if conn.key_id == msg.node_key:  # a client key is revoked the same way
                    self.connection_counters.client_refused += 1
                    conn.abort()
        return why or ""

    def _tell_revocations(self, conn: Connection, node: str) -> None:
        """A newly proven neighbour hears the revocations this node holds: it may have been
        away when they were announced."""
        for revoke in self.trust.revocations.latest(TELL_REVOCATIONS):
            conn.send_message(node, revoke)

    def _peer_hello(self, conn: Connection, msg: m.PeerHello) -> None:
        """A neighbour says who it is (with its proof, when identities are required): take
        the link, and answer with this node's own proof on a connection it accepted."""
        if self.requires_identity:
            called = conn.peer if conn.outbound else None
            key_id = self.trust.hello(
                msg, conn.codec.peer_hello, conn.codec.hello(), called, conn.address
            )
            if key_id is None:
                conn.abort()
                return
            conn.verified, conn.key_id = True, key_id
            if conn.outbound:  # the called node proved it is the one this node called
                self._tell_revocations(conn, msg.node)
                self._attach_link(msg.node)
                return
        if not self._introduced(conn, msg.node):
            return
        conn.peer = msg.node
        self.peers[msg.node] = conn
        if self.requires_identity and not conn.said_hello:
            conn.say_hello()  # before anything the link sends: the peer drops frames till then
            self._tell_revocations(conn, msg.node)
        self._attach_link(msg.node)

    def on_connection_lost(self, conn: Connection) -> None:
        self.accepted.discard(conn)
        self.admission.gone(conn)
        self._held_total -= self._held.pop(conn, 0)
        if conn.peer is not None and self.peers.get(conn.peer) is conn:
            del self.peers[conn.peer]  # (its relay budget stays: a reconnection refills
            # nothing, or a member reconnecting every moment would relay a burst each time)
            self._unconnected.setdefault(conn.peer, self.loop.time())
            if conn.link is not None:
                conn.link.close()
            spec = self.view.neighbours().get(conn.peer)
            if spec is not None and self._node_id < conn.peer and not self._closed:
                self.loop.create_task(self._connect(conn.peer, spec.host, spec.port))
        if conn.client is not None:
            self.clients.pop(conn.client, None)

    # -- neighbours -------------------------------------------------------------------------
    def _routes_changed(self, _: RoutesChanged) -> None:
        self.routes_changed()

    def routes_changed(self) -> None:
        """Follow the view: drop links to former neighbours, reshape or connect current ones
        (the lower node id connects), then offer waiting frames the new routes."""
        neighbours = self.view.neighbours()
        for node in list(self.peers):
            if node not in neighbours:
                self.peers.pop(node).close()
        for node in list(self._unconnected):
            if node not in neighbours:
                del self._unconnected[node]
        for node, spec in neighbours.items():
            if node in self.peers:
                self._attach_link(node)
            elif self._node_id < node:
                self.loop.create_task(self._connect(node, spec.host, spec.port))
        self.waiting.release(self.loop.time(), self._release)

    async def _connect(self, node: str, host: str, port: int) -> None:
        for attempt in range(CONNECT_ATTEMPTS):
            if node not in self.view.neighbours() or node in self.peers or self._closed:
                return
            try:
                _, conn = await asyncio.wait_for(
                    self.loop.create_connection(lambda: Connection(self, peer=node), host, port),
                    CONNECT_TIMEOUT_S,
                )
            except (OSError, TimeoutError) as exc:
                log.info("connecting to %s at %s:%s: %s", node, host, port, exc)
                await asyncio.sleep(0.05 * (attempt + 1))  # back off (not a synchronisation)
                continue
            self.peers[node] = conn
            self._attach_link(node)
            return
        log.warning("could not reach neighbour %s at %s:%s", node, host, port)

    def _attach_link(self, node: str) -> None:
        """Give a connected neighbour a link of the current shape and send what it held; with
        identities required, only once it has proved its name (its frames wait till then)."""
        conn = self.peers.get(node)
        spec = self.view.neighbours().get(node)
        if conn is None or spec is None or (self.requires_identity and not conn.verified):
            return
        self._unconnected.pop(node, None)
        held = self.held.pop(node, None)
        self._held_bytes.pop(node, None)
        if conn.link is None or conn.link.shape != spec.shape:
            seed = zlib.crc32(f"{self._node_id}-{node}".encode())
            conn.link = Link(
                conn, spec.shape, seed, self.loop, self._lost, self.limits.queues, self._full
            )
        for payload, kind, _ in held or ():
            conn.link.send(payload, kind)

    def _lost(self) -> None:
        self.counters.frames_dropped_loss += 1

    def _full(self) -> None:
        self.counters.frames_dropped_queue += 1
