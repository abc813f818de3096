"""The kernel's routing view: what a device's routing daemon (babeld, OLSR, batman-adv's
layer-3 mode, static routes) installed, read over netlink, with node ids learned from the nodes.

On a real MANET, and on the netns testbed, a routing daemon keeps the kernel's routing table and
the kernel forwards multi-hop traffic; the node reads the table rather than being told. Three
parts, of which only the first touches netlink (pyroute2 stays out of every other path):

- **the tables**: a dump of the policy rules and every IPv4 table at start and again
  (debounced) after every route or rule event, looked up as the kernel does
  (:mod:`mso.net.routes_policy`): batmand's table 66 behind its rules counts like babeld's
  main-table routes. Connected-subnet routes (``proto kernel``) are left out: on a shared ad
  hoc subnet they claim every node is one hop away, which only the daemon knows.
- **membership**: every node announces itself in a small authenticated UDP datagram on its
  node port, every :data:`ANNOUNCE_S` and at once when a new destination appears, to every
  address the kernel has a route to and every member it knows of. The datagram carries its id
  and port, its hop counts to the nodes its kernel reaches, and its address book (id ->
  address): a receiver learns the sender's address from the datagram's source and the others'
  from the book, so membership spreads with the announcements, with no static list -- and a
  node learns of nodes it has no route to, so a reactive daemon gets the first packet that
  makes it find the route.
- **resolution** (:func:`resolve`, pure): a member is reachable when the kernel has a route to
  its address; the route's gateway, named through the book, is the next hop; hops are 1 to a
  neighbour and 1 + the next hop's announced count otherwise (the kernel table has none).
- **the overlay relay** (:func:`relays`): a member the kernel has no route to (a daemon that
  starves a route, an asymmetric route, a reactive daemon still looking) but that a reachable
  node announces, is routed through that node: frames go there and it forwards them, until the
  kernel route returns and they go direct again.

The transport then opens its TCP connection straight to any reachable node (``neighbours``
lists them all, ``next_hop(dst)`` is ``dst``, or the relay): the kernel carries it over the
hops. ``routes`` keeps the daemon's real next hop and hop count, so probes walk the real path
and the core sees the neighbours the radio has.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hashlib
import hmac
import ipaddress
import logging
import socket
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import msgspec

from mso.net.base import Neighbour, Route
from mso.net.netns import socket_in_netns
from mso.net.routes import TableRoutes
from mso.net.routes_policy import (
    DEFAULT_RULES,
    LOCAL_TABLE,
    RTN_UNICAST,
    KernelRoute,
    Policy,
    Rule,
    longest_match,
    route_from_netlink,
    rule_from_netlink,
)

__all__ = ["Announce", "KernelRoute", "KernelRoutes", "Policy", "resolve"]

log = logging.getLogger("mso.node")

ANNOUNCE_S = 1.0
"""How often a node announces itself to every address it has a route to."""
DEBOUNCE_S = 0.02
"""A burst of netlink route events (a daemon installs many routes at once) is one re-read."""
STALE_ANNOUNCES = 3.5
"""A node's announced hops are forgotten after this many announcement periods without one."""
RETRY_S = 0.5
"""A dump that failed is tried again this much later."""
RESYNC_S = 5.0
"""The tables are re-read at least this often whatever the events say: a burst of route events
that overflowed the netlink socket's buffer (ENOBUFS: the events are gone) or a dump that failed
leaves the view stale this long at most, not until the next route change."""
MAX_DATAGRAM = 60_000
TAG_BYTES = 16
MAX_HOPS = 64
RTMGRP_IPV4_ROUTE = 0x40
RTMGRP_IPV4_RULE = 0x80
AF = socket.AF_INET


class Announce(msgspec.Struct, array_like=True, forbid_unknown_fields=True):
    """A node's self-announcement (UDP, authenticated with the overlay key)."""

    node: str
    port: int
    hops: dict[str, int]
    book: dict[str, tuple[str, int]]


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Announce)


def _tag(psk: bytes, body: bytes) -> bytes:
    return hmac.new(psk, b"mso-announce" + body, hashlib.sha256).digest()[:TAG_BYTES]


def seal_announce(psk: bytes, msg: Announce) -> bytes:
    body = _encoder.encode(msg)
    return _tag(psk, body) + body


def open_announce(psk: bytes, datagram: bytes) -> Announce | None:
    """The announcement in ``datagram``, or None if it is not ours, forged or malformed."""
    if len(datagram) <= TAG_BYTES or len(datagram) > MAX_DATAGRAM:
        return None
    tag, body = datagram[:TAG_BYTES], datagram[TAG_BYTES:]
    if not hmac.compare_digest(tag, _tag(psk, body)):
        return None
    try:
        msg = _decoder.decode(body)
        for ip, _port in msg.book.values():
            ipaddress.IPv4Address(ip)
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
        return None
    if not (0 < msg.port < 65536 and msg.node):
        return None
    return msg


def lookup(table: Iterable[KernelRoute], ip: str) -> KernelRoute | None:
    """The longest-prefix match for ``ip`` in one table (first of equals)."""
    return longest_match(table, ipaddress.IPv4Address(ip))


def resolve(
    node_id: str,
    table: Policy | Iterable[KernelRoute],
    book: Mapping[str, tuple[str, int]],
    announced_hops: Mapping[str, Mapping[str, int]],
) -> tuple[dict[str, Route], dict[str, Neighbour]]:
    """Routes and reachable nodes by id from the kernel's tables and the address book.

    ``table`` is the kernel's :class:`~mso.net.routes_policy.Policy` (rules and tables) or
    one table's routes (looked up as the main table under the default rules). A member the
    kernel has no route to is still routed when a reachable node announces a kernel route to
    it: through that node, at the overlay level (:func:`relays`); it is not in the
    reachable set, since no connection goes straight to it.
    """
    policy = table if isinstance(table, Policy) else Policy(table)
    by_ip = {ip: n for n, (ip, _) in book.items()}
    routes: dict[str, Route] = {}
    reach: dict[str, Neighbour] = {}
    for node, (ip, port) in sorted(book.items()):
        if node == node_id:
            continue
        r = policy.lookup(ip)
        if r is None:
            continue
        hop = by_ip.get(r.gateway or ip)
        if hop is None or hop == node_id:
            continue  # the gateway has not announced itself yet
        via = announced_hops.get(hop, {}).get(node, 1)
        hops = 1 if hop == node else min(1 + via, MAX_HOPS)
        routes[node] = (hop, hops)
        reach[node] = Neighbour(ip, port)
    routes.update(relays(node_id, routes, book, announced_hops))
    return routes, reach


def relays(
    node_id: str,
    direct: Mapping[str, Route],
    book: Mapping[str, tuple[str, int]],
    announced_hops: Mapping[str, Mapping[str, int]],
) -> dict[str, Route]:
    """Overlay routes to the members the kernel has no route to: through the reachable node
    that announces the fewest hops to it (ties: the smaller id), ``(relay, hops)``.

    Announcements carry kernel routes only, so a relay always hands the frame to its kernel:
    one overlay hop, never a loop between two nodes that each think the other reaches it.
    """
    out: dict[str, Route] = {}
    for node in sorted(book):
        if node == node_id or node in direct:
            continue
        best: tuple[int, str] | None = None
        for relay, (_, hops) in direct.items():
            via = announced_hops.get(relay, {}).get(node)
            if via is not None and relay != node:
                cand = (min(hops + via, MAX_HOPS), relay)
                best = cand if best is None or cand < best else best
        if best is not None:
            out[node] = (best[1], best[0])
    return out


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, view: KernelRoutes) -> None:
        self.view = view

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.view.on_announce(data, str(addr[0]))


class KernelRoutes(TableRoutes):
    """A :class:`~mso.net.base.RoutingView` read from the kernel (see the module doc).

    ``start()`` before the driver uses it and ``close()`` after; ``netns`` names a network
    namespace to read and announce in (tests; a node started inside one leaves it None).
    """

    def __init__(
        self,
        node_id: str,
        port: int,
        psk: bytes,
        *,
        netns: str | None = None,
        announce_s: float = ANNOUNCE_S,
        host: str = "0.0.0.0",
    ) -> None:
        super().__init__(node_id)
        self.port = port
        self.psk = psk
        self.netns = netns
        self.announce_s = announce_s
        self.host = host
        self.table: list[KernelRoute] = []  # every table's routes
        self.rules: list[Rule] = list(DEFAULT_RULES)
        self.book: dict[str, tuple[str, int]] = {}
        self._direct: set[str] = set()  # book entries learned from the node itself
        self.announced_hops: dict[str, dict[str, int]] = {}
        self.announced_at: dict[str, float] = {}  # node -> when its last announcement came
        self.rejected = 0
        self._udp: asyncio.DatagramTransport | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._ipr: Any = None
        self._events: Any = None
        self._reread: asyncio.TimerHandle | None = None
        self._reading: asyncio.Future[None] | None = None  # the dump under way
        self._stale = False  # an event came during that dump: read again after it
        self.events_lost = 0  # times the netlink socket overflowed (ENOBUFS)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._announce_soon = False

    def next_hop(self, dst: str) -> str | None:
        """The kernel forwards: a reachable node is reached directly; one the kernel has no
        route to goes through the node that relays for it (:func:`relays`)."""
        if dst in self._neighbours:
            return dst
        route = self._routes.get(dst)
        return None if route is None else route[0]

    def detour(self, dst: str) -> str | None:
        """The node that would relay for ``dst`` if the kernel had no route to it: for a
        neighbour whose connection cannot be made (its kernel routes to this node, this one's
        replies have no way back)."""
        book = self.book.get(dst)
        if book is None:
            return None
        direct = {n: r for n, r in self._routes.items() if n in self._neighbours and n != dst}
        route = relays(self.node_id, direct, {dst: book}, self.announced_hops).get(dst)
        return None if route is None else route[0]

    async def start(self) -> None:
        from pyroute2 import AsyncIPRoute  # netlink only here

        self._loop = asyncio.get_running_loop()
        self._ipr = AsyncIPRoute(netns=self.netns)
        self._events = AsyncIPRoute(netns=self.netns)
        await self._events.bind(groups=RTMGRP_IPV4_ROUTE | RTMGRP_IPV4_RULE)
        sock = socket_in_netns(self.netns, socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.host, self.port))
        sock.setblocking(False)
        transport, _ = await self._loop.create_datagram_endpoint(
            lambda: _Datagrams(self), sock=sock
        )
        self._udp = transport
        await self.reread()
        self._tasks = [
            asyncio.create_task(self._follow(), name=f"kernel-routes-{self.node_id}"),
            asyncio.create_task(self._announce_loop(), name=f"announce-{self.node_id}"),
            asyncio.create_task(self._resync_loop(), name=f"kernel-resync-{self.node_id}"),
        ]

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        if self._reread is not None:
            self._reread.cancel()
        if self._reading is not None:
            self._reading.cancel()
        if self._udp is not None:
            self._udp.close()
        for ipr in (self._ipr, self._events):
            if ipr is not None:
                with contextlib.suppress(Exception):
                    ipr.close()

    # -- the kernel's table ---------------------------------------------------------------
    async def reread(self) -> None:
        """Dump the rules and every table, and recompute."""
        rules = [rule_from_netlink(r) async for r in await self._ipr.rule("dump", family=AF)]
        table: list[KernelRoute] = []
        async for msg in await self._ipr.route("dump", family=AF):
            r = route_from_netlink(msg)
            if r is not None:
                table.append(r)
        new_dsts = {r.dst for r in table} - {r.dst for r in self.table}
        self.table, self.rules = table, rules or list(DEFAULT_RULES)
        self._recompute()
        if new_dsts and self._udp is not None:
            self.announce()  # a new destination hears of us at once

    async def _follow(self) -> None:
        """Re-read after every route or rule event. A burst the socket's buffer could not hold
        (a loaded machine, a daemon re-routing many destinations) makes ``get`` raise ENOBUFS:
        events were lost, so the tables are read anew and the events followed on."""
        while True:
            try:
                got = False
                async for _msg in self._events.get():
                    got = True
                    self._schedule_reread()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # pyroute2's NetlinkError carries the errno as ``code``
                self._schedule_reread()
                if getattr(exc, "code", None) != errno.ENOBUFS:
                    log.warning("route events stopped (%s): re-reading every %g s", exc, RESYNC_S)
                    return
                self.events_lost += 1
                log.info("route events lost (ENOBUFS): the tables are read anew")
                continue
            if not got:  # the socket closed under us: nothing more will come
                return

    async def _resync_loop(self) -> None:
        while True:
            await asyncio.sleep(RESYNC_S)  # a period, not a synchronisation
            self._schedule_reread()

    def _schedule_reread(self, delay: float = DEBOUNCE_S) -> None:
        if self._reread is None and self._loop is not None:
            self._reread = self._loop.call_later(delay, self._do_reread)

    def _do_reread(self) -> None:
        """One dump at a time: two under way could end in either order, and a dump begun
        before a route was withdrawn that ended last would put the route back for good."""
        self._reread = None
        if self._reading is not None:
            self._stale = True
            return
        self._reading = asyncio.ensure_future(self.reread())
        self._reading.add_done_callback(self._read_done)

    def _read_done(self, task: asyncio.Future[None]) -> None:
        self._reading = None
        if task.cancelled():
            return
        failed = task.exception() is not None
        _log_failure(task)
        if self._stale or failed:  # events came meanwhile, or the dump failed: read again
            self._stale = False
            self._schedule_reread(RETRY_S if failed else DEBOUNCE_S)

    # -- membership -----------------------------------------------------------------------
    def targets(self) -> set[str]:
        """Where announcements go: every host route's address and every known member's."""
        out = {
            str(r.dst.network_address)
            for r in self.table
            if r.dst.prefixlen == 32 and r.type == RTN_UNICAST and r.table != LOCAL_TABLE
        }
        out |= {ip for n, (ip, _) in self.book.items() if n != self.node_id}
        return out

    def announce(self) -> None:
        if self._udp is None:
            return
        msg = Announce(
            self.node_id,
            self.port,
            # kernel routes only: what others may relay through this node (see relays)
            {d: h for d, (_, h) in self._routes.items() if d in self._neighbours},
            dict(self.book),
        )
        datagram = seal_announce(self.psk, msg)
        for ip in sorted(self.targets()):
            port = next((p for n, (a, p) in self.book.items() if a == ip), self.port)
            with contextlib.suppress(OSError):  # unreachable now: the next round retries
                self._udp.sendto(datagram, (ip, port))

    async def _announce_loop(self) -> None:
        while True:
            self.announce()
            self.expire_announcements(asyncio.get_running_loop().time())
            await asyncio.sleep(self.announce_s)  # a period, not a synchronisation

    def expire_announcements(self, now: float) -> None:
        """Forget the hops a node announced once its announcements stop coming (a node that
        died, or whose datagrams no longer reach us): what it last said it reaches would
        otherwise keep an overlay relay through it to a node nobody reaches any more (a dead
        relay's neighbour kept a route to it through another for 45 s)."""
        stale = [
            n for n, at in self.announced_at.items() if now - at > STALE_ANNOUNCES * self.announce_s
        ]
        for n in stale:
            del self.announced_at[n]
            self.announced_hops.pop(n, None)
        if stale:
            self._recompute()

    def on_announce(self, datagram: bytes, src_ip: str) -> None:
        msg = open_announce(self.psk, datagram)
        if msg is None:
            self.rejected += 1
            return
        if msg.node == self.node_id:
            return
        changed = self.book.get(msg.node) != (src_ip, msg.port)
        self.book[msg.node] = (src_ip, msg.port)
        self._direct.add(msg.node)
        for node, (ip, port) in msg.book.items():
            if node != self.node_id and node not in self._direct and node not in self.book:
                self.book[node] = (ip, port)
                changed = True
        hops = {d: h for d, h in msg.hops.items() if isinstance(h, int) and 0 < h <= MAX_HOPS}
        if self._loop is not None:
            self.announced_at[msg.node] = self._loop.time()
        if self.announced_hops.get(msg.node) != hops:
            self.announced_hops[msg.node] = hops
            changed = True
        if changed:
            self._recompute()

    def _recompute(self) -> None:
        policy = Policy(self.table, self.rules)
        routes, reach = resolve(self.node_id, policy, self.book, self.announced_hops)
        if routes != self._routes or reach != self._neighbours:
            hops_changed = {d: h for d, (_, h) in routes.items()} != {
                d: h for d, (_, h) in self._routes.items()
            }
            self.update(reach, routes)
            if hops_changed and self._loop is not None and not self._announce_soon:
                # the others count hops through ours: tell them now, once per burst
                self._announce_soon = True
                self._loop.call_soon(self._announce_now)

    def _announce_now(self) -> None:
        self._announce_soon = False
        self.announce()

    def wait_for(self, predicate: Callable[[KernelRoutes], bool]) -> asyncio.Future[None]:
        """A future done once ``predicate(self)`` holds after a change (or already does)."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        if predicate(self):
            fut.set_result(None)
            return fut

        def check(_: object) -> None:
            if not fut.done() and predicate(self):
                fut.set_result(None)
                unsubscribe()

        unsubscribe = self.subscribe(check)
        return fut


def _log_failure(task: asyncio.Future[None]) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.warning("reading the kernel's routes failed: %s", task.exception())
