"""Documents cost what their size says (issue 27, Build 5); the figures: bench/documents.py.

A 4 MiB document of tiny scalars took 21 s and 1 GB to validate (two million YAML nodes, each
walked in Python with its path); now it is refused once it has more nodes than the largest app
the limits allow needs, counted on the event stream before anything is built. Planning the
largest app walked the graph from every chain's tail and summed over every chain (minutes);
now what lies downstream is summarised once per plan (:mod:`mso.planning.reach`): checked here
against that walk.
"""

from __future__ import annotations

import random

import pytest

from mso.errors import SpecError
from mso.model.app import App
from mso.model.appfile import loads_app
from mso.model.chains import form_chains
from mso.model.yamlfile import MAX_NODES, load_yaml
from mso.planning.reach import Downstream


@pytest.mark.parametrize(
    "body",
    [
        "x: [" + "0," * MAX_NODES + "0]\n",  # a flow sequence
        "x:\n" + "- 0\n" * (MAX_NODES + 1),  # a block sequence
        "x: {" + ",".join(f"k{i}: 0" for i in range(MAX_NODES // 2 + 1)) + "}\n",
    ],
    ids=["flow", "block", "map"],
)
def test_a_document_of_more_nodes_than_the_largest_app_needs_is_refused(body: str) -> None:
    text = "name: big\nvertices:\n  A: {}\n" + body
    with pytest.raises(SpecError, match=f"more than {MAX_NODES:,} nodes") as err:
        load_yaml(text)
    assert err.value.line is not None  # where counting stopped: the rest was never parsed


def test_the_largest_app_the_limits_allow_fits_the_node_limit() -> None:
    lines = ["name: biggest", "vertices:"]
    lines += [f"  v{i}: {{cost: 1.5, pinned: N1}}" for i in range(5000)]
    lines += ["edges:"]
    pairs = [(i, i + d) for d in range(1, 5) for i in range(5000 - d)]  # 19,990 edges
    lines += [f"  - {{from: v{a}, to: v{b}, size: 100}}" for a, b in pairs]
    app = loads_app("\n".join(lines) + "\n", resolve_code=False)
    assert len(app.vertices) == 5000 and len(app.edges) == 19990


def walk(succ: dict[str, list[str]], start: str) -> set[str]:
    seen, stack = {start}, [start]
    while stack:
        for w in succ[stack.pop()]:
            if w not in seen:
                seen.add(w)
                stack.append(w)
    return seen


@pytest.mark.parametrize("seed", range(40))
def test_what_lies_downstream_matches_a_walk_from_every_chain(seed: int) -> None:
    rng = random.Random(seed)
    n = rng.randint(2, 60)
    app = App("dag")
    nodes = [f"N{i}" for i in range(rng.randint(1, 6))]
    for i in range(n):
        pin = rng.choice(nodes) if rng.random() < 0.3 else None
        app.vertex(f"v{i}", cost=rng.choice([0.5, 1.0, 2.5, 4.0]), pinned=pin)
    edges = {(i, i + 1) for i in range(n - 1)}
    for _ in range(rng.randint(0, 2 * n)):
        a = rng.randrange(n - 1)
        edges.add((a, rng.randrange(a + 1, min(n, a + 8))))
    for a, b in sorted(edges):
        app.edge(f"v{a}", f"v{b}")
    succ, pred = app.successors(), app.predecessors()
    order = {v: i for i, v in enumerate(app.vertices)}
    pinned = {v.id: v.pinned for v in app.vertices.values() if v.pinned is not None}
    chains = form_chains(app)
    cost = {v.id: float(v.cost) for v in app.vertices.values()}
    down = Downstream(app.topological_order(), succ, pred, pinned, order, chains, cost)
    for c in chains:
        below = walk(succ, c.tail)
        distances = {node: rng.randint(0, 3) for node in nodes if rng.random() < 0.8}
        candidates = [v for v in below if v in pinned and pinned[v] in distances]
        want = max(candidates, key=lambda v: (distances[pinned[v]], -order[v]), default=None)
        assert down.furthest_pinned(c.tail, distances) == want
        if want is None:
            continue
        above = walk(pred, want)
        between = sum(
            sum(cost[v] for v in o.vertices)
            for o in chains
            if o.index != c.index and o.head in below and o.tail in above and len(o) > 1
        )
        assert down.cost_between(c.tail, want, c.index) == pytest.approx(between)
