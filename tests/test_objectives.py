"""Objective functions (mso.planning.objectives) against hand-computed values."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mso.model.app import App
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.planning.objectives import (
    DEFAULT_EVENT_BYTES,
    OBJECTIVES,
    end_to_end_hops,
    energy_per_event,
    evaluate,
    is_routable,
    max_node_load,
    route_tables,
)


def line(*nodes: NodeSpec) -> Network:
    ids = [n.id for n in nodes]
    return Network(list(nodes), [LinkSpec(a, b) for a, b in itertools.pairwise(ids)])


def two_vertex_app(size: int | None = 100) -> App:
    app = App("two")
    app.vertex("A", pinned="N1", cost=2.0)
    app.vertex("B", cost=3.0)
    app.edge("A", "B", size=size)
    return app.validate(resolve_code=False)


def three_node_line() -> Network:
    return line(
        NodeSpec(
            "N1", cpu=2.0, power=PowerModel(cpu_w=4.0, tx_uj_per_byte=2.0, rx_uj_per_byte=1.0)
        ),
        NodeSpec(
            "N2", cpu=1.0, power=PowerModel(cpu_w=5.0, tx_uj_per_byte=5.0, rx_uj_per_byte=1.0)
        ),
        NodeSpec(
            "N3", cpu=1.0, power=PowerModel(cpu_w=6.0, tx_uj_per_byte=7.0, rx_uj_per_byte=3.0)
        ),
    )


# -- energy ---------------------------------------------------------------------------------


def test_energy_two_hops_by_hand() -> None:
    app, net = two_vertex_app(), three_node_line()
    # CPU: A 2 ms / cpu 2 = 1 ms at 4 W = 4 mJ; B 3 ms at 6 W = 18 mJ.
    # Radio N1->N2: 100 B * (tx 2 + rx 1) µJ = 300 µJ; N2->N3: 100 * (5 + 3) = 800 µJ.
    expected = 0.004 + 0.018 + 0.0003 + 0.0008
    assert energy_per_event(app, net, {"A": "N1", "B": "N3"}) == pytest.approx(expected, abs=1e-12)


def test_energy_is_directional() -> None:
    """Sender pays tx, receiver rx: the reverse direction costs differently."""
    app = App("rev")
    app.vertex("A", pinned="N3", cost=0.0)
    app.vertex("B", cost=0.0)
    app.edge("A", "B", size=100)
    app.validate(resolve_code=False)
    # N3->N2: 100 * (7 + 1) = 800 µJ; N2->N1: 100 * (5 + 1) = 600 µJ.
    got = energy_per_event(app, three_node_line(), {"A": "N3", "B": "N1"})
    assert got == pytest.approx(0.0014, abs=1e-12)


def test_energy_colocated_has_no_radio_cost() -> None:
    app, net = two_vertex_app(), three_node_line()
    # A 1 ms at 4 W + B 1.5 ms at 4 W = 10 mJ, nothing on the radio.
    assert energy_per_event(app, net, {"A": "N1", "B": "N1"}) == pytest.approx(0.010, abs=1e-12)


def test_energy_default_event_size() -> None:
    app = two_vertex_app(size=None)
    net = three_node_line()
    radio = DEFAULT_EVENT_BYTES * (3 + 8) * 1e-6
    got = energy_per_event(app, net, {"A": "N1", "B": "N3"})
    assert got == pytest.approx(0.022 + radio, abs=1e-12)
    assert DEFAULT_EVENT_BYTES == 64


def test_energy_excludes_idle_power() -> None:
    app = two_vertex_app()
    busy = line(
        NodeSpec("N1", power=PowerModel(idle_w=100.0)), NodeSpec("N2", power=PowerModel(idle_w=50))
    )
    idle = line(NodeSpec("N1"), NodeSpec("N2"))
    p = {"A": "N1", "B": "N2"}
    assert energy_per_event(app, busy, p) == energy_per_event(app, idle, p)


def test_unreachable_is_infinite() -> None:
    app = two_vertex_app()
    net = Network([NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3")], [LinkSpec("N1", "N2")])
    p = {"A": "N1", "B": "N3"}
    assert energy_per_event(app, net, p) == math.inf
    assert end_to_end_hops(app, net, p) == math.inf
    assert max_node_load(app, net, p) == 3.0  # load does not care about routes
    assert not is_routable(app, net, p)
    assert is_routable(app, net, {"A": "N1", "B": "N2"})


# -- load -----------------------------------------------------------------------------------


def test_max_load_by_hand() -> None:
    app = App("load")
    app.vertex("A", cost=2.0)
    app.vertex("B", cost=3.0)
    app.vertex("C", cost=4.0)
    app.edge("A", "B")
    app.edge("B", "C")
    app.validate(resolve_code=False)
    net = line(NodeSpec("N1", cpu=2.0), NodeSpec("N2", cpu=0.5), NodeSpec("N3", cpu=1.0))
    # N1: (2 + 4) / 2 = 3; N2: 3 / 0.5 = 6; N3 empty.
    assert max_node_load(app, net, {"A": "N1", "B": "N2", "C": "N1"}) == pytest.approx(6.0)
    # N1: 9 / 2 = 4.5.
    assert max_node_load(app, net, {"A": "N1", "B": "N1", "C": "N1"}) == pytest.approx(4.5)


def test_max_load_no_cpu_node() -> None:
    app = App("z")
    app.vertex("A", cost=1.0)
    app.vertex("F", cost=0.0)
    app.validate(resolve_code=False)
    net = Network([NodeSpec("N1"), NodeSpec("N2", cpu=0.0)])
    assert max_node_load(app, net, {"A": "N1", "F": "N2"}) == 1.0
    assert max_node_load(app, net, {"A": "N2", "F": "N1"}) == math.inf


# -- hops -----------------------------------------------------------------------------------


def diamond() -> App:
    app = App("diamond")
    for v in "ABCD":
        app.vertex(v)
    for s, d in ("AB", "AC", "BD", "CD"):
        app.edge(s, d)
    return app.validate(resolve_code=False)


def test_hops_diamond_by_hand() -> None:
    net = line(*(NodeSpec(f"N{i}") for i in range(1, 5)))
    # d[A] = 0, d[B] = 1, d[C] = 3, d[D] = max(1 + 1, 3 + 1) = 4.
    assert end_to_end_hops(diamond(), net, {"A": "N1", "B": "N2", "C": "N4", "D": "N3"}) == 4
    # Both branches 1 hop then back: d[D] = max(1 + 1, 1 + 1) = 2.
    assert end_to_end_hops(diamond(), net, {"A": "N1", "B": "N2", "C": "N2", "D": "N1"}) == 2
    assert end_to_end_hops(diamond(), net, dict.fromkeys("ABCD", "N3")) == 0


def test_hops_single_vertex() -> None:
    app = App("one")
    app.vertex("A")
    app.validate(resolve_code=False)
    assert end_to_end_hops(app, line(NodeSpec("N1")), {"A": "N1"}) == 0


# -- shared ---------------------------------------------------------------------------------


def test_evaluate_returns_every_objective() -> None:
    app, net = two_vertex_app(), three_node_line()
    p = {"A": "N1", "B": "N3"}
    got = evaluate(app, net, p)
    assert set(got) == set(OBJECTIVES) == {"energy", "max_load", "hops"}
    assert got == {
        "energy": energy_per_event(app, net, p),
        "max_load": max_node_load(app, net, p),
        "hops": end_to_end_hops(app, net, p),
    }
    assert got["hops"] == 2
    assert got["max_load"] == 3.0


def test_bad_placement_is_rejected() -> None:
    app, net = two_vertex_app(), three_node_line()
    with pytest.raises(ValueError, match="does not place vertex 'B'"):
        energy_per_event(app, net, {"A": "N1"})
    with pytest.raises(ValueError, match="not in the network"):
        max_node_load(app, net, {"A": "N1", "B": "N9"})


def test_route_tables_follow_network_routes() -> None:
    net = Network(
        [NodeSpec(f"N{i}") for i in range(5)],
        [LinkSpec("N0", "N1"), LinkSpec("N1", "N2"), LinkSpec("N0", "N2"), LinkSpec("N3", "N4")],
    )
    t = route_tables(net)
    for a in net.nodes:
        for b in net.nodes:
            h = net.hops(a, b)
            assert t.hops.get((a, b)) == h
            assert t.reachable(a, b) == (h is not None)
    assert t.comm_uj_per_byte["N0", "N0"] == 0.0
    assert t.comm_uj_per_byte["N0", "N2"] == 3.0  # one hop, default tx 2 + rx 1


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.integers(0, 3), min_size=3, max_size=3),
    st.lists(st.integers(0, 1000), min_size=2, max_size=2),
)
def test_chain_energy_matches_hop_by_hop_sum(nodes: list[int], sizes: list[int]) -> None:
    """Chain A -> B -> C on a 4-node line with default power: each hop costs 3 µJ/byte."""
    app = App("chain")
    for v in "ABC":
        app.vertex(v, cost=1.0)
    app.edge("A", "B", size=sizes[0])
    app.edge("B", "C", size=sizes[1])
    app.validate(resolve_code=False)
    net = line(*(NodeSpec(f"N{i}") for i in range(4)))
    p = {v: f"N{n}" for v, n in zip("ABC", nodes, strict=True)}
    d1, d2 = abs(nodes[0] - nodes[1]), abs(nodes[1] - nodes[2])
    expected = 3 * 1e-3 * 4.0 + (sizes[0] * d1 + sizes[1] * d2) * 3e-6
    tables = route_tables(net)
    assert energy_per_event(app, net, p) == pytest.approx(expected, abs=1e-12)
    assert energy_per_event(app, net, p, tables=tables) == energy_per_event(app, net, p)
    assert end_to_end_hops(app, net, p) == d1 + d2
