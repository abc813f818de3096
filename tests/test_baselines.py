"""Baseline placements and the exact ILP (mso.planning.baselines)."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mso.planning.baselines as baselines
from mso.errors import PlanningError
from mso.model.app import App
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.planning.baselines import (
    BASELINES,
    MAX_ILP_VARIABLES,
    all_at_source,
    greedy_capacity,
    optimal,
    random_placement,
)
from mso.planning.objectives import OBJECTIVES, evaluate, is_routable, route_tables
from mso.planning.placement import plan

OBJECTIVE_NAMES = list(OBJECTIVES)


def line(n: int, cpu: float = 1.0) -> Network:
    ids = [f"N{i}" for i in range(1, n + 1)]
    return Network(
        [NodeSpec(i, cpu=cpu) for i in ids],
        [LinkSpec(a, b) for a, b in itertools.pairwise(ids)],
    )


def chain_app(n: int) -> App:
    app = App("chain")
    for i in range(n):
        app.vertex(f"V{i}", cost=1.0)
    for i in range(n - 1):
        app.edge(f"V{i}", f"V{i + 1}", size=100)
    return app.validate(resolve_code=False)


# -- random instances ------------------------------------------------------------------------


@st.composite
def instances(draw: st.DrawFn, connected: bool = True) -> tuple[App, Network]:
    """<= 5 vertices (a random DAG, some pinned) on <= 4 nodes (heterogeneous cpu and radio)."""
    n_nodes = draw(st.integers(1, 4))
    ids = [f"N{i}" for i in range(1, n_nodes + 1)]
    nodes = [
        NodeSpec(
            i,
            cpu=draw(st.sampled_from([0.5, 1.0, 2.0, 3.0])),
            power=PowerModel(
                cpu_w=draw(st.sampled_from([1.0, 4.0, 9.0])),
                tx_uj_per_byte=draw(st.sampled_from([0.5, 2.0, 6.0])),
                rx_uj_per_byte=draw(st.sampled_from([0.5, 1.0, 3.0])),
            ),
        )
        for i in ids
    ]
    links = []
    for k in range(1, n_nodes):
        if connected or draw(st.booleans()):
            links.append(LinkSpec(ids[draw(st.integers(0, k - 1))], ids[k]))
    for a, b in itertools.combinations(ids, 2):
        if draw(st.integers(0, 3)) == 0:
            links.append(LinkSpec(a, b))
    network = Network(nodes, links)

    n_verts = draw(st.integers(1, 5))
    app = App("rand")
    for i in range(n_verts):
        pin = draw(st.none() | st.sampled_from(ids)) if draw(st.integers(0, 2)) == 0 else None
        app.vertex(f"V{i}", cost=float(draw(st.integers(0, 6))), pinned=pin)
    for i, j in itertools.combinations(range(n_verts), 2):
        if draw(st.booleans()):
            app.edge(f"V{i}", f"V{j}", size=draw(st.none() | st.integers(0, 400)))
    return app.validate(resolve_code=False), network


def brute_force(app: App, network: Network, objective: str) -> float:
    """Minimum of ``objective`` over every routable placement that honours the pins."""
    tables = route_tables(network)
    f = OBJECTIVES[objective]
    verts = list(app.vertices.values())
    choices = [[v.pinned] if v.pinned else list(network.nodes) for v in verts]
    best = math.inf
    for combo in itertools.product(*choices):
        p = {v.id: n for v, n in zip(verts, combo, strict=True)}
        if is_routable(app, network, p, tables=tables):
            best = min(best, f(app, network, p, tables=tables))
    return best


# -- the ILP against brute force ----------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(instances())
def test_ilp_matches_brute_force(inst: tuple[App, Network]) -> None:
    app, network = inst
    for objective in OBJECTIVE_NAMES:
        p = optimal(app, network, objective)
        assert set(p) == set(app.vertices)
        assert is_routable(app, network, p)
        got = OBJECTIVES[objective](app, network, p)
        assert got == pytest.approx(brute_force(app, network, objective), abs=1e-6, rel=1e-9)


@settings(max_examples=25, deadline=None)
@given(instances(connected=False))
def test_ilp_on_partitioned_networks(inst: tuple[App, Network]) -> None:
    """Pairs without a route are forbidden; with no routable placement the ILP refuses."""
    app, network = inst
    for objective in OBJECTIVE_NAMES:
        best = brute_force(app, network, objective)
        if math.isinf(best):
            with pytest.raises(PlanningError):
                optimal(app, network, objective)
        else:
            p = optimal(app, network, objective)
            assert is_routable(app, network, p)
            got = OBJECTIVES[objective](app, network, p)
            assert got == pytest.approx(best, abs=1e-6, rel=1e-9)


@settings(max_examples=25, deadline=None)
@given(instances(), st.integers(0, 2**32 - 1))
def test_ilp_never_worse_than_algorithm1_or_baselines(inst: tuple[App, Network], seed: int) -> None:
    app, network = inst
    others = {
        "algorithm1": plan(app, network).placement,
        "source": all_at_source(app, network),
        "random": random_placement(app, network, seed),
        "greedy": greedy_capacity(app, network),
    }
    for objective in OBJECTIVE_NAMES:
        best = OBJECTIVES[objective](app, network, optimal(app, network, objective))
        for name, p in others.items():
            assert best <= OBJECTIVES[objective](app, network, p) + 1e-6, (objective, name)


def test_ilp_hand_example() -> None:
    """A(pinned N1, 2 ms) -> B (5 ms) -> C (pinned N4, 1 ms) on a line N1..N4 of cpu 1..4."""
    app = App("x")
    app.vertex("A", pinned="N1", cost=2.0)
    app.vertex("B", cost=5.0)
    app.vertex("C", pinned="N4", cost=1.0)
    app.edge("A", "B", size=100)
    app.edge("B", "C", size=100)
    app.validate(resolve_code=False)
    net = Network(
        [NodeSpec(f"N{i}", cpu=float(i)) for i in range(1, 5)],
        [LinkSpec("N1", "N2"), LinkSpec("N2", "N3"), LinkSpec("N3", "N4")],
    )
    # Energy: B on the fastest node, N4 (the radio cost is the same 3 hops wherever B is).
    assert optimal(app, net, "energy") == {"A": "N1", "B": "N4", "C": "N4"}
    # Load: N1 always has 2; B on N3 gives 5/3, on N4 (5+1)/4 = 1.5, so 2 either way.
    assert evaluate(app, net, optimal(app, net, "max_load"))["max_load"] == pytest.approx(2.0)
    assert evaluate(app, net, optimal(app, net, "hops"))["hops"] == 3


def test_ilp_no_route_between_pins() -> None:
    app = App("x")
    app.vertex("A", pinned="N1")
    app.vertex("B", pinned="N2")
    app.edge("A", "B")
    app.validate(resolve_code=False)
    net = Network([NodeSpec("N1"), NodeSpec("N2")])
    for objective in OBJECTIVE_NAMES:
        with pytest.raises(PlanningError, match="routes every edge"):
            optimal(app, net, objective)


def test_ilp_unknown_objective() -> None:
    with pytest.raises(PlanningError, match="unknown objective 'latency'"):
        optimal(chain_app(2), line(2), "latency")


def test_ilp_empty_app() -> None:
    assert optimal(App("empty"), line(2)) == {}


def test_ilp_size_limit() -> None:
    # 20 vertices on 10 connected nodes: x = 200, y = 19 edges * 100 pairs = 1900.
    app, net = chain_app(20), line(10)
    with pytest.raises(PlanningError, match=f"2100 variables, more than the limit of {2000}"):
        optimal(app, net, "energy")
    with pytest.raises(PlanningError, match="limit"):
        optimal(app, net, "hops")
    assert MAX_ILP_VARIABLES == 2000
    # max_load needs no edge variables: 201, solved.
    p = optimal(app, net, "max_load")
    assert evaluate(app, net, p)["max_load"] == pytest.approx(2.0)


def test_ilp_size_limit_is_the_module_constant(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(baselines, "MAX_ILP_VARIABLES", 5)
    with pytest.raises(PlanningError, match="limit of 5"):
        optimal(chain_app(2), line(3), "max_load")  # 6 x + 1 z


# -- the simple baselines ---------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(instances(connected=False), st.integers(0, 1000))
def test_every_baseline_honours_pins(inst: tuple[App, Network], seed: int) -> None:
    app, network = inst
    for name, baseline in BASELINES.items():
        for objective in OBJECTIVE_NAMES if name == "optimal" else ["energy"]:
            try:
                p = baseline(app, network, seed=seed, objective=objective)
            except PlanningError:
                assert name == "optimal"  # only the ILP refuses unroutable instances
                continue
            assert set(p) == set(app.vertices), name
            assert all(n in network.nodes for n in p.values()), name
            for v in app.vertices.values():
                if v.pinned is not None:
                    assert p[v.id] == v.pinned, (name, v.id)


def test_pin_to_unknown_node_is_refused() -> None:
    app = App("x")
    app.vertex("A", pinned="N7")
    app.vertex("B")
    app.edge("A", "B")
    app.validate(resolve_code=False)
    for baseline in BASELINES.values():
        with pytest.raises(PlanningError, match="pinned to node 'N7', which is not in the network"):
            baseline(app, line(2))


def test_random_is_seed_deterministic() -> None:
    app, net = chain_app(5), line(4)
    assert random_placement(app, net, 7) == random_placement(app, net, 7)
    assert BASELINES["random"](app, net, seed=7) == random_placement(app, net, 7)
    seen = {tuple(random_placement(app, net, s).values()) for s in range(20)}
    assert len(seen) > 10
    used = {n for s in range(50) for n in random_placement(app, net, s).values()}
    assert used == set(net.nodes)


def test_all_at_source() -> None:
    app = App("src")
    app.vertex("U")  # unpinned source -> origin
    app.vertex("S2", pinned="N3")
    app.vertex("S1", pinned="N2")
    app.vertex("M")  # below S2 and S1: S2 is first in vertex order
    app.vertex("K", pinned="N4")  # pinned sink stays
    app.vertex("X")  # below U only -> origin
    app.vertex("Y")  # below S1 only
    app.edge("S1", "M")
    app.edge("S2", "M")
    app.edge("M", "K")
    app.edge("U", "X")
    app.edge("S1", "Y")
    app.validate(resolve_code=False)
    net = line(4)
    expected = {"U": "N1", "S2": "N3", "S1": "N2", "M": "N3", "K": "N4", "X": "N1", "Y": "N2"}
    assert all_at_source(app, net) == expected
    assert all_at_source(app, net, origin="N4") == {**expected, "U": "N4", "X": "N4"}
    with pytest.raises(PlanningError, match="origin node 'N9'"):
        all_at_source(app, net, origin="N9")


def test_all_at_source_skips_pinned_non_sources() -> None:
    """Only pinned *sources* own downstream work; a pinned operator on the way does not."""
    app = App("mid")
    app.vertex("S", pinned="N1")
    app.vertex("P", pinned="N3")
    app.vertex("Q")
    app.edge("S", "P")
    app.edge("P", "Q")
    app.validate(resolve_code=False)
    assert all_at_source(app, line(3)) == {"S": "N1", "P": "N3", "Q": "N1"}


def test_greedy_capacity_by_hand() -> None:
    app = App("g")
    app.vertex("A", pinned="N1", cost=2.0)
    app.vertex("B", cost=2.0)
    app.vertex("C", cost=3.0)
    app.vertex("D", cost=1.0)
    for s, d in ("AB", "BC", "CD"):
        app.edge(s, d)
    app.validate(resolve_code=False)
    net = Network([NodeSpec("N1", cpu=1.0), NodeSpec("N2", cpu=2.0)], [LinkSpec("N1", "N2")])
    # B: N1 (2+2)/1 = 4, N2 2/2 = 1 -> N2.  C: N1 5, N2 (2+3)/2 = 2.5 -> N2.
    # D: N1 (2+1)/1 = 3, N2 (5+1)/2 = 3 -> tie, first declared: N1.
    assert greedy_capacity(app, net) == {"A": "N1", "B": "N2", "C": "N2", "D": "N1"}


def test_greedy_follows_topological_order() -> None:
    """Vertices declared sink-first are still placed source-first."""
    app = App("t")
    app.vertex("C", cost=1.0)
    app.vertex("B", cost=1.0)
    app.vertex("A", cost=1.0)
    app.edge("A", "B")
    app.edge("B", "C")
    app.validate(resolve_code=False)
    net = Network([NodeSpec("N1", cpu=1.0), NodeSpec("N2", cpu=1.5)])
    # A: N1 1, N2 0.67 -> N2.  B: N1 1, N2 1.33 -> N1.  C: N1 2, N2 1.33 -> N2.
    assert greedy_capacity(app, net) == {"C": "N2", "B": "N1", "A": "N2"}


def test_registry() -> None:
    assert set(BASELINES) == {"source", "random", "greedy", "optimal"}
    app, net = chain_app(3), line(3)
    assert BASELINES["source"](app, net) == all_at_source(app, net)
    assert BASELINES["greedy"](app, net) == greedy_capacity(app, net)
    assert BASELINES["optimal"](app, net, objective="hops") == optimal(app, net, "hops")


def test_empty_network_is_refused() -> None:
    for baseline in BASELINES.values():
        with pytest.raises(PlanningError, match="no nodes"):
            baseline(chain_app(1), Network([]))
