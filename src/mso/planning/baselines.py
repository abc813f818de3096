"""Placements to compare Algorithm 1 (:mod:`mso.planning.placement`) against.

* :func:`all_at_source` -- no distribution at all: the node that owns the data runs everything,
  as the paper's leader robot would.
* :func:`random_placement` -- the floor any planner must beat.
* :func:`greedy_capacity` -- load balancing that ignores the network.
* :func:`optimal` -- the exact optimum of one objective of :mod:`mso.planning.objectives` by an
  integer linear program; a yardstick for small instances only (:data:`MAX_ILP_VARIABLES`).

All honour ``Vertex.pinned``, place every vertex and return ``{vertex: node}``. A pin to a node
not in the network is a :class:`~mso.errors.PlanningError`.
"""

from __future__ import annotations

import itertools
import math
import random
from typing import Protocol

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_array

from mso.errors import PlanningError
from mso.model.app import App
from mso.model.network import Network
from mso.planning.bytesplit import LINK_SHARE
from mso.planning.objectives import (
    OBJECTIVES,
    cpu_ms,
    edge_bytes,
    route_tables,
    vertex_energy_j,
    vertex_rates,
)
from mso.planning.placement import vertex_loads

MAX_ILP_VARIABLES = 2000
""":func:`optimal` refuses models with more variables than this. It counts ``x[v, n]`` (one per
vertex and node), for ``energy`` and ``hops`` also ``y[e, n, m]`` (one per edge and ordered pair
of mutually reachable nodes), plus a few continuous ones. E.g. 6 vertices, 6 edges, 8 nodes:
``48 + 6 * 64 = 432``."""


def _check(app: App, network: Network) -> None:
    if not network.nodes:
        raise PlanningError("the network has no nodes")
    for v in app.vertices.values():
        if v.pinned is not None and v.pinned not in network.nodes:
            raise PlanningError(
                f"vertex {v.id!r} is pinned to node {v.pinned!r}, which is not in the network "
                f"(nodes: {', '.join(network.nodes)})"
            )


def _ancestors(app: App) -> dict[str, set[str]]:
    pred = app.predecessors()
    out: dict[str, set[str]] = {}
    for v in app.topological_order():
        acc: set[str] = set()
        for u in pred[v]:
            acc.add(u)
            acc |= out[u]
        out[v] = acc
    return out


def all_at_source(app: App, network: Network, origin: str | None = None) -> dict[str, str]:
    """Run each unpinned vertex where its data comes from: on the node of the first (in app
    vertex order) pinned source among its ancestors; with none, on ``origin`` (default: the
    network's first node). No work is spread, so this is the "no middleware" reference."""
    _check(app, network)
    origin = origin if origin is not None else next(iter(network.nodes))
    if origin not in network.nodes:
        raise PlanningError(f"origin node {origin!r} is not in the network")
    sources = set(app.sources())
    anc = _ancestors(app)
    out: dict[str, str] = {}
    for v in app.vertices.values():
        if v.pinned is not None:
            out[v.id] = v.pinned
            continue
        owner = next(
            (
                s.pinned
                for s in app.vertices.values()
                if s.id in anc[v.id] and s.id in sources and s.pinned is not None
            ),
            None,
        )
        out[v.id] = owner if owner is not None else origin
    return out


def random_placement(app: App, network: Network, seed: int) -> dict[str, str]:
    """Each unpinned vertex on a node drawn uniformly, in app vertex order; the same ``seed``
    always gives the same placement (for repeatable benchmarks)."""
    _check(app, network)
    rng = random.Random(seed)
    nodes = list(network.nodes)
    return {
        v.id: v.pinned if v.pinned is not None else rng.choice(nodes) for v in app.vertices.values()
    }


def greedy_capacity(app: App, network: Network) -> dict[str, str]:
    """In topological order, each unpinned vertex on the node whose load would be lowest
    afterwards, ``(load_n + cost_v) / cpu_n`` (load includes pinned vertices); ties go to the
    node declared first. Balances CPU but ignores the radio."""
    _check(app, network)
    load = dict.fromkeys(network.nodes, 0.0)
    for v in app.vertices.values():
        if v.pinned is not None:
            load[v.pinned] += v.cost
    out: dict[str, str] = {}
    for vid in app.topological_order():
        v = app.vertices[vid]
        if v.pinned is not None:
            out[vid] = v.pinned
            continue
        best = min(
            enumerate(network.nodes),
            key=lambda item: (cpu_ms(load[item[1]] + v.cost, network.nodes[item[1]].cpu), item[0]),
        )[1]
        load[best] += v.cost
        out[vid] = best
    return {vid: out[vid] for vid in app.vertices}


def _rated_links(
    network: Network, nodes: list[str], pairs: list[tuple[int, int]]
) -> list[tuple[float, list[int]]]:
    """For each link with a rate: the bits per second edges may put on it (its
    :data:`~mso.planning.bytesplit.LINK_SHARE`, both directions together) and the node pairs
    whose routes cross it."""
    rated = {k: lk.bandwidth_mbps for k, lk in network.links.items() if lk.bandwidth_mbps}
    if not rated:
        return []
    crossing: dict[tuple[str, str], list[int]] = {}
    for p, (a, b) in enumerate(pairs):
        route = network.route(nodes[a], nodes[b]) or []
        for s, t in itertools.pairwise(route):
            key = (s, t) if s <= t else (t, s)
            if key in rated:
                crossing.setdefault(key, []).append(p)
    return [(rated[k] * 1e6 * LINK_SHARE, ps) for k, ps in sorted(crossing.items())]


def optimal(
    app: App,
    network: Network,
    objective: str = "energy",
    time_limit: float = 10.0,
    *,
    capacity: bool = True,
) -> dict[str, str]:
    """A placement minimising ``objective`` (a key of :data:`~mso.planning.objectives.OBJECTIVES`)
    exactly, by a mixed-integer program solved with HiGHS (``scipy.optimize.milp``).

    Binary ``x[v, n]`` puts vertex ``v`` on node ``n``. For ``energy`` and ``hops`` each edge
    ``u -> v`` gets continuous ``y[e, n, m]`` over reachable ordered pairs, tied to ``x`` by
    ``sum_m y[e, n, m] = x[u, n]`` and ``sum_n y[e, n, m] = x[v, m]`` (exact for integral
    ``x``); a pair with no route has no ``y``, so it is infeasible. ``max_load`` forbids such
    pairs with ``x[u, n] + x[v, m] <= 1`` and minimises ``z >= load_n``; ``hops`` minimises
    ``z >= d_v >= d_u + sum y[e, n, m] * hops(n, m)``. Nodes where a vertex would cost infinite
    energy or load (``cpu <= 0``) are excluded for it. With ``capacity`` (the default) every
    node's load stays within its CPU: ``sum_v load_v * x[v, n] <= 1000 * cpu_n``, a vertex's
    load being its cost times its event rate in ms per second
    (:func:`~mso.planning.placement.vertex_loads`) -- a yardstick no deployable placement
    could reach is no yardstick; and for ``energy`` and ``hops`` every link with a rate
    (``bandwidth_mbps``) carries at most :data:`~mso.planning.bytesplit.LINK_SHARE` of it:
    ``sum_e bits_e * y[e, n, m] <= share * rate`` over the pairs whose route crosses it, an
    edge's bits being its size times its producer's events per second times 8.

    Raises PlanningError when the model would exceed :data:`MAX_ILP_VARIABLES`, when no
    placement routes every edge, or when ``time_limit`` seconds pass before optimality is
    proven (a yardstick must be exact, so no incumbent is returned).
    """
    if objective not in OBJECTIVES:
        raise PlanningError(f"unknown objective {objective!r} (known: {', '.join(OBJECTIVES)})")
    _check(app, network)
    verts = list(app.vertices.values())
    if not verts:
        return {}
    nodes = list(network.nodes)
    nv, nn = len(verts), len(nodes)
    vi = {v.id: i for i, v in enumerate(verts)}
    tables = route_tables(network)
    pairs = [(a, b) for a in range(nn) for b in range(nn) if tables.reachable(nodes[a], nodes[b])]
    use_y = objective in ("energy", "hops")
    rates = vertex_rates(app)

    n_x = nv * nn
    n_y = len(app.edges) * len(pairs) if use_y else 0
    n_var = n_x + n_y + (nv + 1 if objective == "hops" else 0) + (objective == "max_load")
    if n_var > MAX_ILP_VARIABLES:
        raise PlanningError(
            f"the {objective} ILP for {nv} vertices, {len(app.edges)} edges and {nn} nodes "
            f"needs {n_var} variables, more than the limit of {MAX_ILP_VARIABLES}; "
            "optimal() is a yardstick for small instances only"
        )

    def x(v: int, n: int) -> int:
        return v * nn + n

    def y(e: int, p: int) -> int:
        return n_x + e * len(pairs) + p

    d0 = n_x + n_y  # hops: d_v at d0 + v
    z = n_var - 1  # hops, max_load: the objective variable

    c = np.zeros(n_var)
    lb, ub = np.zeros(n_var), np.ones(n_var)
    integrality = np.zeros(n_var)
    integrality[:n_x] = 1
    if objective in ("hops", "max_load"):
        ub[n_x + n_y :] = np.inf
        c[z] = 1.0

    for vert in verts:
        for n, node in enumerate(nodes):
            i = x(vi[vert.id], n)
            if vert.pinned is not None:
                lb[i] = ub[i] = 1.0 if node == vert.pinned else 0.0
            if objective in ("energy", "max_load") and math.isinf(
                cpu_ms(vert.cost, network.nodes[node].cpu)
            ):
                ub[i] = 0.0
            if objective == "energy" and ub[i] > 0:
                c[i] = vertex_energy_j(vert.cost, network, node) * 1e6  # µJ: keeps HiGHS' gaps tiny
    if np.any(lb > ub):
        raise PlanningError("a vertex is pinned to a node with no CPU; no placement exists")

    rows: list[int] = []
    cols: list[int] = []
    vals: list[float] = []
    row_lb: list[float] = []
    row_ub: list[float] = []

    def row(terms: list[tuple[int, float]], lo: float, hi: float) -> None:
        r = len(row_lb)
        for col, val in terms:
            rows.append(r)
            cols.append(col)
            vals.append(val)
        row_lb.append(lo)
        row_ub.append(hi)

    for v in range(nv):
        row([(x(v, n), 1.0) for n in range(nn)], 1.0, 1.0)

    for e, edge in enumerate(app.edges):
        u, w = vi[edge.src], vi[edge.dst]
        if use_y:
            for n in range(nn):
                out_terms = [(y(e, p), 1.0) for p, (a, _) in enumerate(pairs) if a == n]
                row([*out_terms, (x(u, n), -1.0)], 0.0, 0.0)
                in_terms = [(y(e, p), 1.0) for p, (_, b) in enumerate(pairs) if b == n]
                row([*in_terms, (x(w, n), -1.0)], 0.0, 0.0)
            if objective == "energy":
                size = edge_bytes(edge)
                for p, (a, b) in enumerate(pairs):
                    c[y(e, p)] = size * tables.comm_uj_per_byte[nodes[a], nodes[b]]
            else:  # d_w - d_u - sum y * hops >= 0
                hop_terms = [
                    (y(e, p), -float(tables.hops[nodes[a], nodes[b]]))
                    for p, (a, b) in enumerate(pairs)
                ]
                row([(d0 + w, 1.0), (d0 + u, -1.0), *hop_terms], 0.0, np.inf)
        else:
            reach = set(pairs)
            for n in range(nn):
                for m in range(nn):
                    if (n, m) not in reach:
                        row([(x(u, n), 1.0), (x(w, m), 1.0)], -np.inf, 1.0)

    if capacity:
        loads = vertex_loads(app)
        for n, node in enumerate(nodes):
            terms = [(x(i, n), loads[t.id]) for i, t in enumerate(verts) if loads[t.id] > 0]
            if terms:
                row(terms, -np.inf, 1000.0 * max(network.nodes[node].cpu, 0.0))
    if capacity and use_y:
        for limit, ps in _rated_links(network, nodes, pairs):
            bits = [edge_bytes(edge) * rates[edge.src] * 8 for edge in app.edges]
            terms = [(y(e, p), b) for e, b in enumerate(bits) if b > 0 for p in ps]
            if terms:
                row(terms, -np.inf, limit)

    if objective == "hops":
        for v in range(nv):
            row([(z, 1.0), (d0 + v, -1.0)], 0.0, np.inf)
    elif objective == "max_load":
        for n, node in enumerate(nodes):
            cpu = network.nodes[node].cpu
            terms = [(x(i, n), t.cost / cpu) for i, t in enumerate(verts) if t.cost and cpu > 0]
            row([*terms, (z, -1.0)], -np.inf, 0.0)

    a_mat = coo_array((vals, (rows, cols)), shape=(len(row_lb), n_var)).tocsr()
    res = milp(
        c,
        integrality=integrality,
        bounds=Bounds(lb, ub),
        constraints=LinearConstraint(a_mat, row_lb, row_ub),
        options={"time_limit": time_limit, "mip_rel_gap": 0.0},
    )
    if res.status == 2:
        within = " within every node's CPU capacity" if capacity else ""
        raise PlanningError(
            f"no placement of app {app.name!r} routes every edge between its pinned "
            f"vertices{within}"
        )
    if res.status == 1:
        raise PlanningError(f"the {objective} ILP did not prove optimality within {time_limit:g} s")
    if res.status != 0 or res.x is None:
        raise PlanningError(f"the {objective} ILP failed: {res.message}")
    sol = np.asarray(res.x[:n_x]).reshape(nv, nn)
    return {v.id: nodes[int(np.argmax(sol[i]))] for i, v in enumerate(verts)}


class Baseline(Protocol):
    """The uniform signature of :data:`BASELINES`: ``(app, network, *, seed=0,
    objective="energy") -> {vertex: node}``; each entry ignores what it does not use
    (``seed`` is for ``random``, ``objective`` for ``optimal``)."""

    def __call__(
        self, app: App, network: Network, /, *, seed: int = 0, objective: str = "energy"
    ) -> dict[str, str]: ...


def _source(
    app: App, network: Network, /, *, seed: int = 0, objective: str = "energy"
) -> dict[str, str]:
    return all_at_source(app, network)


def _random(
    app: App, network: Network, /, *, seed: int = 0, objective: str = "energy"
) -> dict[str, str]:
    return random_placement(app, network, seed)


def _greedy(
    app: App, network: Network, /, *, seed: int = 0, objective: str = "energy"
) -> dict[str, str]:
    return greedy_capacity(app, network)


def _optimal(
    app: App, network: Network, /, *, seed: int = 0, objective: str = "energy"
) -> dict[str, str]:
    return optimal(app, network, objective)


BASELINES: dict[str, Baseline] = {
    "source": _source,
    "random": _random,
    "greedy": _greedy,
    "optimal": _optimal,
}
"""Baselines by name, all callable as :class:`Baseline`. Algorithm 1 itself is
``mso.planning.placement.plan(app, network).placement``."""
