"""Objective functions for placements, defined once and shared by every planner, the exact ILP
(:mod:`mso.planning.baselines`) and the benchmarks, so they all score a placement the same way.

Each objective takes ``(app, network, placement)`` and returns a float, lower is better; a
placement with an edge between nodes that have no route scores ``math.inf``. The per-pair route
quantities are computed by :func:`route_tables`; pass the result as ``tables=`` to score many
placements on one network without walking routes again.

Units: a vertex's ``cost`` is ms of CPU per event on a node of ``cpu: 1.0``; an edge carries
``edge.size`` bytes per event (:data:`DEFAULT_EVENT_BYTES` when not given).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Protocol

from mso.model.app import App, Edge
from mso.model.network import Network

DEFAULT_EVENT_BYTES = 64
"""Bytes per event assumed for an edge without a ``size`` estimate."""

Placement = Mapping[str, str]


@dataclass(frozen=True)
class RouteTables:
    """Route quantities for every ordered pair of nodes of one network snapshot.

    ``hops[a, b]`` is the hop count of ``network.route(a, b)`` and ``comm_uj_per_byte[a, b]`` the
    µJ one byte costs along it (sender's tx plus receiver's rx at every hop); both are absent
    when ``b`` is unreachable from ``a``. Ordered, because routes and tx/rx costs are not
    symmetric. A snapshot: rebuild it after the network's links change.
    """

    nodes: tuple[str, ...]
    hops: dict[tuple[str, str], int]
    comm_uj_per_byte: dict[tuple[str, str], float]

    def reachable(self, a: str, b: str) -> bool:
        return (a, b) in self.hops


def route_tables(network: Network) -> RouteTables:
    """Walk ``network.route`` once for every ordered node pair."""
    hops: dict[tuple[str, str], int] = {}
    comm: dict[tuple[str, str], float] = {}
    for a in network.nodes:
        for b in network.nodes:
            route = network.route(a, b)
            if route is None:
                continue
            hops[a, b] = len(route) - 1
            comm[a, b] = sum(
                network.nodes[x].power.tx_uj_per_byte + network.nodes[y].power.rx_uj_per_byte
                for x, y in pairwise(route)
            )
    return RouteTables(tuple(network.nodes), hops, comm)


def edge_bytes(edge: Edge) -> int:
    """Bytes one event on ``edge`` carries, for planning."""
    return DEFAULT_EVENT_BYTES if edge.size is None else edge.size


def cpu_ms(cost: float, cpu: float) -> float:
    """ms of CPU a vertex of ``cost`` takes per event on a node of speed ``cpu``.

    A node with no CPU (``cpu <= 0``) cannot run work: infinite unless the cost is zero."""
    if cost == 0:
        return 0.0
    return cost / cpu if cpu > 0 else math.inf


def vertex_energy_j(cost: float, network: Network, node: str) -> float:
    """Joules of CPU power (idle excluded) one event of a vertex of ``cost`` takes on ``node``."""
    spec = network.nodes[node]
    return cpu_ms(cost, spec.cpu) * 1e-3 * spec.power.cpu_w


def _check(app: App, network: Network, placement: Placement) -> None:
    for v in app.vertices:
        node = placement.get(v)
        if node is None:
            raise ValueError(f"the placement does not place vertex {v!r}")
        if node not in network.nodes:
            raise ValueError(f"vertex {v!r} is placed on {node!r}, which is not in the network")


def is_routable(
    app: App, network: Network, placement: Placement, *, tables: RouteTables | None = None
) -> bool:
    """Whether every edge's endpoints are placed on nodes with a route between them."""
    _check(app, network, placement)
    t = tables or route_tables(network)
    return all(t.reachable(placement[e.src], placement[e.dst]) for e in app.edges)


def energy_per_event(
    app: App, network: Network, placement: Placement, *, tables: RouteTables | None = None
) -> float:
    """Joules for one round: every vertex processes one event and every edge carries one.

    CPU: ``cost * 1e-3 / cpu`` seconds at ``cpu_w`` watts. Radio: each hop ``a -> b`` of the
    edge's route costs ``bytes * (tx[a] + rx[b])`` µJ; co-located endpoints cost nothing.
    Idle power is left out because no placement changes it.
    """
    _check(app, network, placement)
    t = tables or route_tables(network)
    total = sum(vertex_energy_j(v.cost, network, placement[v.id]) for v in app.vertices.values())
    for e in app.edges:
        uj = t.comm_uj_per_byte.get((placement[e.src], placement[e.dst]))
        if uj is None:
            return math.inf
        total += edge_bytes(e) * uj * 1e-6
    return total


def max_node_load(
    app: App, network: Network, placement: Placement, *, tables: RouteTables | None = None
) -> float:
    """The busiest node's ms of CPU per round: ``max_n sum(cost_v on n) / cpu_n``.

    The bottleneck that bounds the app's sustainable event rate. ``tables`` is accepted only
    for a uniform signature; load does not depend on routes.
    """
    _check(app, network, placement)
    cost: dict[str, float] = dict.fromkeys(network.nodes, 0.0)
    for v in app.vertices.values():
        cost[placement[v.id]] += v.cost
    return max((cpu_ms(c, network.nodes[n].cpu) for n, c in cost.items()), default=0.0)


def end_to_end_hops(
    app: App, network: Network, placement: Placement, *, tables: RouteTables | None = None
) -> float:
    """Network hops along the app's longest source-to-sink path, a proxy for latency.

    ``d[v] = max over predecessors u of d[u] + hops(node[u], node[v])``; the result is the
    largest ``d`` (0 with no edges).
    """
    _check(app, network, placement)
    t = tables or route_tables(network)
    pred = app.predecessors()
    d: dict[str, float] = {}
    for v in app.topological_order():
        best = 0.0
        for u in pred[v]:
            h = t.hops.get((placement[u], placement[v]))
            if h is None:
                return math.inf
            best = max(best, d[u] + h)
        d[v] = best
    return max(d.values(), default=0.0)


def vertex_rates(
    app: App,
    topo: Sequence[str] | None = None,
    pred: Mapping[str, Sequence[str]] | None = None,
) -> dict[str, float]:
    """Each vertex's events per second: a source's ``rate`` (1/s if not given), any other
    vertex's the sum of its inputs'. ``topo``/``pred``: the app's topological order and
    predecessors, if the caller has them."""
    pred = pred if pred is not None else app.predecessors()
    rate: dict[str, float] = {}
    for v in topo if topo is not None else app.topological_order():
        vert = app.vertices[v]
        rate[v] = sum(rate[u] for u in pred[v]) if pred[v] else float(vert.rate or 1.0)
    return rate


def busiest_cpu(app: App, network: Network, placement: Placement) -> float:
    """The busiest node's CPU share with events at their rates (1.0: full): whether a
    placement can run at all, which the per-event objectives do not say."""
    _check(app, network, placement)
    rates = vertex_rates(app)
    used = dict.fromkeys(network.nodes, 0.0)
    for v in app.vertices.values():
        used[placement[v.id]] += rates[v.id] * float(v.cost)
    return max((cpu_ms(ms, network.nodes[n].cpu) / 1e3 for n, ms in used.items()), default=0.0)


def busiest_link(app: App, network: Network, placement: Placement) -> float:
    """The busiest link's share of its rate (``bandwidth_mbps``; 1.0: full) with the edges'
    bytes at their events per second, both directions summed (one radio channel); 0 when no
    link has a rate. Routes as :func:`route_tables` takes them."""
    _check(app, network, placement)
    rates = vertex_rates(app)
    share: dict[tuple[str, str], float] = {}
    for e in app.edges:
        route = network.route(placement[e.src], placement[e.dst]) or []
        for a, b in pairwise(route):
            link = network.link(a, b)
            if link is not None and link.bandwidth_mbps:
                key = (a, b) if a <= b else (b, a)
                bits = edge_bytes(e) * rates[e.src] * 8
                share[key] = share.get(key, 0.0) + bits / (link.bandwidth_mbps * 1e6)
    return max(share.values(), default=0.0)


class Objective(Protocol):
    """``(app, network, placement, *, tables=None) -> float``; lower is better."""

    def __call__(
        self,
        app: App,
        network: Network,
        placement: Placement,
        /,
        *,
        tables: RouteTables | None = None,
    ) -> float: ...


OBJECTIVES: dict[str, Objective] = {
    "energy": energy_per_event,
    "max_load": max_node_load,
    "hops": end_to_end_hops,
}


def evaluate(
    app: App, network: Network, placement: Placement, *, tables: RouteTables | None = None
) -> dict[str, float]:
    """Every objective of :data:`OBJECTIVES` for one placement."""
    t = tables or route_tables(network)
    return {name: f(app, network, placement, tables=t) for name, f in OBJECTIVES.items()}
