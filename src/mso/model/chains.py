"""Chain formation (paper §3.2): cut the flow graph into maximal single-entry, single-exit paths.

A vertex is a *junction* unless it has exactly one incoming and one outgoing edge. Every chain
starts at a junction (its head), runs through non-junction vertices and stops at the next
junction (its tail), so every edge lies in exactly one chain and a junction such as D or G in
Fig. 2 ends the chains coming in and heads the chains going out. An isolated vertex is a chain of
one. A ring made only of non-junction vertices (impossible in a DAG) becomes one chain that starts
and ends at its lowest-numbered edge's source.

The work is in numpy: list ranking by pointer jumping (O(|E| log L) for the longest chain L),
then a linear layout (a 16-bit radix sort of the chains, one scatter of the edges), which forms
a 1M-vertex graph's chains in about a tenth of a second; see ``bench/chains.py``.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mso.model.app import App
from mso.model.graph import topological_order

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class Chain:
    """A chain of vertices, head first. ``index`` is its position in formation order."""

    index: int
    vertices: tuple[str, ...]

    @property
    def head(self) -> str:
        return self.vertices[0]

    @property
    def tail(self) -> str:
        return self.vertices[-1]

    @property
    def name(self) -> str:
        return "-".join(self.vertices)

    def __len__(self) -> int:
        return len(self.vertices)


def _stable_order(keys: npt.NDArray[np.integer]) -> IntArray:
    """A stable argsort of non-negative integer keys in linear time: numpy's stable sort is a
    radix sort for 16-bit keys, so sort by the low 16 bits, then stably by the high 16."""
    top = int(keys.max()) if len(keys) else 0
    if top < 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind="stable").astype(np.int64)
    if top >= 1 << 32:
        return np.argsort(keys, kind="stable").astype(np.int64)
    low = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((keys[low] >> 16).astype(np.uint16), kind="stable")].astype(np.int64)


def form_chains_indexed(
    n: int, src: Sequence[int] | IntArray, dst: Sequence[int] | IntArray
) -> tuple[IntArray, IntArray]:
    """Chains of a graph with vertices ``0..n-1`` and edges ``src[i] -> dst[i]``.

    Returns ``(offsets, vertices)``: chain ``c`` is ``vertices[offsets[c]:offsets[c+1]]``,
    head first. Chains are ordered by head vertex, then by the index of their first edge;
    isolated vertices come before the edge chains that share their index (they have none).
    """
    m = len(src)
    if len(dst) != m:
        raise ValueError("src and dst must have the same length")
    # int64 throughout: numpy converts narrower index arrays to intp on every gather
    it = np.int64
    s = np.asarray(src, dtype=it)
    d = np.asarray(dst, dtype=it)
    if m and (s.min() < 0 or d.min() < 0 or s.max() >= n or d.max() >= n):
        raise ValueError("edge endpoint out of range")
    indeg = np.bincount(d, minlength=n)
    outdeg = np.bincount(s, minlength=n)
    junction = (indeg != 1) | (outdeg != 1)
    edge_ids = np.arange(m, dtype=it)

    # prv[e]: the edge before e in its chain (e itself when e leaves a junction).
    in_edge = np.full(n, -1, dtype=it)
    in_edge[d] = edge_ids
    prv = np.where(junction[s], edge_ids, in_edge[s])
    dist = (prv != edge_ids).astype(it)
    # List ranking by pointer jumping: after k rounds prv points 2^k edges back (or at the head).
    # Rounds run over every edge while many still move, then only over those still moving
    # (most edges of a graph with short chains are done after a round or two).
    active: IntArray | None = None
    for _ in range(max(1, int(m).bit_length() + 1)):
        if active is None:
            nxt = prv[prv]
            moving = nxt != prv
            n_moving = int(np.count_nonzero(moving))
            if n_moving == 0:
                break
            if n_moving * 4 >= m:
                dist = dist + dist[prv]
                prv = nxt
                continue
            active = np.flatnonzero(moving)
        if len(active) == 0:
            break
        p = prv[active]
        dist[active] += dist[p]
        prv[active] = prv[p]
        p = prv[active]
        active = active[prv[p] != p]
    root = prv

    # Rings of non-junction vertices never reach a head: walk them in Python (rare, tiny).
    ring = ~junction[s[root]] if m else np.zeros(0, dtype=bool)
    if ring.any():
        out_edge = np.full(n, -1, dtype=np.int64)
        out_edge[s] = edge_ids
        done: set[int] = set()
        for e0 in sorted(int(e) for e in np.flatnonzero(ring)):
            if e0 in done:
                continue
            e, k = e0, 0
            while e not in done:
                done.add(e)
                root[e], dist[e] = e0, k
                k += 1
                e = int(out_edge[d[e]])

    # Lay the chains out by head vertex, then first edge (isolated vertices have no edges,
    # so they never tie), with a linear sort of the chains and one scatter of the edges.
    firsts = np.flatnonzero(root == edge_ids)  # each chain's first edge, in edge order
    isolated = np.flatnonzero((indeg == 0) & (outdeg == 0))
    k_iso = len(isolated)
    order = _stable_order(np.concatenate([isolated, s[firsts]]))
    lengths = np.concatenate(
        [np.ones(k_iso, dtype=np.int64), np.bincount(root, minlength=m)[firsts] + 1]
    )
    offsets = np.zeros(len(order) + 1, dtype=np.int64)
    np.cumsum(lengths[order], out=offsets[1:])
    start = np.empty(len(order), dtype=np.int64)
    start[order] = offsets[:-1]
    verts = np.empty(int(offsets[-1]), dtype=it)
    verts[start[:k_iso]] = isolated
    verts[start[k_iso:]] = s[firsts]
    chain_start = np.empty(m, dtype=np.int64)  # at each chain's first edge: where it begins
    chain_start[firsts] = start[k_iso:]
    verts[chain_start[root] + dist + 1] = d
    return offsets, verts


def form_chains(app: App) -> list[Chain]:
    """Partition ``app`` into chains, in a deterministic order (by head, then first edge)."""
    names = list(app.vertices)
    index = {v: i for i, v in enumerate(names)}
    src = [index[e.src] for e in app.edges]
    dst = [index[e.dst] for e in app.edges]
    offsets, verts = form_chains_indexed(len(names), src, dst)
    flat = [names[i] for i in verts.tolist()]
    bounds = offsets.tolist()
    return [Chain(c, tuple(flat[a:b])) for c, (a, b) in enumerate(itertools.pairwise(bounds))]


def chain_dependencies(chains: Sequence[Chain]) -> list[list[int]]:
    """For each chain, the chains leading to it: those whose tail is its head."""
    ending_at: dict[str, list[int]] = {}
    for c in chains:
        verts = c.vertices  # (not the properties: this runs per chain of the largest apps)
        if len(verts) > 1:
            ending_at.setdefault(verts[-1], []).append(c.index)
    none: list[int] = []
    return [[i for i in ending_at.get(c.vertices[0], none) if i != c.index] for c in chains]


def chain_order(
    chains: Sequence[Chain], dependencies: Sequence[Sequence[int]] | None = None
) -> list[int]:
    """Chain indices in dependency order (Algorithm 1): a chain only after all leading to it.
    ``dependencies``: :func:`chain_dependencies` of ``chains``, if the caller has them."""
    leading = chain_dependencies(chains) if dependencies is None else dependencies
    followers: dict[int, list[int]] = {c.index: [] for c in chains}
    for c, before in zip(chains, leading, strict=True):
        for i in before:
            followers[i].append(c.index)
    order = topological_order([c.index for c in chains], followers)
    if len(order) != len(chains):
        raise ValueError("chains depend on each other in a cycle; the app graph must be a DAG")
    return order
