"""What lies downstream of a vertex, summarised once per plan so that each chain's target costs
what its answer holds, not the app's size.

Algorithm 1 asks, for every chain, for the furthest pinned vertex downstream of its tail and
(the paper's split) the cost of the chains between its tail and that vertex. Walking the
graph from each chain's tail and summing over every chain made that O(chains x (vertices +
edges + chains)): the largest app the limits allow (5,000 vertices, 20,000 edges) took minutes
to plan. Here, in one pass each way over a topological order, every vertex gets the set of
pinned vertices it reaches and of the chains that start below it (as bit sets, Python ints),
and every vertex the set of chains that end above it; a chain's cost between two vertices is
then one AND and a weighted count.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from mso.model.chains import Chain


class Downstream:
    """Reachability bit sets over an acyclic app, computed once."""

    def __init__(
        self,
        topo: Sequence[str],
        succ: Mapping[str, Sequence[str]],
        pred: Mapping[str, Sequence[str]],
        pinned: Mapping[str, str],
        order: Mapping[str, int],
        chains: Sequence[Chain],
        cost: Mapping[str, float],
    ) -> None:
        """``pinned``: vertex -> node; ``order``: each vertex's place in the app, the
        tie-break between pinned vertices on equally far nodes (the first wins)."""
        self.pinned = sorted(pinned, key=order.__getitem__)  # bit i: pinned[i]
        bit = self._bit = {v: 1 << i for i, v in enumerate(self.pinned)}
        self._on: dict[str, int] = {}  # node -> its pinned vertices' bits
        for v, node in pinned.items():
            self._on[node] = self._on.get(node, 0) | bit[v]
        self._pinned_below: dict[str, int] = {}
        for v in reversed(topo):
            p = bit.get(v, 0)
            for w in succ[v]:
                p |= self._pinned_below[w]
            self._pinned_below[v] = p
        self._topo, self._succ, self._pred = topo, succ, pred
        self._chains, self._costs = chains, cost
        # the chains' sets (the paper's split only): _chain_sets
        self._cost: npt.NDArray[np.float64] | None = None

    def _chain_sets(self) -> npt.NDArray[np.float64]:
        """Which chains lie below and above each vertex, and each chain's cost, made when the
        paper's split first asks (the bytes split never does)."""
        if self._cost is not None:
            return self._cost
        chains, topo = self._chains, self._topo
        heads: dict[str, int] = {}
        tails: dict[str, int] = {}
        for c in chains:
            if len(c) > 1:  # (one-vertex chains carry no cost between)
                heads[c.head] = heads.get(c.head, 0) | 1 << c.index
                tails[c.tail] = tails.get(c.tail, 0) | 1 << c.index
        self._chains_below: dict[str, int] = {}  # chains whose head is reachable from v
        for v in reversed(topo):
            h = heads.get(v, 0)
            for w in self._succ[v]:
                h |= self._chains_below[w]
            self._chains_below[v] = h
        self._chains_above: dict[str, int] = {}  # chains whose tail reaches v
        for v in topo:
            t = tails.get(v, 0)
            for u in self._pred[v]:
                t |= self._chains_above[u]
            self._chains_above[v] = t
        cost = np.zeros(max(8, -(-len(chains) // 8) * 8))
        costs = self._costs
        for c in chains:
            total = 0.0  # (sum()'s order: the same float)
            for v in c.vertices:
                total += costs[v]
            cost[c.index] = total
        self._cost = cost
        return cost

    def furthest_pinned(
        self, v: str, distances: Mapping[str, int], leave_out: Sequence[str] = ()
    ) -> str | None:
        """The pinned vertex ``v`` reaches (itself included) whose node is furthest by
        ``distances`` (nodes it lacks do not count), the first in the app's order among
        those on equally far nodes; never one of ``leave_out``."""
        below = self._pinned_below[v]
        for u in leave_out:
            below &= ~self._bit.get(u, 0)
        far, bits = -1, 0  # the furthest distance yet, and the pinned vertices there
        for node, on in self._on.items():
            hit = below & on
            if hit:
                d = distances.get(node)
                if d is None or d < far:
                    continue
                if d > far:
                    far, bits = d, hit
                else:
                    bits |= hit
        if not bits:
            return None
        return self.pinned[(bits & -bits).bit_length() - 1]

    def cost_between(self, start: str, target: str, leave_out: int) -> float:
        """The cost of the chains (of two or more vertices) whose head ``start`` reaches and
        whose tail reaches ``target``, but chain ``leave_out``."""
        costs = self._chain_sets()
        bits = self._chains_below[start] & self._chains_above[target] & ~(1 << leave_out)
        if not bits:
            return 0.0
        raw = np.frombuffer(bits.to_bytes(len(costs) // 8, "little"), dtype=np.uint8)
        mask = np.unpackbits(raw, bitorder="little").view(np.bool_)
        return float(costs[mask].sum())
