"""What a probe collects along a route for the planner (issue 25): each node's capacity and
power figures and each link's rate, from a probe reply's lists (:func:`probed_hops`) or from a
known network (:func:`network_probe`, the central plan's and the simulator's). Pure."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import replace

from mso.model.network import Network, NodeSpec
from mso.planning.bytesplit import Hop

Capacity = Callable[[NodeSpec], float]

# probe(from_node, to_node) -> the hops of the route, both ends included.
Probe = Callable[[str, str], Sequence[Hop]]


def cpu_capacity(node: NodeSpec) -> float:
    """The default capacity a probe reports: relative processing speed."""
    return node.cpu


def hop_of(node: NodeSpec, capacity: float, rate_mbps: float | None = None) -> Hop:
    """The hop a probe collects at ``node``: ``capacity``, the node's power model and the rate
    of the link it was reached over."""
    pw = node.power
    return Hop(node.id, capacity, pw.cpu_w, pw.tx_uj_per_byte, pw.rx_uj_per_byte, rate_mbps)


def _figure(x: object) -> bool:
    return isinstance(x, int | float) and math.isfinite(x) and x >= 0


def probed_hops(
    nodes: Sequence[str],
    capacities: Sequence[float],
    power: Sequence[Sequence[float]] = (),
    rates: Sequence[float] = (),
) -> list[Hop]:
    """The hops a probe reply carries. Power figures are taken only when there is one valid
    ``[cpu_w, tx, rx]`` (finite, non-negative) per hop; otherwise each hop gets the defaults,
    so a reply from a node that predates them, or a malformed one, still places the chain.
    Link rates likewise only when there is one valid figure (Mb/s, 0: not known) per link."""
    n = min(len(nodes), len(capacities))
    ok = len(power) == len(nodes) and all(len(f) == 3 and all(_figure(x) for x in f) for f in power)
    into: list[float | None] = [None] * n
    if len(rates) == len(nodes) - 1 and all(_figure(x) for x in rates):
        into = [None, *(float(x) or None for x in rates)][:n]
    if not ok:
        return [Hop(nodes[i], capacities[i], rate_mbps=into[i]) for i in range(n)]
    out = []
    for i in range(n):
        cpu_w, tx, rx = (float(x) for x in power[i])
        out.append(Hop(nodes[i], capacities[i], cpu_w, tx, rx, into[i]))
    return out


def link_rate(network: Network, a: str, b: str) -> float | None:
    """The rate (Mb/s) of the link between ``a`` and ``b`` in a known network (None: unshaped
    or no link): what a simulated node knows of its links, and the central plan's probe."""
    link = network.link(a, b)
    return None if link is None else link.bandwidth_mbps


def network_probe(network: Network, capacity: Capacity = cpu_capacity) -> Probe:
    """A probe over a known network: the shortest route and each node's capacity."""

    hops: dict[str, Hop] = {}  # each node's, made once

    def at(n: str) -> Hop:
        h = hops.get(n)
        if h is None:
            h = hops[n] = hop_of(network.nodes[n], capacity(network.nodes[n]))
        return h

    def probe(a: str, b: str) -> list[Hop]:
        route = network.route(a, b)
        if route is None:
            return []
        out = [at(route[0])]
        for x, y in itertools.pairwise(route):
            rate = link_rate(network, x, y)
            out.append(at(y) if rate is None else replace(at(y), rate_mbps=rate))
        return out

    return probe
