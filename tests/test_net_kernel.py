"""The kernel routing view: resolution by id (pure), announcements, and the real thing over
netlink in three network namespaces this test builds (a line A-B-C with static routes)."""

from __future__ import annotations

import asyncio
import ipaddress
import os
import shutil
import subprocess
from collections.abc import Iterator
from typing import Any

import pytest

from mso.net.base import Neighbour
from mso.net.routes_kernel import (
    Announce,
    KernelRoute,
    KernelRoutes,
    open_announce,
    resolve,
    seal_announce,
)

PSK = b"k" * 32


def _r(dst: str, gw: str | None = None, proto: int = 42) -> KernelRoute:
    return KernelRoute(ipaddress.IPv4Network(dst), gw, proto)


def test_resolve_names_next_hops_and_counts_hops() -> None:
    book = {"A": ("10.0.0.1", 7000), "B": ("10.0.0.2", 7000), "C": ("10.0.0.3", 7001)}
    table = [
        _r("10.0.0.0/24", proto=2),  # connected subnet: says nothing about who hears whom
        _r("10.0.0.2/32", "10.0.0.2"),
        _r("10.0.0.3/32", "10.0.0.2"),
    ]
    routes, reach = resolve("A", table, book, {"B": {"C": 1, "A": 1}})
    assert routes == {"B": ("B", 1), "C": ("B", 2)}
    assert reach == {"B": Neighbour("10.0.0.2", 7000), "C": Neighbour("10.0.0.3", 7001)}
    # without B's announcement A still routes to C, assuming the shortest unknown distance
    assert resolve("A", table, book, {})[0]["C"] == ("B", 2)
    # a route whose gateway has not announced itself is not usable yet
    assert resolve("A", table, {"A": book["A"], "C": book["C"]}, {})[0] == {}
    # a subnet route via a gateway covers its members; a route with no gateway is a neighbour
    routes, _ = resolve("A", [_r("10.0.0.0/30", "10.0.0.2"), _r("10.0.0.3/32")], book, {})
    assert routes == {"B": ("B", 1), "C": ("C", 1)}


def test_announcements_are_authenticated_and_validated() -> None:
    msg = Announce("B", 7000, {"C": 1}, {"C": ("10.0.0.3", 7000)})
    sealed = seal_announce(PSK, msg)
    assert open_announce(PSK, sealed) == msg
    assert open_announce(b"x" * 32, sealed) is None  # another overlay's key
    assert open_announce(PSK, sealed[:-1] + b"\x00") is None  # tampered
    assert open_announce(PSK, b"short") is None
    bad = Announce("B", 7000, {}, {"C": ("not-an-ip", 1)})
    assert open_announce(PSK, seal_announce(PSK, bad)) is None


def test_view_learns_members_from_announcements() -> None:
    view = KernelRoutes("A", 7000, PSK)
    view.table = [_r("10.0.0.2/32", "10.0.0.2"), _r("10.0.0.3/32", "10.0.0.2")]
    seen: list[dict[str, tuple[str, int]]] = []
    view.subscribe(lambda ev: seen.append(dict(ev.routes)))
    # B announces itself (and knows C): A learns both addresses, routes to both
    msg = Announce("B", 7000, {"C": 1}, {"C": ("10.0.0.3", 7000)})
    view.on_announce(seal_announce(PSK, msg), "10.0.0.2")
    assert view.routes() == {"B": ("B", 1), "C": ("B", 2)}
    assert view.next_hop("C") == "C"  # the kernel forwards: the transport goes straight there
    assert view.next_hop("Z") is None
    view.on_announce(seal_announce(PSK, msg), "10.0.0.2")  # nothing new: no event
    view.on_announce(b"\x00" * 40, "10.0.0.9")
    assert len(seen) == 1 and view.rejected == 1


def test_a_relay_through_a_node_whose_announcements_stopped_is_forgotten() -> None:
    """B announced it reaches C; A has no kernel route to C, so it relays through B. B's
    announcements stop (it died, or its datagrams no longer reach A): after 3.5 periods what
    it said is forgotten, and with it the relay to C (a netns run kept one for 45 s)."""

    class Clock:
        t = 10.0

        def time(self) -> float:
            return self.t

        def call_soon(self, callback: Any) -> None:  # the view's "announce now": not here
            pass

    view = KernelRoutes("A", 7000, PSK, announce_s=1.0)
    clock = Clock()
    view._loop = clock  # type: ignore[assignment]
    view.table = [_r("10.0.0.2/32", "10.0.0.2")]
    msg = Announce("B", 7000, {"C": 1}, {"C": ("10.0.0.3", 7000)})
    view.on_announce(seal_announce(PSK, msg), "10.0.0.2")
    assert view.routes() == {"B": ("B", 1), "C": ("B", 2)}
    clock.t = 13.0
    view.expire_announcements(clock.t)  # 3 periods: still held
    assert "C" in view.routes()
    clock.t = 14.0
    view.expire_announcements(clock.t)
    assert view.routes() == {"B": ("B", 1)}  # B itself: the kernel still routes to it
    view.on_announce(seal_announce(PSK, msg), "10.0.0.2")  # it speaks again: relayed again
    assert view.routes()["C"] == ("B", 2)


class _Dumps(KernelRoutes):
    """A view whose table dumps the test hands out one by one (no netlink)."""

    def __init__(self) -> None:
        super().__init__("A", 7000, PSK)
        self.dumps: list[asyncio.Future[list[KernelRoute]]] = []
        self.started = asyncio.Event()

    async def reread(self) -> None:
        fut: asyncio.Future[list[KernelRoute]] = asyncio.get_running_loop().create_future()
        self.dumps.append(fut)
        self.started.set()
        self.table = await fut
        self._recompute()


def test_a_dump_begun_before_a_withdrawal_never_lands_after_a_later_one() -> None:
    """Re-reads run one at a time: an event during a dump reads again after it, so the last
    table the view holds is one read after the last event (else a route babeld withdrew could
    come back for good: under load a netns test waited 45 s for it)."""

    async def main() -> None:
        view = _Dumps()
        view._loop = asyncio.get_running_loop()
        old = [_r("10.0.0.2/32", "10.0.0.2")]
        view.book = {"B": ("10.0.0.2", 7000)}
        view._do_reread()
        await asyncio.wait_for(view.started.wait(), 5)
        view.started.clear()
        view._do_reread()  # the route is withdrawn while the first dump is under way
        assert len(view.dumps) == 1
        view.dumps[0].set_result(old)  # the first dump ends, with the old route
        await asyncio.wait_for(view.started.wait(), 5)  # and the view reads again
        assert len(view.dumps) == 2 and "B" in view.routes()
        view.dumps[1].set_result([])
        await asyncio.wait_for(view.wait_for(lambda v: "B" not in v.routes()), 5)
        assert view._reading is None and view._reread is None and len(view.dumps) == 2

    asyncio.run(main())


def test_lost_route_events_make_the_view_read_the_tables_anew() -> None:
    """A netlink socket that overflowed (ENOBUFS) raises from ``get``: the view counts it,
    re-reads the tables, and keeps following events (it used to stop following for good)."""
    import errno

    from pyroute2.netlink.exceptions import NetlinkError

    async def main() -> None:
        view = _Dumps()
        view._loop = asyncio.get_running_loop()
        calls: list[int] = []
        idle = asyncio.Event()

        class Events:
            async def get(self) -> Any:
                calls.append(1)
                if len(calls) == 1:
                    raise NetlinkError(errno.ENOBUFS)
                idle.set()
                await asyncio.Event().wait()  # no more events
                yield None

        view._events = Events()
        follow = asyncio.create_task(view._follow())
        await asyncio.wait_for(view.started.wait(), 5)
        await asyncio.wait_for(idle.wait(), 5)
        assert view.events_lost == 1 and len(calls) == 2 and len(view.dumps) == 1
        follow.cancel()
        view.dumps[0].set_result([])

    asyncio.run(main())


def _root_netns_reason() -> str | None:
    if os.geteuid() != 0:
        return "needs root to create network namespaces (CI runs as root)"
    if shutil.which("ip") is None:
        return "needs iproute2's ip command"
    probe = subprocess.run(["ip", "netns", "add", "mso-t11-probe"], capture_output=True)
    if probe.returncode != 0:
        return f"network namespaces unavailable: {probe.stderr.decode().strip()}"
    subprocess.run(["ip", "netns", "del", "mso-t11-probe"], capture_output=True)
    return None


_REASON = _root_netns_reason()


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def line3() -> Iterator[list[str]]:
    """Namespaces A - B - C joined by veth pairs, /32 addresses, static host routes."""
    tag = f"mso-kt{os.getpid() % 10000}"
    names = [f"{tag}-{n}" for n in "ABC"]
    try:
        for ns in names:
            _ip("netns", "add", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        a, b, c = names
        _ip("-n", a, "link", "add", "eth0", "type", "veth", "peer", "name", "ea", "netns", b)
        _ip("-n", c, "link", "add", "eth0", "type", "veth", "peer", "name", "ec", "netns", b)
        for ns, dev, ip in ((a, "eth0", 1), (b, "ea", 2), (b, "ec", 2), (c, "eth0", 3)):
            _ip("-n", ns, "addr", "add", f"10.77.0.{ip}/32", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
        subprocess.run(
            ["ip", "netns", "exec", b, "sysctl", "-qw", "net.ipv4.ip_forward=1"], check=True
        )
        _ip("-n", a, "route", "add", "10.77.0.2/32", "dev", "eth0", "proto", "static")
        _ip("-n", a, "route", "add", "10.77.0.3/32", "via", "10.77.0.2", "dev", "eth0", "onlink")
        _ip("-n", b, "route", "add", "10.77.0.1/32", "dev", "ea", "proto", "static")
        _ip("-n", b, "route", "add", "10.77.0.3/32", "dev", "ec", "proto", "static")
        _ip("-n", c, "route", "add", "10.77.0.2/32", "dev", "eth0", "proto", "static")
        _ip("-n", c, "route", "add", "10.77.0.1/32", "via", "10.77.0.2", "dev", "eth0", "onlink")
        yield names
    finally:
        for ns in names:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


@pytest.mark.slow
@pytest.mark.skipif(_REASON is not None, reason=_REASON or "")
def test_kernel_view_over_netlink_follows_route_changes(line3: list[str]) -> None:
    async def main() -> None:
        views = [
            KernelRoutes(n, 7411, PSK, netns=ns, announce_s=0.2)
            for n, ns in zip("ABC", line3, strict=True)
        ]
        for v in views:
            await v.start()
        a = views[0]
        try:
            want = {"B": ("B", 1), "C": ("B", 2)}
            await asyncio.wait_for(a.wait_for(lambda v: dict(v.routes()) == want), 10)
            assert a.neighbours()["C"] == Neighbour("10.77.0.3", 7411)
            assert a.next_hop("C") == "C"
            # a route the daemon withdraws is gone at once (an event, not a poll); B still
            # announces its own kernel route to C, so A reaches C through B, at the overlay
            await asyncio.wait_for(a.wait_for(lambda v: "C" in v.neighbours()), 5)
            _ip("-n", line3[0], "route", "del", "10.77.0.3/32")
            await asyncio.wait_for(a.wait_for(lambda v: "C" not in v.neighbours()), 5)
            assert a.routes()["C"] == ("B", 2) and a.next_hop("C") == "B"
            _ip("-n", line3[0], "route", "add", "10.77.0.3/32", "via", "10.77.0.2", "dev", "eth0",
                "onlink")  # fmt: skip
            await asyncio.wait_for(a.wait_for(lambda v: "C" in v.neighbours()), 5)
            assert dict(a.routes()) == want and a.next_hop("C") == "C"  # direct again
            # a rule that sends C's address to a table saying unreachable (as batmand's 67
            # does, or a starved route) hides the main table's route: relayed again
            _ip("-n", line3[0], "route", "add", "unreachable", "10.77.0.3/32", "table", "77")
            _ip("-n", line3[0], "rule", "add", "to", "10.77.0.3/32", "lookup", "77", "pref",
                "700")  # fmt: skip
            await asyncio.wait_for(a.wait_for(lambda v: "C" not in v.neighbours()), 5)
            assert a.next_hop("C") == "B"
            _ip("-n", line3[0], "rule", "del", "pref", "700")
            await asyncio.wait_for(a.wait_for(lambda v: "C" in v.neighbours()), 5)
        finally:
            for v in views:
                await v.close()

    asyncio.run(main())


def test_netns_addresses_split() -> None:
    from mso.client import split_netns

    assert split_netns("mso-1-n2@127.0.0.1:7000") == ("mso-1-n2", "127.0.0.1:7000")
    assert split_netns("10.0.0.1:7000") == (None, "10.0.0.1:7000")
    assert split_netns("@127.0.0.1:7000") == (None, "@127.0.0.1:7000")
