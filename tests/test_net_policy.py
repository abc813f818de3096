"""The kernel view reads what the kernel uses: policy rules and the tables they select (batmand's
table 66, parsed from a capture of a real batmand in the netns testbed), and the overlay relay
to a member the kernel has no route to."""

from __future__ import annotations

import asyncio
import ipaddress
from pathlib import Path

import pytest

from mso.client import overlay_key
from mso.net.base import encode
from mso.net.routes_kernel import KernelRoutes, relays, resolve
from mso.net.routes_policy import (
    FR_ACT_GOTO,
    FR_ACT_UNREACHABLE,
    RTN_THROW,
    RTN_UNREACHABLE,
    KernelRoute,
    Policy,
    Rule,
    routes_from_ip_json,
    rules_from_ip_json,
)
from mso.net.tcp import TcpTransport
from mso.protocol import messages as m

DATA = Path(__file__).parent / "data" / "batmand"


def _net(s: str) -> ipaddress.IPv4Network:
    return ipaddress.IPv4Network(s)


def _batmand() -> Policy:
    rules = rules_from_ip_json((DATA / "ip-rule.json").read_text())
    routes = routes_from_ip_json((DATA / "ip-route-all.json").read_text())
    return Policy(routes, rules)


def test_batmand_routes_in_table_66_are_found_and_its_67_stops_the_lookup() -> None:
    policy = _batmand()
    assert [r.priority for r in policy.rules] == [0, 6600, 6699, 6700, 32766, 32767]
    r = policy.lookup("10.77.0.3")
    assert r is not None and r.table == 66 and r.dst == _net("10.77.0.3/32")
    # a node batmand does not know: table 67's unreachable default ends the lookup before
    # main's connected /16 (which the view would ignore anyway)
    assert policy.lookup("10.77.0.9") is None
    book = {"N1": ("10.77.0.1", 7000), "N2": ("10.77.0.2", 7000), "N3": ("10.77.0.3", 7000)}
    routes, reach = resolve("N1", policy, book, {})
    assert routes == {"N2": ("N2", 1), "N3": ("N3", 1)} and set(reach) == {"N2", "N3"}
    # read as the main table alone (what the view did before), batmand's nodes are invisible
    main_only = [r for r in routes_from_ip_json((DATA / "ip-route-all.json").read_text())]
    assert resolve("N1", Policy([r for r in main_only if r.table == 254]), book, {}) == ({}, {})


def test_rules_in_priority_order_with_throw_suppress_goto_invert_and_selectors() -> None:
    a = KernelRoute(_net("10.0.0.2/32"), None, 4, table=10)
    main = KernelRoute(_net("10.0.0.0/24"), "10.0.0.1", 4)
    throw = KernelRoute(_net("10.0.0.3/32"), None, 4, table=10, type=RTN_THROW)
    dead = KernelRoute(_net("10.0.0.4/32"), None, 4, table=11, type=RTN_UNREACHABLE)
    routes = [a, main, throw, dead]
    default = Rule(32766)
    assert Policy(routes, [Rule(100, 10), default]).lookup("10.0.0.2") == a
    # a throw route goes on to the next rule
    assert Policy(routes, [Rule(100, 10), default]).lookup("10.0.0.3") == main
    # an unreachable route stops it; so does an unreachable rule
    assert Policy(routes, [Rule(50, 11), default]).lookup("10.0.0.4") is None
    assert Policy(routes, [Rule(50, action=FR_ACT_UNREACHABLE), default]).lookup("10.0.0.2") is None
    # suppress_prefixlength 24 ignores main's /24 (a /32 in it would still count)
    assert Policy(routes, [Rule(100, 254, suppress_prefixlen=24)]).lookup("10.0.0.7") is None
    # goto skips the rules in between
    skipped = [Rule(10, action=FR_ACT_GOTO, goto=300), Rule(100, 10), Rule(300, 254)]
    assert Policy(routes, skipped).lookup("10.0.0.2") == main
    # a rule selecting on a mark or a source does not match the node's own traffic...
    assert Policy(routes, [Rule(100, 10, selective=True), default]).lookup("10.0.0.2") == main
    # ...unless inverted; a destination prefix limits a rule to it
    assert Policy(routes, [Rule(100, 10, selective=True, invert=True)]).lookup("10.0.0.2") == a
    only = [Rule(100, 10, dst=_net("10.0.1.0/24")), default]
    assert Policy(routes, only).lookup("10.0.0.2") == main
    # the default rules read the main table (local and default hold nothing for a node)
    assert Policy([main]).lookup("10.0.0.9") == main


def test_ip_json_parsing_of_rules_and_routes_and_bad_input() -> None:
    rules = rules_from_ip_json(
        '[{"priority": 5, "src": "10.0.0.0", "srclen": 8, "table": "main"},'
        ' {"priority": 6, "fwmark": "0x1", "table": "7"},'
        ' {"priority": 7, "not": true, "iif": "eth0", "table": "8"},'
        ' {"priority": 8, "action": "goto", "goto": 100},'
        ' {"priority": 9, "table": "main", "suppress_prefixlength": 0}]'
    )
    assert [r.selective for r in rules] == [True, True, True, False, False]
    assert rules[2].invert and rules[3].goto == 100 and rules[4].suppress_prefixlen == 0
    routes = routes_from_ip_json(
        '[{"dst": "default", "gateway": "10.0.0.1", "protocol": "babel"},'
        ' {"type": "multicast", "dst": "224.0.0.0/4"}, {"dst": "fe80::/64"}]'
    )
    assert routes == [KernelRoute(_net("0.0.0.0/0"), "10.0.0.1", 42)]
    for bad, why in (
        ("nope", "not JSON"),
        ('{"a": 1}', "JSON list of objects"),
        ('[{"priority": "x"}]', "entry 0"),
        ('[{"dst": "10.0.0.300"}]', "entry 0"),
    ):
        with pytest.raises(ValueError, match=why):
            (routes_from_ip_json if "dst" in bad else rules_from_ip_json)(bad)


def test_relays_only_through_nodes_whose_kernel_reaches_the_destination() -> None:
    book = {n: (f"10.0.0.{i}", 7000) for i, n in enumerate("ABCDX", start=1)}
    direct = {"B": ("B", 1), "C": ("C", 1), "D": ("B", 2)}
    heard = {"B": {"X": 3, "A": 1}, "C": {"X": 1}, "D": {"X": 1}}
    # C reaches X in 1 (2 from here), D in 1 but D is 2 away (3): C relays
    assert relays("A", direct, book, heard) == {"X": ("C", 2)}
    # nobody announces X: no route; a node never relays to itself
    assert relays("A", direct, book, {"B": {"B": 1}}) == {}
    # resolve adds the relay to the kernel's routes but not to the reachable set
    table = [KernelRoute(_net(f"10.0.0.{i}/32")) for i in (2, 3)]
    routes, reach = resolve("A", table, book, heard)
    assert routes == {"B": ("B", 1), "C": ("C", 1), "X": ("C", 2)} and "X" not in reach


def test_frames_to_a_node_without_a_kernel_route_go_through_a_relay_then_direct() -> None:
    """A, R, X on loopback addresses 127.0.0.1-3 with kernel views fed by hand: A's kernel has
    no route to X (a starved route) while R's has; A reaches X through R at the overlay level,
    and once A's route returns its frames go straight to X."""
    key = overlay_key("relay")

    async def run() -> None:
        names = {"A": "127.0.0.1", "R": "127.0.0.2", "X": "127.0.0.3"}
        views = {n: KernelRoutes(n, 0, key) for n in names}
        nets = {n: TcpTransport(n, ip, 0, key, views[n]) for n, ip in names.items()}
        got: asyncio.Queue[tuple[str, m.Message]] = asyncio.Queue()
        nets["X"].set_receiver(lambda src, msg: got.put_nowait((src, msg)))
        for n in names:
            await nets[n].start()
        try:
            book = {n: (ip, nets[n].port) for n, ip in names.items()}
            hosts = {n: KernelRoute(_net(f"{ip}/32")) for n, ip in names.items()}
            reach = {"A": ["R"], "R": ["A", "X"], "X": ["R"]}  # A and X: no kernel route
            for n, v in views.items():
                v.book = dict(book)
                v.table = [hosts[o] for o in reach[n]]
                v.announced_hops = {"R": {"A": 1, "X": 1}}
                v._recompute()
            assert views["A"].next_hop("X") == "R" and views["A"].routes()["X"] == ("R", 2)
            probe = m.Probe("app", 0, 0, "A", "X", ["A"], [1.0])
            nets["A"].send("X", *encode("A", "X", probe))
            assert await asyncio.wait_for(got.get(), 10) == ("A", probe)
            relayed = views["R"].counters.bytes_forwarded
            assert relayed > 0
            # the kernel route returns: A connects to X and frames go direct
            views["A"].table.append(hosts["X"])
            views["A"]._recompute()
            assert views["A"].next_hop("X") == "X"
            again = m.Probe("app", 0, 1, "A", "X", ["A"], [1.0])
            nets["A"].send("X", *encode("A", "X", again))
            assert await asyncio.wait_for(got.get(), 10) == ("A", again)
            assert views["R"].counters.bytes_forwarded == relayed
        finally:
            for n in names:
                await nets[n].close()

    asyncio.run(run())


def test_an_asymmetric_route_detours_through_a_neighbour_that_reaches_the_node() -> None:
    """X's kernel routes to A but A's has no route back (babeld's "no return route"): X sees
    A as a neighbour whose connection never comes, so after a moment what X holds for A goes
    through R, which reaches A; A reaches X through R as well (the relay)."""
    key = overlay_key("detour")

    async def run() -> None:
        names = {"A": "127.0.0.1", "R": "127.0.0.2", "X": "127.0.0.3"}
        views = {n: KernelRoutes(n, 0, key) for n in names}
        nets = {n: TcpTransport(n, ip, 0, key, views[n]) for n, ip in names.items()}
        got: dict[str, asyncio.Queue[tuple[str, m.Message]]] = {n: asyncio.Queue() for n in names}
        for n in names:
            nets[n].set_receiver(lambda src, msg, n=n: got[n].put_nowait((src, msg)))
            await nets[n].start()
        try:
            book = {n: (ip, nets[n].port) for n, ip in names.items()}
            hosts = {n: KernelRoute(_net(f"{ip}/32")) for n, ip in names.items()}
            reach = {"A": ["R"], "R": ["A", "X"], "X": ["A", "R"]}  # X -> A, not A -> X
            for n, v in views.items():
                v.book = dict(book)
                v.table = [hosts[o] for o in reach[n]]
                v.announced_hops = {"R": {"A": 1, "X": 1}, "X": {"A": 1, "R": 1}}
                v._recompute()
            assert views["X"].next_hop("A") == "A" and views["X"].detour("A") == "R"
            probe = m.Probe("app", 0, 0, "X", "A", ["X"], [1.0])
            nets["X"].send("A", *encode("X", "A", probe))  # held, then sent through R
            assert await asyncio.wait_for(got["A"].get(), 10) == ("X", probe)
            assert views["R"].counters.bytes_forwarded > 0
            back = m.Probe("app", 0, 1, "A", "X", ["A"], [1.0])
            nets["A"].send("X", *encode("A", "X", back))
            assert await asyncio.wait_for(got["X"].get(), 10) == ("A", back)
        finally:
            for n in names:
                await nets[n].close()

    asyncio.run(run())
