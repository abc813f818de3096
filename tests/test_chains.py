"""Chain formation (paper §3.2) against the paper's Fig. 2, small shapes and a reference."""

from __future__ import annotations

import itertools
import random
from collections import Counter
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mso.model.app import App
from mso.model.chains import (
    Chain,
    chain_dependencies,
    chain_order,
    form_chains,
    form_chains_indexed,
)

FIG2_VERTICES = "ABCDEFGHI"
FIG2_EDGES = [
    ("A", "B"),
    ("B", "C"),
    ("C", "D"),
    ("D", "E"),
    ("F", "G"),
    ("G", "D"),
    ("G", "H"),
    ("H", "I"),
]
FIG2_CHAINS = ["A-B-C-D", "D-E", "F-G", "G-D", "G-H-I"]


def make_app(vertices: Sequence[str], edges: Sequence[tuple[str, str]], name: str = "t") -> App:
    app = App(name)
    for v in vertices:
        app.vertex(v)
    for a, b in edges:
        app.edge(a, b)
    return app


def names(chains: Sequence[Chain]) -> list[str]:
    return [c.name for c in chains]


def as_lists(offsets: Sequence[int], verts: Sequence[int]) -> list[list[int]]:
    offs = [int(x) for x in offsets]
    vs = [int(x) for x in verts]
    return [vs[a:b] for a, b in itertools.pairwise(offs)]


def indexed(n: int, edges: Sequence[tuple[int, int]]) -> list[list[int]]:
    offsets, verts = form_chains_indexed(n, [e[0] for e in edges], [e[1] for e in edges])
    assert len(offsets) >= 1 and int(offsets[0]) == 0 and int(offsets[-1]) == len(verts)
    return as_lists(offsets, verts)


# -- reference ------------------------------------------------------------------------------


def reference_chains(n: int, edges: Sequence[tuple[int, int]]) -> list[list[int]]:
    """Obviously-correct chain formation: walk every out-edge of every junction until the next
    junction; isolated vertices are chains of one; left-over edges lie on pure rings, each walked
    from its lowest-numbered edge. Ordered by (head, first edge), isolated vertices first."""
    indeg = [0] * n
    outdeg = [0] * n
    out_edges: list[list[int]] = [[] for _ in range(n)]
    for i, (u, v) in enumerate(edges):
        outdeg[u] += 1
        indeg[v] += 1
        out_edges[u].append(i)

    def junction(v: int) -> bool:
        return indeg[v] != 1 or outdeg[v] != 1

    used = [False] * len(edges)
    keyed: list[tuple[tuple[int, int], list[int]]] = []
    for v in range(n):
        if indeg[v] == 0 and outdeg[v] == 0:
            keyed.append(((v, -1), [v]))
        if not junction(v):
            continue
        for first in out_edges[v]:
            path, e = [v], first
            while True:
                used[e] = True
                w = edges[e][1]
                path.append(w)
                if junction(w):
                    break
                (e,) = out_edges[w]
            keyed.append(((v, first), path))
    for first in range(len(edges)):
        if used[first]:
            continue
        head = edges[first][0]
        path, e = [head], first
        while not used[e]:
            used[e] = True
            w = edges[e][1]
            path.append(w)
            (e,) = out_edges[w]
        assert path[-1] == head
        keyed.append(((head, first), path))
    keyed.sort(key=lambda kc: kc[0])
    return [c for _, c in keyed]


def check_chain_properties(n: int, edges: Sequence[tuple[int, int]], chains: list[list[int]]):
    indeg = Counter(v for _, v in edges)
    outdeg = Counter(u for u, _ in edges)

    def junction(v: int) -> bool:
        return indeg[v] != 1 or outdeg[v] != 1

    # Every edge in exactly one chain (as a multiset) and consecutive vertices are edges.
    chain_edges: Counter[tuple[int, int]] = Counter()
    for c in chains:
        assert len(c) >= 1
        chain_edges.update(itertools.pairwise(c))
    assert chain_edges == Counter(edges)
    for c in chains:
        if len(c) == 1:
            (v,) = c
            # Only isolated vertices are chains of one; degree > 0 never is.
            assert indeg[v] == 0 and outdeg[v] == 0
            continue
        ring = c[0] == c[-1] and not junction(c[0])
        for v in c[1:-1]:
            assert indeg[v] == 1 and outdeg[v] == 1, (c, v)
        if ring:
            assert all(not junction(v) for v in c)
            assert len(set(c[:-1])) == len(c) - 1
        else:
            # Maximal: both ends are junctions, so the chain cannot be extended either way.
            assert junction(c[0]), (c, "head")
            assert junction(c[-1]), (c, "tail")
    # Every isolated vertex appears as a chain of one, exactly once.
    singles = Counter(c[0] for c in chains if len(c) == 1)
    isolated = [v for v in range(n) if indeg[v] == 0 and outdeg[v] == 0]
    assert singles == Counter(isolated)
    # One chain per out-edge of a junction, plus rings and isolated vertices.
    rings = sum(1 for c in chains if len(c) > 1 and c[0] == c[-1] and not junction(c[0]))
    expected = sum(outdeg[v] for v in range(n) if junction(v)) + rings + len(isolated)
    assert len(chains) == expected


# -- Fig. 2 ---------------------------------------------------------------------------------


def test_fig2_chains_and_order() -> None:
    chains = form_chains(make_app(FIG2_VERTICES, FIG2_EDGES, "fig2"))
    assert names(chains) == FIG2_CHAINS
    assert [c.index for c in chains] == list(range(5))
    assert [(c.head, c.tail) for c in chains] == [
        ("A", "D"),
        ("D", "E"),
        ("F", "G"),
        ("G", "D"),
        ("G", "I"),
    ]
    assert [len(c) for c in chains] == [4, 2, 2, 2, 3]


def test_fig2_order_follows_head_then_first_edge() -> None:
    # G's out-edges declared H first: G-H-I now comes before G-D.
    edges = [e for e in FIG2_EDGES if e != ("G", "D")] + [("G", "D")]
    chains = form_chains(make_app(FIG2_VERTICES, edges, "fig2"))
    assert names(chains) == ["A-B-C-D", "D-E", "F-G", "G-H-I", "G-D"]
    # Heads follow vertex declaration order, not alphabetical order.
    chains = form_chains(make_app("FGHIABCDE", FIG2_EDGES, "fig2"))
    assert names(chains) == ["F-G", "G-D", "G-H-I", "A-B-C-D", "D-E"]


@pytest.mark.parametrize("seed", range(8))
def test_fig2_shuffled_edges_same_set(seed: int) -> None:
    rng = random.Random(seed)
    edges = list(FIG2_EDGES)
    rng.shuffle(edges)
    verts = list(FIG2_VERTICES)
    rng.shuffle(verts)
    chains = form_chains(make_app(verts, edges, "fig2"))
    assert sorted(names(chains)) == sorted(FIG2_CHAINS)
    heads = [verts.index(c.head) for c in chains]
    assert heads == sorted(heads)


def test_fig2_dependencies_and_order() -> None:
    chains = form_chains(make_app(FIG2_VERTICES, FIG2_EDGES, "fig2"))
    # D-E waits for every chain ending at D, G-D and G-H-I wait for F-G.
    assert chain_dependencies(chains) == [[], [0, 3], [], [2], [2]]
    order = chain_order(chains)
    assert sorted(order) == list(range(5))
    pos = {c: i for i, c in enumerate(order)}
    assert pos[0] < pos[1] and pos[3] < pos[1] and pos[2] < pos[3] and pos[2] < pos[4]


# -- small shapes ---------------------------------------------------------------------------


def test_isolated_vertex_is_a_chain_of_one() -> None:
    assert names(form_chains(make_app(["X"], []))) == ["X"]
    chains = form_chains(make_app(["A", "X", "B"], [("A", "B")]))
    assert names(chains) == ["A-B", "X"]
    assert chain_order(chains) == [0, 1]
    assert indexed(3, []) == [[0], [1], [2]]
    assert indexed(4, [(2, 3)]) == [[0], [1], [2, 3]]
    assert indexed(0, []) == []


def test_single_pipeline_is_one_chain() -> None:
    chains = form_chains(make_app("PQRST", [("P", "Q"), ("Q", "R"), ("R", "S"), ("S", "T")]))
    assert names(chains) == ["P-Q-R-S-T"]
    # Declared in reverse order: still one chain, head first.
    chains = form_chains(make_app("TSRQP", [("S", "T"), ("R", "S"), ("Q", "R"), ("P", "Q")]))
    assert names(chains) == ["P-Q-R-S-T"]


def test_diamond() -> None:
    edges = [("S", "L1"), ("L1", "L2"), ("S", "R"), ("L2", "T"), ("R", "T")]
    chains = form_chains(make_app(["S", "L1", "L2", "R", "T"], edges))
    assert names(chains) == ["S-L1-L2-T", "S-R-T"]
    assert chain_dependencies(chains) == [[], []]


def test_multi_out_and_multi_in_junctions() -> None:
    # X fans out to three; Y collects three; a chain X -> M -> Y and two direct edges.
    edges = [("X", "M"), ("M", "Y"), ("X", "Y"), ("P", "Y"), ("X", "Z")]
    chains = form_chains(make_app(["X", "M", "Y", "P", "Z"], edges))
    assert sorted(names(chains)) == sorted(["X-M-Y", "X-Y", "P-Y", "X-Z"])
    assert names(chains) == ["X-M-Y", "X-Y", "X-Z", "P-Y"]
    # A vertex with one in and two outs, and one with two ins and one out, end and start chains.
    edges = [("a", "b"), ("b", "c"), ("b", "d"), ("c", "e"), ("d", "e"), ("e", "f"), ("f", "g")]
    chains = form_chains(make_app("abcdefg", edges))
    assert names(chains) == ["a-b", "b-c-e", "b-d-e", "e-f-g"]


def test_pure_ring_is_one_chain_from_its_lowest_edge() -> None:
    assert indexed(3, [(0, 1), (1, 2), (2, 0)]) == [[0, 1, 2, 0]]
    # The lowest-numbered edge is 2 -> 0: the ring starts and ends at 2.
    assert indexed(3, [(2, 0), (1, 2), (0, 1)]) == [[2, 0, 1, 2]]
    assert indexed(3, [(1, 2), (2, 0), (0, 1)]) == [[1, 2, 0, 1]]
    # A ring next to a pipeline and an isolated vertex.
    got = indexed(6, [(3, 4), (4, 3), (0, 1)])
    assert got == [[0, 1], [2], [3, 4, 3], [5]]


def test_cycle_through_a_junction_is_not_a_ring() -> None:
    # 0 -> 1 -> 2 -> 0 plus 0 -> 3: 0 is a junction and heads both chains.
    assert indexed(4, [(0, 1), (1, 2), (2, 0), (0, 3)]) == [[0, 1, 2, 0], [0, 3]]


def test_bad_indexed_input() -> None:
    with pytest.raises(ValueError):
        form_chains_indexed(2, [0, 1], [1])
    with pytest.raises(ValueError):
        form_chains_indexed(2, [0], [2])
    with pytest.raises(ValueError):
        form_chains_indexed(2, [-1], [0])


def test_long_pipeline_pointer_jumping() -> None:
    # Long chains exercise every round of list ranking.
    for n in (2, 3, 4, 5, 8, 9, 16, 17, 33, 1000):
        edges = [(i, i + 1) for i in range(n - 1)]
        perm = list(range(n - 1))
        random.Random(n).shuffle(perm)
        shuffled = [edges[i] for i in perm]
        assert indexed(n, shuffled) == [list(range(n))]


# -- random graphs against the reference ----------------------------------------------------


@st.composite
def dags(draw: st.DrawFn, max_n: int = 60) -> tuple[int, list[tuple[int, int]]]:
    n = draw(st.integers(1, max_n))
    if n == 1:
        return 1, []
    pair = st.tuples(st.integers(0, n - 2), st.integers(1, n - 1)).filter(lambda p: p[0] < p[1])
    edges = draw(st.lists(pair, max_size=2 * n))
    # Long paths make interesting chains: thread some of them in.
    if draw(st.booleans()):
        k = draw(st.integers(0, n - 1))
        edges += [(i, i + 1) for i in range(k, n - 1)]
    edges = draw(st.permutations(edges))
    return n, list(edges)


@st.composite
def digraphs(draw: st.DrawFn, max_n: int = 40) -> tuple[int, list[tuple[int, int]]]:
    """General digraphs without self loops, with some pure rings on their own vertices."""
    base = draw(st.integers(0, max_n))
    rings = draw(st.lists(st.integers(2, 6), max_size=3))
    n = base + sum(rings)
    if n == 0:
        return 0, []
    edges: list[tuple[int, int]] = []
    if base >= 2:
        pair = st.tuples(st.integers(0, base - 1), st.integers(0, base - 1)).filter(
            lambda p: p[0] != p[1]
        )
        edges += draw(st.lists(pair, max_size=2 * base))
    start = base
    for size in rings:
        edges += [(start + i, start + (i + 1) % size) for i in range(size)]
        start += size
    perm = draw(st.permutations(range(n)))
    edges = [(perm[u], perm[v]) for u, v in edges]
    return n, list(draw(st.permutations(edges)))


@settings(max_examples=150, deadline=None)
@given(dags())
def test_random_dags_match_reference(graph: tuple[int, list[tuple[int, int]]]) -> None:
    n, edges = graph
    got = indexed(n, edges)
    assert got == reference_chains(n, edges)
    check_chain_properties(n, edges, got)


@settings(max_examples=150, deadline=None)
@given(digraphs())
def test_random_digraphs_match_reference(graph: tuple[int, list[tuple[int, int]]]) -> None:
    n, edges = graph
    got = indexed(n, edges)
    assert got == reference_chains(n, edges)
    check_chain_properties(n, edges, got)


@settings(max_examples=60, deadline=None)
@given(dags(max_n=30))
def test_form_chains_on_apps_matches_indexed(graph: tuple[int, list[tuple[int, int]]]) -> None:
    n, edges = graph
    edges = sorted(set(edges), key=edges.index)  # an App has no duplicate edges
    vs = [f"v{i}" for i in range(n)]
    app = make_app(vs, [(vs[u], vs[v]) for u, v in edges]).validate()
    chains = form_chains(app)
    assert [list(c.vertices) for c in chains] == [
        [vs[i] for i in c] for c in reference_chains(n, edges)
    ]
    assert [c.index for c in chains] == list(range(len(chains)))


@settings(max_examples=80, deadline=None)
@given(dags(max_n=40))
def test_chain_order_respects_dependencies(graph: tuple[int, list[tuple[int, int]]]) -> None:
    n, edges = graph
    edges = sorted(set(edges), key=edges.index)
    vs = [f"v{i}" for i in range(n)]
    chains = form_chains(make_app(vs, [(vs[u], vs[v]) for u, v in edges]).validate())
    order = chain_order(chains)
    assert sorted(order) == list(range(len(chains)))
    pos = {ci: k for k, ci in enumerate(order)}
    deps = chain_dependencies(chains)
    for c in chains:
        leading = [o.index for o in chains if len(o) > 1 and o.tail == c.head]
        assert sorted(deps[c.index]) == sorted(leading)
        for i in leading:
            assert pos[i] < pos[c.index], (chains[i].name, c.name)
