"""Which route the kernel uses to reach an address: its policy rules, then the tables they select.

A routing daemon need not write the main table. batmand puts its routes in table 66 behind
rules (``6600: to 10.77.0.0/16 lookup 66``, then ``6700: to 10.77.0.0/16 lookup 67`` whose
``unreachable default`` stops the lookup); FRR, BIRD and babeld can all be told to use another
table. So the view reads every rule and every table and does what the kernel does
(:meth:`Policy.lookup`): rules in priority order; a rule that matches sends the lookup to its
table; the longest prefix there decides: a unicast route is the answer, a ``throw`` (or no
match, or a prefix no longer than the rule's ``suppress_prefixlength``) goes on to the next rule,
``unreachable``/``blackhole``/``prohibit`` end it with no route. A rule whose action is
``unreachable``, ``blackhole`` or ``prohibit`` ends it too; ``goto`` jumps ahead.

The node's own traffic is what matters: an unbound socket's first lookup has no source address,
no mark, no type of service and comes from ``lo``. So a rule that selects on a source prefix,
a mark, an output interface, an input interface other than ``lo``, a type of service, a user
range, a protocol or ports is taken not to match (``not`` inverts that, as in the kernel).

Parsers: netlink messages as pyroute2 returns them (:func:`rule_from_netlink`,
:func:`route_from_netlink`) and ``ip -j rule`` / ``ip -j route show table all`` output
(:func:`rules_from_ip_json`, :func:`routes_from_ip_json`: fixtures, and a record of a device
to check the view against).
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

RTN_UNICAST = 1
RTN_LOCAL = 2
RTN_BROADCAST = 3
RTN_BLACKHOLE = 6
RTN_UNREACHABLE = 7
RTN_PROHIBIT = 8
RTN_THROW = 9
ROUTE_TYPES = {
    "unicast": RTN_UNICAST,
    "local": RTN_LOCAL,
    "broadcast": RTN_BROADCAST,
    "blackhole": RTN_BLACKHOLE,
    "unreachable": RTN_UNREACHABLE,
    "prohibit": RTN_PROHIBIT,
    "throw": RTN_THROW,
}
"""Route types the lookup acts on (anycast, multicast and nat never route to a node)."""
STOPS = {RTN_BLACKHOLE, RTN_UNREACHABLE, RTN_PROHIBIT, RTN_LOCAL, RTN_BROADCAST}

FR_ACT_TO_TBL = 1
FR_ACT_GOTO = 2
FR_ACT_NOP = 3
FR_ACT_BLACKHOLE = 6
FR_ACT_UNREACHABLE = 7
FR_ACT_PROHIBIT = 8
RULE_ACTIONS = {
    "goto": FR_ACT_GOTO,
    "nop": FR_ACT_NOP,
    "blackhole": FR_ACT_BLACKHOLE,
    "unreachable": FR_ACT_UNREACHABLE,
    "prohibit": FR_ACT_PROHIBIT,
}
FIB_RULE_INVERT = 0x2
NO_SUPPRESS = -1

LOCAL_TABLE, MAIN_TABLE, DEFAULT_TABLE = 255, 254, 253
TABLE_NAMES = {"local": LOCAL_TABLE, "main": MAIN_TABLE, "default": DEFAULT_TABLE, "unspec": 0}
PROTO_KERNEL = 2  # a connected subnet
PROTOCOLS = {"redirect": 1, "kernel": 2, "boot": 3, "static": 4, "babel": 42, "bird": 12,
             "zebra": 11, "ospf": 188, "bgp": 186}  # fmt: skip
MAX_RULES = 10_000
MAX_ROUTES = 200_000


@dataclass(frozen=True)
class KernelRoute:
    """One IPv4 route of one of the kernel's tables."""

    dst: ipaddress.IPv4Network
    gateway: str | None = None
    proto: int = 0
    table: int = MAIN_TABLE
    type: int = RTN_UNICAST


@dataclass(frozen=True)
class Rule:
    """One policy rule, as far as the node's own traffic can match it."""

    priority: int
    table: int = MAIN_TABLE
    action: int = FR_ACT_TO_TBL
    dst: ipaddress.IPv4Network | None = None
    selective: bool = False  # selects on something the node's plain traffic does not carry
    invert: bool = False
    suppress_prefixlen: int = NO_SUPPRESS
    goto: int | None = None

    def matches(self, addr: ipaddress.IPv4Address) -> bool:
        hit = not self.selective and (self.dst is None or addr in self.dst)
        return hit != self.invert


DEFAULT_RULES = (Rule(0, LOCAL_TABLE), Rule(32766, MAIN_TABLE), Rule(32767, DEFAULT_TABLE))
"""What a kernel has before anyone adds a rule."""


class Policy:
    """The kernel's rules and tables, to look addresses up in as the kernel does.

    Connected-subnet routes (``proto kernel``) are left out of the lookup: on a shared ad hoc
    subnet they claim every node is one hop away, which only the routing daemon knows.
    """

    def __init__(self, routes: Iterable[KernelRoute], rules: Iterable[Rule] = DEFAULT_RULES):
        self.rules = sorted(rules, key=lambda r: r.priority)
        self.tables: dict[int, list[KernelRoute]] = {}
        for r in routes:
            if r.type in ROUTE_TYPES.values() and not (
                r.proto == PROTO_KERNEL and r.type == RTN_UNICAST
            ):
                self.tables.setdefault(r.table, []).append(r)

    def routes(self) -> list[KernelRoute]:
        """Every unicast route in every table (where announcements may go)."""
        return [r for t in self.tables.values() for r in t if r.type == RTN_UNICAST]

    def lookup(self, ip: str) -> KernelRoute | None:
        """The unicast route the kernel would send a packet for ``ip`` by; None when it has
        none (no rule found one, or a rule or route said unreachable)."""
        addr = ipaddress.IPv4Address(ip)
        skip_below: int | None = None
        for rule in self.rules:
            if skip_below is not None and rule.priority < skip_below:
                continue
            skip_below = None
            if not rule.matches(addr):
                continue
            if rule.action == FR_ACT_GOTO:
                skip_below = rule.goto if rule.goto is not None else rule.priority + 1
                continue
            if rule.action == FR_ACT_NOP:
                continue
            if rule.action != FR_ACT_TO_TBL:
                return None  # blackhole, unreachable, prohibit
            best = longest_match(self.tables.get(rule.table, ()), addr)
            if best is None or best.type == RTN_THROW:
                continue
            if best.type in STOPS:
                return None
            if best.dst.prefixlen <= rule.suppress_prefixlen:
                continue
            return best
        return None


def longest_match(table: Iterable[KernelRoute], addr: ipaddress.IPv4Address) -> KernelRoute | None:
    """The longest-prefix match for ``addr`` (first of equals)."""
    best: KernelRoute | None = None
    for r in table:
        if addr in r.dst and (best is None or r.dst.prefixlen > best.dst.prefixlen):
            best = r
    return best


# -- netlink (pyroute2 messages) ------------------------------------------------------------
_SELECTIVE_ATTRS = ("FRA_OIFNAME", "FRA_FWMARK", "FRA_UID_RANGE", "FRA_IP_PROTO",
                    "FRA_SPORT_RANGE", "FRA_DPORT_RANGE", "FRA_L3MDEV")  # fmt: skip


def _network(addr: str | None, length: int) -> ipaddress.IPv4Network:
    return ipaddress.IPv4Network(f"{addr or '0.0.0.0'}/{length}", strict=False)


def rule_from_netlink(msg: Any) -> Rule:
    """A rule from an ``RTM_NEWRULE`` message (pyroute2's dict-like message)."""
    iif = msg.get("FRA_IIFNAME")
    selective = (
        bool(msg.get("src_len"))
        or bool(msg.get("tos"))
        or (iif is not None and iif != "lo")
        or any(msg.get(a) not in (None, 0) for a in _SELECTIVE_ATTRS)
    )
    suppress = msg.get("FRA_SUPPRESS_PREFIXLEN")
    dst_len = int(msg.get("dst_len") or 0)
    return Rule(
        priority=int(msg.get("FRA_PRIORITY") or 0),
        table=int(msg.get("FRA_TABLE") or msg.get("table") or 0),
        action=int(msg.get("action") or FR_ACT_TO_TBL),
        dst=_network(msg.get("FRA_DST"), dst_len) if dst_len else None,
        selective=selective,
        invert=bool(int(msg.get("flags") or 0) & FIB_RULE_INVERT),
        suppress_prefixlen=NO_SUPPRESS if suppress in (None, 0xFFFFFFFF) else int(suppress),
        goto=msg.get("FRA_GOTO"),
    )


def route_from_netlink(msg: Any) -> KernelRoute | None:
    """A route from an ``RTM_NEWROUTE`` message; None for a type no lookup acts on."""
    kind = int(msg["type"])
    if kind not in ROUTE_TYPES.values():
        return None
    table = msg.get("table")
    return KernelRoute(
        _network(msg.get("dst"), int(msg["dst_len"])),
        msg.get("gateway"),
        int(msg["proto"]),
        int(table if table is not None else MAIN_TABLE),
        kind,
    )


# -- ip -j output ---------------------------------------------------------------------------
def _table(name: Any) -> int:
    if isinstance(name, int):
        return name
    if name in TABLE_NAMES:
        return TABLE_NAMES[name]
    return int(str(name))


def _entries(text: str, what: str) -> list[dict[str, Any]]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what}: not JSON ({exc})") from None
    if not isinstance(data, list) or not all(isinstance(e, dict) for e in data):
        raise ValueError(f"{what}: expected a JSON list of objects (ip -j output)")
    if len(data) > (MAX_RULES if what == "ip -j rule" else MAX_ROUTES):
        raise ValueError(f"{what}: {len(data)} entries is more than a device has")
    return data


def rules_from_ip_json(text: str) -> list[Rule]:
    """The rules in ``ip -j rule`` output; ValueError saying what is wrong with bad input."""
    out = []
    for i, e in enumerate(_entries(text, "ip -j rule")):
        try:
            src = e.get("src", "all")
            iif = e.get("iif")
            dst = e.get("dst")
            action = RULE_ACTIONS.get(str(e.get("action", "")), FR_ACT_TO_TBL)
            selective = (
                src not in ("all", None)
                or (iif is not None and iif != "lo")
                or any(k in e for k in ("oif", "fwmark", "tos", "uidrange", "ipproto",
                                        "sport", "dport", "l3mdev"))
            )  # fmt: skip
            out.append(
                Rule(
                    priority=int(e.get("priority", 0)),
                    table=_table(e.get("table", 0)),
                    action=action,
                    dst=None if dst in (None, "all") else _network(dst, int(e.get("dstlen", 32))),
                    selective=selective,
                    invert=bool(e.get("not", False)),
                    suppress_prefixlen=int(e.get("suppress_prefixlength", NO_SUPPRESS)),
                    goto=int(e["goto"]) if "goto" in e else None,
                )
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"ip -j rule: entry {i} ({e!r}): {exc}") from None
    return out


def routes_from_ip_json(text: str) -> list[KernelRoute]:
    """The IPv4 routes in ``ip -j -4 route show table all`` output (others are skipped)."""
    out = []
    for i, e in enumerate(_entries(text, "ip -j route")):
        try:
            kind = ROUTE_TYPES.get(str(e.get("type", "unicast")))
            dst = str(e.get("dst", ""))
            if kind is None or ":" in dst:
                continue
            net = ipaddress.IPv4Network("0.0.0.0/0" if dst == "default" else dst, strict=False)
            proto = e.get("protocol", 0)
            out.append(
                KernelRoute(
                    net,
                    e.get("gateway"),
                    PROTOCOLS.get(proto, 0) if isinstance(proto, str) else int(proto),
                    _table(e.get("table", "main")),
                    kind,
                )
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"ip -j route: entry {i} ({e!r}): {exc}") from None
    return out
