"""Incremental routes: a network that keeps each destination's BFS tree across link changes
(dropping only the trees a change alters) answers exactly what a network built afresh from the
same links answers, and the simulator's cores end up with exactly the all-pairs routes."""

from __future__ import annotations

import itertools
import random

from hypothesis import given, settings
from hypothesis import strategies as st

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.sim.runner import Simulation


def _fresh(ids: list[str], links: set[tuple[str, str]]) -> Network:
    return Network([NodeSpec(i) for i in ids], [LinkSpec(a, b) for a, b in sorted(links)])


def _all_pairs(net: Network) -> dict[tuple[str, str], tuple[str | None, int | None]]:
    return {(s, d): (net.next_hop(s, d), net.hops(s, d)) for s in net.nodes for d in net.nodes}


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 14), steps=st.integers(1, 40))
def test_incremental_routes_equal_recomputed_routes_after_random_link_changes(
    seed: int, n: int, steps: int
) -> None:
    rng = random.Random(seed)
    ids = [f"N{i}" for i in range(n)]
    rng.shuffle(ids)  # node order (the tie-break) is not the name order
    pairs = [tuple(sorted(p)) for p in itertools.combinations(ids, 2)]
    links = {p for p in pairs if rng.random() < 0.3}
    net = _fresh(ids, links)
    _all_pairs(net)  # every tree computed, so every change meets cached trees
    for _ in range(steps):
        for _ in range(rng.randint(1, 3)):  # a few changes between two questions
            a, b = rng.choice(pairs)
            if (a, b) in links:
                links.discard((a, b))
                net.remove_link(b, a)
            else:
                links.add((a, b))
                net.add_link(LinkSpec(b, a))
        assert _all_pairs(net) == _all_pairs(_fresh(ids, links))
        for s, d in rng.sample(pairs, min(3, len(pairs))):
            assert net.route(s, d) == _fresh(ids, links).route(s, d)


def test_a_link_change_drops_only_the_trees_it_changes() -> None:
    ids = [f"N{i}" for i in range(1, 6)]  # a line N1 - N2 - N3 - N4 - N5
    net = _fresh(ids, {(ids[i], ids[i + 1]) for i in range(4)})
    _all_pairs(net)
    net.take_changed()
    net.add_link(LinkSpec("N1", "N3"))  # a shortcut: N1's and N3's trees change, and more
    changed = net.take_changed()
    assert {"N1", "N3"} <= changed
    net.add_link(LinkSpec("N1", "N3", delay_ms=5.0))  # attributes only: no tree changes
    assert net.take_changed() == set()
    _all_pairs(net)
    net.remove_link("N1", "N2")  # an edge of N1's and N2's trees only (the others go via N3)
    assert net.take_changed() == {"N1", "N2"}


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_simulated_cores_hold_the_all_pairs_routes_after_link_changes(seed: int) -> None:
    rng = random.Random(seed)
    ids = [f"N{i}" for i in range(1, 9)]
    pairs = list(itertools.combinations(ids, 2))
    links = {(ids[i], ids[i + 1]) for i in range(len(ids) - 1)}
    sim = Simulation(_fresh(ids, links), manage=False, wire=False)
    for _ in range(12):
        a, b = rng.choice(pairs)
        if (a, b) in links:
            links.discard((a, b))
            sim.network.remove_link(a, b)
        else:
            links.add((a, b))
            sim.network.add_link(LinkSpec(a, b))
        sim.links_changed()
        fresh = _fresh(ids, links)
        for n, core in sim.cores.items():
            want = {}
            for d in ids:
                hop, hops = fresh.next_hop(n, d), fresh.hops(n, d)
                if d != n and hop is not None and hops is not None:
                    want[d] = (hop, hops)
            assert core.routes == want
