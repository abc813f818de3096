"""Placement along probed routes (paper §3.3, Algorithm 1)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mso.errors import PlanningError
from mso.model.app import App
from mso.model.appfile import load_app
from mso.model.chains import Chain, chain_dependencies
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.planning.placement import (
    Hop,
    Plan,
    allocate_prefix,
    assign_along,
    network_probe,
    place_chain,
    plan,
)
from mso.scenario import load_scenario

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


def line(cpus: Sequence[float] = (1, 1, 1, 1)) -> Network:
    ids = [f"N{i + 1}" for i in range(len(cpus))]
    nodes = [NodeSpec(i, cpu=float(c)) for i, c in zip(ids, cpus, strict=True)]
    return Network(nodes, [LinkSpec(a, b) for a, b in itertools.pairwise(ids)])


def section33(cost: float = 1.0) -> App:
    app = App("section33")
    for v in "ABCDEF":
        app.vertex(v, cost=cost, pinned={"A": "N1", "F": "N4"}.get(v))
    for a, b in ["AB", "BC", "CD", "ED", "DF"]:
        app.edge(a, b)
    return app.validate()


# -- the paper's example: the paper's split (planner: paper; the default is bytes) ---------


def test_section33_example() -> None:
    p = plan(section33(), line(), planner="paper")
    assert [c.name for c in p.chains] == ["A-B-C-D", "D-F", "E-D"]
    pl = p.placement
    assert pl["A"] == "N1" and pl["F"] == "N4"
    # A-B-C-D is allocated N1-N2-N3: cost(A-B-C-D) / (cost(A-B-C-D) + cost(D-F)) = 4/6, the
    # fewest route nodes reaching that share of capacity are 3 of 4.
    assert {pl["B"], pl["C"], pl["D"]} <= {"N1", "N2", "N3"}
    assert pl["D"] != "N4"
    # Each of N1..N3 takes 4/3 units of A-B-C-D: midpoints 1.5, 2.5, 3.5.
    assert (pl["B"], pl["C"], pl["D"]) == ("N2", "N2", "N3")
    assert pl["E"] == "N1"  # an unpinned source starts on the origin (the first node)
    assert p.routes[0] == ["N1", "N2", "N3", "N4"]
    # A-B-C-D before D-F, and E-D before D-F.
    pos = {ci: k for k, ci in enumerate(p.order)}
    assert pos[0] < pos[1] and pos[2] < pos[1]
    assert p.order == [0, 2, 1]


def test_section33_from_example_files() -> None:
    app = load_app(EXAMPLES / "section33.yaml")
    net = load_scenario(EXAMPLES / "line4.yaml").network
    assert plan(app, net, planner="paper") == plan(section33(), line(), planner="paper")
    doc = plan(app, net, planner="paper").to_json()
    assert doc["chains"] == [["A", "B", "C", "D"], ["D", "F"], ["E", "D"]]
    assert doc["order"] == [0, 2, 1]
    assert doc["placement"]["D"] == "N3"
    assert doc["routes"][0] == ["N1", "N2", "N3", "N4"]


def test_section33_fast_node_takes_more() -> None:
    # N2 three times as fast: N1-N2 already hold 4/6 of the capacity, so A-B-C-D gets
    # N1-N2 only, and N2 (capacity 3 of 4 in that prefix) takes everything after A.
    p = plan(section33(), line((1, 3, 1, 1)), planner="paper")
    assert [p.placement[v] for v in "ABCDEF"] == ["N1", "N2", "N2", "N2", "N1", "N4"]
    # Cheaper downstream work leaves more of the route to the chain.
    app = section33()
    app.vertices["F"].cost = 0.0
    p = plan(app.validate(), line(), planner="paper")
    # fraction 4/5 -> 4 nodes; 4 units over 4 nodes: B, C, D at 1.5, 2.5, 3.5.
    assert [p.placement[v] for v in "BCD"] == ["N2", "N3", "N4"]


def test_fig2_on_line4() -> None:
    app = load_app(EXAMPLES / "fig2.yaml")
    p = plan(app, line(), planner="paper")
    # A-B-C-D as in §3.3 (target E on N4, D-E after it); F-G has 2 of 6 units on the way to
    # E (D-E and G-D after it): 2 nodes, G on N2; G-H-I runs N2 -> N4 with H in the middle.
    assert p.placement == {
        "A": "N1",
        "B": "N2",
        "C": "N2",
        "D": "N3",
        "E": "N4",
        "F": "N1",
        "G": "N2",
        "H": "N3",
        "I": "N4",
    }
    assert p.routes[4] == ["N2", "N3", "N4"]
    assert p.order == [0, 2, 3, 4, 1]


def test_origin_hosts_unpinned_sources() -> None:
    app = App("t")
    app.vertex("S")
    app.vertex("T", pinned="N4")
    app.vertex("X")  # isolated
    app.edge("S", "T")
    p = plan(app.validate(), line(), origin="N3")
    assert p.placement == {"S": "N3", "T": "N4", "X": "N3"}


# -- errors ---------------------------------------------------------------------------------


def test_pinned_to_unknown_node() -> None:
    app = App("t")
    app.vertex("A", pinned="N1")
    app.vertex("B", pinned="N9")
    app.edge("A", "B")
    with pytest.raises(PlanningError) as info:
        plan(app.validate(), line())
    msg = str(info.value)
    assert "'B'" in msg and "'N9'" in msg and "not in the network" in msg
    assert "\n" not in msg


def test_bad_origin_and_empty_network() -> None:
    with pytest.raises(PlanningError, match="origin node 'N7'"):
        plan(section33(), line(), origin="N7")
    with pytest.raises(PlanningError, match="no nodes"):
        plan(section33(), Network([]))


def test_unreachable_pinned_node() -> None:
    net = Network([NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3"), NodeSpec("N4")])
    net.add_link(LinkSpec("N1", "N2"))
    app = App("t")
    for v, pin in [("A", "N1"), ("B", None), ("C", "N4")]:
        app.vertex(v, pinned=pin)
    app.edge("A", "B")
    app.edge("B", "C")
    with pytest.raises(PlanningError, match="no route from N1 to N4"):
        plan(app.validate(), net)


# -- allocate_prefix and assign_along -------------------------------------------------------


def test_allocate_prefix_hand_values() -> None:
    assert allocate_prefix([1, 1, 1, 1], 4 / 6) == 3
    assert allocate_prefix([1, 1, 1, 1], 0.5) == 2
    assert allocate_prefix([1, 1, 1, 1], 0.51) == 3
    assert allocate_prefix([2, 1, 1], 0.5) == 1  # the fast first node alone holds half
    assert allocate_prefix([1, 2, 1], 0.5) == 2
    assert allocate_prefix([1, 1, 1, 3], 0.5) == 3
    assert allocate_prefix([1, 1], 0.0) == 1  # at least one node
    assert allocate_prefix([1, 1, 1], 1.0) == 3
    assert allocate_prefix([5], 0.3) == 1
    assert allocate_prefix([0, 0, 0, 0], 0.5) == 2  # no capacity anywhere: by count
    with pytest.raises(ValueError):
        allocate_prefix([], 0.5)


def test_assign_along_hand_values() -> None:
    # §3.3: B, C, D after A (lead 1) over three equal nodes: bounds 4/3, 8/3, 4.
    assert assign_along([1, 1, 1], [1, 1, 1], lead=1) == [1, 1, 2]
    # A node with cpu 2 takes twice the slice: bounds 2, 3 for costs 1, 1, 1.
    assert assign_along([1, 1, 1], [2, 1]) == [0, 0, 1]
    assert assign_along([1, 1, 1], [1, 2]) == [0, 1, 1]
    assert assign_along([1, 1, 1, 1], [1, 1, 2]) == [0, 1, 2, 2]
    # One heavy vertex sits where its cost midpoint falls.
    assert assign_along([3], [1, 1, 1]) == [1]
    # A trailing anchor's cost pulls vertices toward the start.
    assert assign_along([1], [1, 1], lead=1) == [1]
    assert assign_along([1], [1, 1], lead=1, trail=2) == [0]
    # All free: spread by count.
    assert assign_along([0, 0], [1, 1]) == [0, 1]
    assert assign_along([0, 0, 0, 0], [1, 1]) == [0, 0, 1, 1]
    # One node takes everything; no capacity anywhere means equal slices.
    assert assign_along([1, 2, 3], [4]) == [0, 0, 0]
    assert assign_along([1, 1], [0, 0]) == [0, 1]
    assert assign_along([], [1, 1]) == []
    with pytest.raises(ValueError):
        assign_along([1], [])


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.sampled_from([0.5, 1.0, 2.0, 3.0, 0.25]), min_size=1, max_size=8),
    st.floats(0.0, 1.0),
)
def test_allocate_prefix_is_the_fewest_nodes(caps: list[float], fraction: float) -> None:
    k = allocate_prefix(caps, fraction)
    assert 1 <= k <= len(caps)
    total = sum(caps)
    assert sum(caps[:k]) / total >= fraction - 1e-9
    if k > 1:
        assert sum(caps[: k - 1]) / total < fraction - 1e-9


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.sampled_from([0.0, 0.5, 1.0, 2.0, 5.0]), max_size=8),
    st.lists(st.sampled_from([0.5, 1.0, 2.0, 3.0]), min_size=1, max_size=6),
    st.sampled_from([0.0, 1.0, 2.5]),
    st.sampled_from([0.0, 1.0, 2.5]),
)
def test_assign_along_never_goes_back(
    costs: list[float], caps: list[float], lead: float, trail: float
) -> None:
    idx = assign_along(costs, caps, lead=lead, trail=trail)
    assert len(idx) == len(costs)
    assert all(0 <= i < len(caps) for i in idx)
    assert idx == sorted(idx)
    # Capacity-proportional: a vertex lands on the node whose slice holds its cost midpoint.
    total = lead + sum(costs) + trail
    if total > 0:
        pos = lead
        for c, i in zip(costs, idx, strict=True):
            mid = (pos + c / 2) / total
            pos += c
            lo = sum(caps[:i]) / sum(caps)
            hi = sum(caps[: i + 1]) / sum(caps)
            assert lo - 1e-9 <= mid <= hi + 1e-9 or (i == len(caps) - 1 and mid >= lo - 1e-9)


# -- place_chain with a recorded probe ------------------------------------------------------


class RecordingProbe:
    def __init__(self, routes: dict[tuple[str, str], list[Hop]]) -> None:
        self.routes = routes
        self.calls: list[tuple[str, str]] = []

    def __call__(self, a: str, b: str) -> list[Hop]:
        self.calls.append((a, b))
        return self.routes.get((a, b), [])


def test_place_chain_uses_probed_capacities() -> None:
    chain = Chain(0, ("X", "Y", "Z"))
    cost = {"X": 1.0, "Y": 1.0, "Z": 1.0}
    probe = RecordingProbe({("a", "c"): [Hop("a", 1), Hop("b", 2), Hop("c", 1)]})
    # Nothing downstream: the whole route; bounds 0.75, 2.25, 3 -> Y at 1.5 on b, Z at 2.5 on c.
    out, route = place_chain(chain, cost, {"X": "a"}, probe, target="c")
    assert out == {"Y": "b", "Z": "c"} and route == ["a", "b", "c"]
    assert probe.calls == [("a", "c")]
    # As much cost downstream: half the capacity -> a, b; 3 units, a takes 1 and b 2.
    out, _ = place_chain(chain, cost, {"X": "a"}, probe, target="c", downstream_cost=3.0)
    assert out == {"Y": "b", "Z": "b"}
    # No target: the free end stays on the head's node, nothing probed.
    probe.calls.clear()
    out, route = place_chain(chain, cost, {"X": "a"}, probe)
    assert out == {"Y": "a", "Z": "a"} and route == ["a"] and probe.calls == []


def test_place_chain_between_anchors() -> None:
    chain = Chain(0, ("P", "Q", "R", "S", "T"))
    cost = dict.fromkeys("PQRST", 1.0)
    probe = RecordingProbe(
        {
            ("a", "c"): [Hop("a", 1), Hop("b", 1), Hop("c", 1)],
            ("c", "e"): [Hop("c", 1), Hop("d", 1), Hop("e", 1)],
        }
    )
    out, route = place_chain(chain, cost, {"P": "a", "R": "c"}, probe, target="e")
    # P..R: Q alone between two anchors (lead 1, trail 1): b. After R: fraction 1 -> c, d, e.
    assert out == {"Q": "b", "S": "d", "T": "e"}
    assert route == ["c", "d", "e"] and probe.calls == [("a", "c"), ("c", "e")]


def test_place_chain_errors() -> None:
    chain = Chain(3, ("X", "Y"))
    with pytest.raises(PlanningError, match="head 'X' is not placed"):
        place_chain(chain, {"X": 1.0, "Y": 1.0}, {}, RecordingProbe({}))
    with pytest.raises(PlanningError, match="chain X-Y: no route from a to z"):
        place_chain(chain, {"X": 1.0, "Y": 1.0}, {"X": "a"}, RecordingProbe({}), target="z")


def test_network_probe() -> None:
    probe = network_probe(line((1, 2, 3)), capacity=lambda n: n.cpu * 10)
    assert list(probe("N1", "N3")) == [Hop("N1", 10), Hop("N2", 20), Hop("N3", 30)]
    net = Network([NodeSpec("A"), NodeSpec("B")])
    assert list(network_probe(net)("A", "B")) == []


# -- random apps on random networks ---------------------------------------------------------


@st.composite
def connected_networks(draw: st.DrawFn) -> Network:
    n = draw(st.integers(1, 7))
    ids = [f"N{i}" for i in range(n)]
    cpus = draw(st.lists(st.sampled_from([0.5, 1.0, 2.0, 3.0]), min_size=n, max_size=n))
    links = {(ids[draw(st.integers(0, i - 1))], ids[i]) for i in range(1, n)}
    if n >= 3:
        extra = st.tuples(st.integers(0, n - 1), st.integers(0, n - 1))
        for a, b in draw(st.lists(extra, max_size=n)):
            if a < b:
                links.add((ids[a], ids[b]))
    perm = draw(st.permutations(ids))
    nodes = [NodeSpec(i, cpu=cpus[ids.index(i)]) for i in perm]
    return Network(nodes, [LinkSpec(a, b) for a, b in sorted(links)])


@st.composite
def dag_apps(draw: st.DrawFn, nodes: list[str]) -> App:
    n = draw(st.integers(1, 12))
    names = [f"v{i}" for i in range(n)]
    edges: set[tuple[int, int]] = set()
    if n >= 2:
        pair = st.tuples(st.integers(0, n - 2), st.integers(1, n - 1)).filter(lambda p: p[0] < p[1])
        edges = set(draw(st.lists(pair, max_size=2 * n)))
        if draw(st.booleans()):
            edges |= {(i, i + 1) for i in range(n - 1)}
    has_in = {b for _, b in edges}
    has_out = {a for a, _ in edges}
    app = App("random")
    for i, v in enumerate(names):
        end = i not in has_in or i not in has_out
        pin = draw(st.sampled_from(nodes)) if end and draw(st.booleans()) else None
        cost = draw(st.sampled_from([0.0, 0.5, 1.0, 2.0, 4.0]))
        app.vertex(v, cost=cost, pinned=pin)
    for a, b in sorted(edges):
        app.edge(names[a], names[b])
    return app.validate()


def check_plan(app: App, net: Network, p: Plan) -> None:
    pl = p.placement
    assert set(pl) == set(app.vertices)
    assert all(node in net.nodes for node in pl.values())
    for v in app.vertices.values():
        if v.pinned is not None:
            assert pl[v.id] == v.pinned, v.id
    assert sorted(p.order) == list(range(len(p.chains)))
    pos = {ci: k for k, ci in enumerate(p.order)}
    for c, deps in zip(p.chains, chain_dependencies(p.chains), strict=True):
        assert all(pos[d] < pos[c.index] for d in deps)
    tails = {c.tail for c in p.chains if len(c) > 1}
    origin = next(iter(net.nodes))
    for c in p.chains:
        if c.head not in tails and app.vertices[c.head].pinned is None:
            assert pl[c.head] == origin
    for c in p.chains:
        if any(app.vertices[v].pinned is not None for v in c.vertices[1:-1]):
            continue
        route = p.routes[c.index]
        assert route[0] == pl[c.head], (c.name, route)
        for a, b in itertools.pairwise(route):
            assert net.link(a, b) is not None
        # With no probe between two placed ends (a 2-vertex chain), the route is just the
        # head's node: the tail may be elsewhere.
        skip_tail = len(c) == 2 and pl[c.tail] not in route
        verts = c.vertices[:-1] if skip_tail else c.vertices
        assert all(pl[v] in route for v in verts), (c.name, route, pl)
        where = [route.index(pl[v]) for v in verts]
        assert where == sorted(where), (c.name, route, [pl[v] for v in c.vertices])


@settings(max_examples=120, deadline=None)
@given(st.data())
def test_random_plans(data: st.DataObject) -> None:
    net = data.draw(connected_networks())
    app = data.draw(dag_apps(list(net.nodes)))
    p = plan(app, net)
    check_plan(app, net, p)
    assert plan(app, net) == p  # deterministic
