"""The asyncio driver of ``mso node``: sockets, timers and link shaping around a NodeCore.

It only does I/O. Frames arrive on TCP connections (neighbours, clients, the emulator
controller), are authenticated by :class:`~mso.protocol.framing.FrameCodec`, decoded and either
forwarded toward their destination (multi-hop, hop by hop) or handed to the core with
``loop.time()``; the core's effects become frames, timers and replies. Nodes talk only to their
current neighbours; each neighbour link applies its bandwidth, delay and loss in the sender, and
control frames overtake queued data frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import zlib
from collections import deque
from typing import Any

import msgspec

from mso.node.core import Effect, NodeCore, Reply, Send, SetTimer
from mso.protocol import messages as m
from mso.protocol.framing import FrameCodec, FramingError

log = logging.getLogger("mso.node")

HIGH_WATER = 1 << 20
MAX_HELD = 10_000  # frames kept per neighbour while its connection is being set up
# A control or marker frame whose next hop is gone waits this long for the routes to change
# instead of being dropped: after a failure the nodes on a path learn the new routes a moment
# apart, and a probe sent by the first to learn would otherwise die at the next, still stale,
# hop and wait for a 1 s step retry. Data frames are not kept: acks and replay cover them.
ROUTE_WAIT_S = 1.0
MAX_AWAITING = 1_000
# The event loop's timers have millisecond resolution (epoll), so a frame due within this slack
# leaves now instead of waiting a whole tick: bandwidth holds on average, with bursts of up to a
# millisecond's worth, and delays under a millisecond are not emulated (loopback adds ~50 µs).
TIMER_SLACK_S = 1e-3


class Counters:
    """Byte and frame counters the monitor and ``mso status`` report."""

    def __init__(self) -> None:
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_forwarded = 0
        self.frames_rejected = 0
        self.frames_malformed = 0
        self.frames_dropped_loss = 0
        self.frames_unroutable = 0

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))


class Link:
    """The sending side of one neighbour link: shaping, loss, control before data."""

    def __init__(
        self, conn: Connection, shape: tuple[float | None, float, float], seed: int
    ) -> None:
        self.conn = conn
        self.bandwidth_mbps, self.delay_ms, self.loss = shape
        self._rng = random.Random(seed)
        self._control: deque[bytes] = deque()
        self._data: deque[bytes] = deque()
        self._next_free = 0.0
        self._in_air: deque[tuple[float, bytes]] = deque()
        self._timer: asyncio.TimerHandle | None = None

    @property
    def shaped(self) -> bool:
        return self.bandwidth_mbps is not None or self.delay_ms > 0

    def send(self, payload: bytes, kind: int) -> None:
        if kind == m.DATA and self.loss and self._rng.random() < self.loss:
            self.conn.driver.counters.frames_dropped_loss += 1
            return
        (self._control if kind == m.CONTROL else self._data).append(payload)
        self.pump()

    def pump(self) -> None:
        conn = self.conn
        loop = conn.driver.loop
        now = loop.time()
        while (self._control or self._data) and not conn.paused:
            if self.bandwidth_mbps is not None and self._next_free > now + TIMER_SLACK_S:
                self._arm(self._next_free - TIMER_SLACK_S)
                break
            payload = (self._control or self._data).popleft()
            if not self.shaped:
                conn.write_frame(payload)
                continue
            if self.bandwidth_mbps is not None:
                start = max(now, self._next_free)
                self._next_free = start + len(payload) * 8 / (self.bandwidth_mbps * 1e6)
                arrive = self._next_free + self.delay_ms / 1e3
            else:
                arrive = now + self.delay_ms / 1e3
            self._in_air.append((arrive, payload))
        self._deliver_due()

    def _deliver_due(self) -> None:
        loop = self.conn.driver.loop
        now = loop.time()
        while self._in_air and self._in_air[0][0] <= now + TIMER_SLACK_S:
            self.conn.write_frame(self._in_air.popleft()[1])
        if self._in_air:
            self._arm(self._in_air[0][0] - TIMER_SLACK_S)

    def _arm(self, at: float) -> None:
        if self._timer is not None and self._timer.when() <= at:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self.conn.driver.loop.call_at(at, self._fire)

    def _fire(self) -> None:
        self._timer = None
        self.pump()

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()


class Connection(asyncio.Protocol):
    """One TCP connection: framing, authentication, and who is on the other end."""

    def __init__(self, driver: NodeDriver, peer: str | None = None) -> None:
        self.driver = driver
        self.codec = FrameCodec(driver.psk)
        self.transport: asyncio.Transport | None = None
        self.peer = peer  # neighbour node id once known
        self.client: int | None = None
        self.paused = False
        self.link: Link | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        transport.set_write_buffer_limits(high=HIGH_WATER)
        transport.write(self.codec.hello())
        if self.peer is not None:
            self.send_message(self.peer, m.PeerHello(self.driver.core.id), control=True)

    def send_message(self, dst: str, msg: m.Message, control: bool = False) -> None:
        self.write_frame(m.wrap(self.driver.core.id, dst, msg))

    def write_frame(self, payload: bytes) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        frame = self.codec.seal(payload)
        self.driver.counters.bytes_out += len(frame)
        if frame:
            self.transport.write(frame)

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        if self.link is not None:
            self.link.pump()

    def data_received(self, data: bytes) -> None:
        driver = self.driver
        driver.counters.bytes_in += len(data)
        rejected = self.codec.rejected
        try:
            payloads, flush = self.codec.feed(data)
        except FramingError as exc:
            driver.counters.frames_rejected += 1
            log.warning("closing connection: %s", exc)
            assert self.transport is not None
            self.transport.close()
            return
        driver.counters.frames_rejected += self.codec.rejected - rejected
        if flush and self.transport is not None:
            self.transport.write(flush)
        for payload in payloads:
            try:
                env = m.unwrap(payload)
            except (msgspec.DecodeError, msgspec.ValidationError):
                driver.counters.frames_malformed += 1
                continue
            driver.on_envelope(self, env, len(payload))

    def connection_lost(self, exc: Exception | None) -> None:
        self.driver.on_connection_lost(self)


class NodeDriver:
    """Runs one NodeCore on an asyncio loop."""

    def __init__(self, core: NodeCore, host: str, port: int, psk: bytes) -> None:
        self.core = core
        self.host = host
        self.port = port
        self.psk = psk
        self.loop = asyncio.get_running_loop()
        self.counters = Counters()
        self.peers: dict[str, Connection] = {}
        self.clients: dict[int, Connection] = {}
        self.neighbours: dict[str, list[Any]] = {}
        self._client_ids = 0
        self._timers: dict[tuple[Any, ...], asyncio.TimerHandle] = {}
        self._server: asyncio.Server | None = None
        self.stopped = asyncio.Event()
        self._link_version = -1
        self._held: dict[str, deque[tuple[bytes, int]]] = {}
        # frames waiting for a route: (deadline, destination, payload, kind, forwarded size)
        self._awaiting: deque[tuple[float, str, bytes, int, int]] = deque()
        core.status_hook = self._link_status
        core.traffic = lambda: (self.counters.bytes_out, self.counters.bytes_in)
        core.clock = self.loop.time

    def _link_status(self) -> dict[str, Any]:
        return {"traffic": self.counters.as_dict(), "connected": sorted(self.peers)}

    async def start(self) -> None:
        self._server = await self.loop.create_server(
            lambda: Connection(self), self.host, self.port, reuse_address=True
        )
        self._apply(self.core.start(self.loop.time()))

    async def stop(self) -> None:
        for t in self._timers.values():
            t.cancel()
        for conn in [*self.peers.values(), *self.clients.values()]:
            if conn.link is not None:
                conn.link.close()
            if conn.transport is not None:
                conn.transport.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
        self.stopped.set()

    # -- inbound ----------------------------------------------------------------------------
    def on_envelope(self, conn: Connection, env: m.Envelope, size: int) -> None:
        core = self.core
        if env.dst != core.id and conn.client is None and conn.peer is not None:
            self._forward(env, size)
            return
        try:
            msg = m.decode(env.body)
        except (msgspec.DecodeError, msgspec.ValidationError):
            self.counters.frames_malformed += 1
            return
        if isinstance(msg, m.PeerHello):
            conn.peer = msg.node
            self.peers[msg.node] = conn
            self._attach_link(msg.node)
            return
        if isinstance(msg, m.ClientHello):
            self._client_ids += 1
            conn.client = self._client_ids
            self.clients[conn.client] = conn
            return
        now = self.loop.time()
        if conn.client is not None:
            if isinstance(msg, m.LinkState):
                self.apply_links(msg)
            elif isinstance(msg, m.Shutdown):
                self.loop.create_task(self.stop())
            else:
                self._apply(core.request(conn.client, msg, now))
            return
        if conn.peer is None:
            self.counters.frames_malformed += 1  # a peer must say hello first
            return
        self._apply(core.receive(env.src, msg, now))

    def _forward(self, env: m.Envelope, size: int) -> None:
        env.ttl -= 1
        if env.ttl <= 0:
            self.counters.frames_unroutable += 1
            return
        payload = m.rewrap(env)
        if self._send_toward(env.dst, payload, env.kind):
            self.counters.bytes_forwarded += size
        else:
            self._await_route(env.dst, payload, env.kind, size)

    def _send_toward(self, dst: str, payload: bytes, kind: int) -> bool:
        """Hand a frame to the next hop toward dst; False when there is no usable next hop."""
        route = self.core.routes.get(dst)
        if route is None:
            return False
        conn = self.peers.get(route[0])
        if conn is not None and conn.link is not None:
            conn.link.send(payload, kind)
        elif route[0] in self.neighbours:
            self._hold(route[0], payload, kind)
        else:
            return False
        return True

    def _await_route(self, dst: str, payload: bytes, kind: int, forwarded: int = 0) -> None:
        """Keep a control frame with no next hop until the routes change (bounded in time)."""
        now = self.loop.time()
        while self._awaiting and self._awaiting[0][0] < now:
            self._awaiting.popleft()
            self.counters.frames_unroutable += 1
        if kind == m.DATA or len(self._awaiting) >= MAX_AWAITING:
            self.counters.frames_unroutable += 1
            return
        self._awaiting.append((now + ROUTE_WAIT_S, dst, payload, kind, forwarded))

    def _retry_awaiting(self) -> None:
        now = self.loop.time()
        waiting, self._awaiting = self._awaiting, deque()
        for deadline, dst, payload, kind, forwarded in waiting:
            if deadline < now:
                self.counters.frames_unroutable += 1
            elif self._send_toward(dst, payload, kind):
                self.counters.bytes_forwarded += forwarded
            else:
                self._awaiting.append((deadline, dst, payload, kind, forwarded))

    # -- outbound ---------------------------------------------------------------------------
    def _apply(self, effects: list[Effect]) -> None:
        for eff in effects:
            if isinstance(eff, Send):
                try:
                    payload = m.wrap(self.core.id, eff.dst, eff.msg)
                except (OverflowError, TypeError, ValueError) as exc:  # a bug, not a crash
                    log.error("cannot encode %s for %s: %s", type(eff.msg).__name__, eff.dst, exc)
                    self.counters.frames_unroutable += 1
                    continue
                kind = m.kind_of(eff.msg)
                if not self._send_toward(eff.dst, payload, kind):
                    self._await_route(eff.dst, payload, kind)
            elif isinstance(eff, SetTimer):
                old = self._timers.pop(eff.key, None)
                if old is not None:
                    old.cancel()
                self._timers[eff.key] = self.loop.call_at(eff.at, self._fire, eff.key)
            elif isinstance(eff, Reply):
                client = self.clients.get(eff.client)
                if client is not None:
                    client.send_message("client", eff.msg)

    def _fire(self, key: tuple[Any, ...]) -> None:
        self._timers.pop(key, None)
        self._apply(self.core.on_timer(key, self.loop.time()))

    # -- links ------------------------------------------------------------------------------
    def apply_links(self, state: m.LinkState) -> None:
        """Take the emulator's (or routing daemon's) view: neighbours, shapes and routes."""
        if state.version <= self._link_version:
            return
        self._link_version = state.version
        self.neighbours = dict(state.neighbours)
        routes = {d: (str(r[0]), int(r[1])) for d, r in state.routes.items()}
        effects = self.core.set_routes(routes, self.loop.time())
        for node in list(self.peers):
            if node not in self.neighbours:
                conn = self.peers.pop(node)
                if conn.link is not None:
                    conn.link.close()
                if conn.transport is not None:
                    conn.transport.close()
        for node, spec in self.neighbours.items():
            if node in self.peers:
                self._attach_link(node)
            elif self.core.id < node:
                self.loop.create_task(self._connect(node, str(spec[0]), int(spec[1])))
        self._retry_awaiting()
        self._apply(effects)

    async def _connect(self, node: str, host: str, port: int) -> None:
        for attempt in range(20):
            if node not in self.neighbours or node in self.peers:
                return
            try:
                _, conn = await self.loop.create_connection(
                    lambda: Connection(self, peer=node), host, port
                )
            except OSError as exc:
                log.info("connecting to %s at %s:%s: %s", node, host, port, exc)
                await asyncio.sleep(0.05 * (attempt + 1))
                continue
            self.peers[node] = conn
            self._attach_link(node)
            return
        log.warning("could not reach neighbour %s at %s:%s", node, host, port)

    def _hold(self, node: str, payload: bytes, kind: int) -> None:
        """Keep frames for a neighbour whose connection is still being set up (bounded)."""
        held = self._held.setdefault(node, deque())
        if len(held) >= MAX_HELD:
            self.counters.frames_unroutable += 1
            return
        held.append((payload, kind))

    def _attach_link(self, node: str) -> None:
        conn = self.peers.get(node)
        spec = self.neighbours.get(node)
        if conn is None or spec is None:
            return
        held = self._held.pop(node, None)
        shape = (spec[2], float(spec[3]), float(spec[4]))
        if (
            conn.link is None
            or (conn.link.bandwidth_mbps, conn.link.delay_ms, conn.link.loss) != shape
        ):
            seed = zlib.crc32(f"{self.core.id}-{node}".encode())
            conn.link = Link(conn, shape, seed)
        for payload, kind in held or ():
            conn.link.send(payload, kind)

    def on_connection_lost(self, conn: Connection) -> None:
        if conn.peer is not None and self.peers.get(conn.peer) is conn:
            del self.peers[conn.peer]
            if conn.link is not None:
                conn.link.close()
            spec = self.neighbours.get(conn.peer)
            if spec is not None and self.core.id < conn.peer:
                self.loop.create_task(self._connect(conn.peer, str(spec[0]), int(spec[1])))
        if conn.client is not None:
            self.clients.pop(conn.client, None)


async def run_node(core: NodeCore, host: str, port: int, psk: bytes) -> None:
    """Serve until a Shutdown request or cancellation."""
    driver = NodeDriver(core, host, port, psk)
    await driver.start()
    log.info("node %s listening on %s:%s", core.id, host, port)
    try:
        await driver.stopped.wait()
    finally:
        if not driver.stopped.is_set():
            await driver.stop()
