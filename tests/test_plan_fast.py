"""The planner's shortcuts for large apps place exactly what Algorithm 1 run plainly does."""

from __future__ import annotations

import random

import pytest

from mso.model.app import App, Edge, Vertex
from mso.model.chains import chain_dependencies, chain_order, form_chains
from mso.model.graph import topological_order
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.planning.placement import Layout, network_probe, plan


def big_app(seed: int, n: int = 500) -> tuple[App, Network]:
    """A random DAG as the largest allowed app is made (edges to the next 50, one vertex in
    ten pinned), smaller, on a random connected 12-node network."""
    rng = random.Random(seed)
    ids = [f"n{i}" for i in range(12)]
    nodes = [NodeSpec(i, cpu=rng.uniform(0.5, 2)) for i in ids]
    links = [LinkSpec(ids[i], ids[rng.randrange(i)]) for i in range(1, len(ids))]
    links += [LinkSpec(ids[i], ids[(i + 3) % len(ids)]) for i in range(0, len(ids), 4)]
    net = Network(nodes, links)
    app = App(f"big{seed}")
    for i in range(n):
        pin = rng.choice(ids) if i % 10 == 0 or i >= n - 3 else None
        app.vertices[f"v{i}"] = Vertex(f"v{i}", cost=round(rng.uniform(0.5, 5), 2), pinned=pin)
    edges = {(i, i + 1) for i in range(n - 1)}
    while len(edges) < 4 * n:
        a = rng.randrange(n - 1)
        edges.add((a, rng.randrange(a + 1, min(n, a + 50))))
    app.edges = [Edge(f"v{a}", f"v{b}", size=rng.choice([10, 100, 1000])) for a, b in sorted(edges)]
    return app, net


def plain_plan(app: App, net: Network, planner: str) -> tuple[dict[str, str], dict[int, list[str]]]:
    """Algorithm 1 as :func:`plan` ran it before its shortcuts: every chain through
    ``Layout.place``, each vertex's load added as it is placed."""
    layout = Layout(app, next(iter(net.nodes)), planner)
    probe = network_probe(net)
    placed = layout.initial_placement()
    used = layout.loads(placed)
    routes: dict[int, list[str]] = {}
    for ci in layout.order:
        start = layout.last_anchor_node(ci, placed)
        assigned, route = layout.place(ci, placed, probe, net.distances(start), used)
        for u, node in assigned.items():
            if u not in placed:
                used[node] = used.get(node, 0.0) + layout.load[u]
        placed.update(assigned)
        routes[ci] = route
    return {v: placed[v] for v in app.vertices}, routes


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("planner", ["paper", "bytes"])
def test_plan_places_as_algorithm_1_run_plainly(seed: int, planner: str) -> None:
    app, net = big_app(seed)
    fast = plan(app, net, planner=planner)
    placement, routes = plain_plan(app, net, planner)
    assert fast.placement == placement
    assert fast.routes == routes
    assert len(set(placement.values())) > 1  # the plan is not trivial


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_chain_order_is_kahns_over_the_dependencies(seed: int) -> None:
    app, _ = big_app(seed, 200)
    chains = form_chains(app)
    followers: dict[int, list[int]] = {c.index: [] for c in chains}
    for j, leading in enumerate(chain_dependencies(chains)):
        for i in leading:
            followers[i].append(j)
    assert chain_order(chains) == topological_order([c.index for c in chains], followers)
