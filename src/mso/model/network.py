"""The resource graph: nodes with capacities and an energy model, links, shortest-path routes.

Pure data and graph queries; the scenario loader (``mso.scenario``) builds it from YAML, and the
emulator and simulator change its links as nodes move.
"""

from __future__ import annotations

import math
from array import array
from bisect import insort
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol


@dataclass(frozen=True)
class PowerModel:
    """Energy model of a node (docs/architecture.md, "Energy model").

    Power drawn = ``idle_w`` always + ``cpu_w`` while a vertex computes; each byte sent costs
    ``tx_uj_per_byte`` µJ and each byte received ``rx_uj_per_byte`` µJ. ``cpu_energy`` says
    what "while a vertex computes" means: ``modelled`` — the vertices' declared costs (c ms per
    event at cpu 1.0), so stand-in code drains the robot that would do the work — or
    ``measured`` — the CPU time the vertex code really took here, divided by the node's cpu.
    """

    idle_w: float = 1.0
    cpu_w: float = 4.0
    tx_uj_per_byte: float = 2.0
    rx_uj_per_byte: float = 1.0
    cpu_energy: str = "modelled"


@dataclass(frozen=True)
class NodeSpec:
    """A device: relative CPU speed (1.0 = reference), battery (Wh, None = wall power)."""

    id: str
    cpu: float = 1.0
    battery_wh: float | None = None
    power: PowerModel = field(default_factory=PowerModel)
    pos: tuple[float, float] | None = None
    # labels and amounts it offers (mso.model.capabilities): camera, gpu, mem_mb, ...
    capabilities: dict[str, float] = field(default_factory=dict, hash=False)


@dataclass(frozen=True)
class LinkSpec:
    """A bidirectional radio link; None bandwidth means unshaped."""

    a: str
    b: str
    bandwidth_mbps: float | None = None
    delay_ms: float = 0.0
    loss: float = 0.0


def _key(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


class _Tree:
    """A destination's BFS tree over node indices: each node's parent toward the destination
    (-1: unreachable; the destination is its own parent), its distance in hops and its rank
    in the search's visiting order (what decides ties). Arrays, so 1,000 trees of 1,000
    nodes take 12 MB, not the 300 MB of dicts."""

    __slots__ = ("dist", "parent", "rank")

    def __init__(self, size: int) -> None:
        self.parent = array("i", [-1]) * size
        self.dist = array("i", [-1]) * size
        self.rank = array("i", [-1]) * size


class Network:
    """Nodes and links; routes are hop-count shortest paths, ties broken by node order.

    Each destination's BFS tree is computed when first asked for and kept until a link change
    can alter it: removing a link invalidates only the trees it is an edge of, adding one only
    the trees in which one end would be found earlier through it (see :meth:`_invalidate`).
    So a link change costs O(N) checks plus a BFS per tree it really changes, not N BFS, and
    :meth:`take_changed` tells a simulator which destinations' routes to look at again."""

    def __init__(self, nodes: list[NodeSpec], links: list[LinkSpec] | None = None) -> None:
        self.nodes: dict[str, NodeSpec] = {}
        for n in nodes:
            if n.id in self.nodes:
                raise ValueError(f"duplicate node id {n.id!r}")
            self.nodes[n.id] = n
        self._ids = list(self.nodes)
        self._order = {n: i for i, n in enumerate(self.nodes)}
        self.links: dict[tuple[str, str], LinkSpec] = {}
        self._adj: dict[str, list[str]] = {n: [] for n in self.nodes}
        self._nbrs: list[list[int]] = [[] for _ in self.nodes]  # by index, in node order
        self._trees: dict[int, _Tree] = {}
        self._changed: set[str] = set()  # destinations whose trees went since take_changed
        self.version = 0  # counts link changes (attributes too): what a cache of paths keys on
        for link in links or []:
            self.add_link(link)

    # -- topology changes (the emulator and simulator call these) -------------------------
    def add_link(self, link: LinkSpec) -> None:
        for end in (link.a, link.b):
            if end not in self.nodes:
                raise ValueError(f"link {link.a}-{link.b} names unknown node {end!r}")
        if link.a == link.b:
            raise ValueError(f"link {link.a}-{link.b} joins a node to itself")
        k = _key(link.a, link.b)
        self.version += 1
        if k not in self.links:
            a, b = self._order[link.a], self._order[link.b]
            self._invalidate(a, b, added=True)
            self._adj[link.a].append(link.b)
            self._adj[link.b].append(link.a)
            for end in (link.a, link.b):
                self._adj[end].sort(key=self._order.__getitem__)
            insort(self._nbrs[a], b)
            insort(self._nbrs[b], a)
        self.links[k] = link

    def remove_link(self, a: str, b: str) -> None:
        if self.links.pop(_key(a, b), None) is not None:
            self.version += 1
            self._adj[a].remove(b)
            self._adj[b].remove(a)
            i, j = self._order[a], self._order[b]
            self._nbrs[i].remove(j)
            self._nbrs[j].remove(i)
            self._invalidate(i, j, added=False)

    def _invalidate(self, a: int, b: int, *, added: bool) -> None:
        """Drop the trees the link a-b changes. Removed: only a tree that has it as an edge
        (otherwise the search never used it). Added: only a tree in which the search, at one
        end ``u``, would find the other ``w`` not yet seen: ``w`` unreachable or further
        than one hop beyond ``u``, or exactly one beyond but first seen from a node visited
        after ``u`` (the tie goes to the first visited)."""
        gone = []
        for dst, t in self._trees.items():
            p, d, r = t.parent, t.dist, t.rank
            if not added:
                hit = p[a] == b or p[b] == a
            else:
                hit = False
                for u, w in ((a, b), (b, a)):
                    du, dw = d[u], d[w]
                    if du < 0:
                        continue
                    if dw < 0 or dw > du + 1 or (dw == du + 1 and r[u] < r[p[w]]):
                        hit = True
                        break
            if hit:
                gone.append(dst)
        for dst in gone:
            del self._trees[dst]
            self._changed.add(self._ids[dst])

    def take_changed(self) -> set[str]:
        """The destinations whose routes may have changed since the last call (their trees
        were dropped), and forget them."""
        out, self._changed = self._changed, set()
        return out

    # -- queries ----------------------------------------------------------------------------
    def link(self, a: str, b: str) -> LinkSpec | None:
        return self.links.get(_key(a, b))

    def neighbours(self, node: str) -> list[str]:
        return list(self._adj[node])

    def _tree(self, dst: int) -> _Tree:
        tree = self._trees.get(dst)
        if tree is None:
            tree = _Tree(len(self._ids))
            parent, dist, rank, nbrs = tree.parent, tree.dist, tree.rank, self._nbrs
            parent[dst], dist[dst] = dst, 0
            queue = [dst]
            for i, u in enumerate(queue):  # the list grows as the search goes: a queue
                rank[u] = i
                du = dist[u] + 1
                for w in nbrs[u]:
                    if dist[w] < 0:
                        parent[w], dist[w] = u, du
                        queue.append(w)
            self._trees[dst] = tree
        return tree

    def route(self, src: str, dst: str) -> list[str] | None:
        """Nodes from ``src`` to ``dst`` inclusive, or None when unreachable (or unknown)."""
        s, d = self._order.get(src), self._order.get(dst)
        if s is None or d is None:
            return None
        parent = self._tree(d).parent  # walk from src toward dst: next hops are parents
        if parent[s] < 0:
            return None
        path = [s]
        while path[-1] != d:
            path.append(parent[path[-1]])
        return [self._ids[i] for i in path]

    def next_hop(self, src: str, dst: str) -> str | None:
        """The neighbour of ``src`` on the route to ``dst`` (what a routing table answers)."""
        if src == dst:
            return src
        s, d = self._order.get(src), self._order.get(dst)
        if s is None or d is None:
            return None
        p = self._tree(d).parent[s]
        return self._ids[p] if p >= 0 else None

    def hops(self, src: str, dst: str) -> int | None:
        s, d = self._order.get(src), self._order.get(dst)
        if s is None or d is None:
            return None
        h = self._tree(d).dist[s]
        return h if h >= 0 else None

    def routes_to(self, dst: str) -> dict[str, tuple[str, int]]:
        """Every node's route to ``dst``: (next hop, hops), for the nodes that reach it."""
        d = self._order[dst]
        t, ids = self._tree(d), self._ids
        return {ids[s]: (ids[p], t.dist[s]) for s, p in enumerate(t.parent) if p >= 0 and s != d}

    def distances(self, src: str) -> dict[str, int]:
        """Hop distance from ``src`` to every reachable node."""
        dist = {src: 0}
        queue = deque([src])
        while queue:
            u = queue.popleft()
            for w in self._adj[u]:
                if w not in dist:
                    dist[w] = dist[u] + 1
                    queue.append(w)
        return dist

    def relink(
        self,
        positions: dict[str, tuple[float, float]],
        radio_range: float,
        template: LinkSpec | None = None,
    ) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
        """Make the links those of nodes within ``radio_range``; returns (added, removed)."""
        want = {_key(a, b) for a, b in self.pairs_within(positions, radio_range)}
        removed = [k for k in self.links if k not in want]
        added = [k for k in sorted(want) if k not in self.links]
        for a, b in removed:
            self.remove_link(a, b)
        t = template or LinkSpec("", "")
        for a, b in added:
            self.add_link(LinkSpec(a, b, t.bandwidth_mbps, t.delay_ms, t.loss))
        return added, removed

    def links_from_positions(
        self,
        radio_range: float,
        template: LinkSpec | None = None,
        propagation: LinkModel | None = None,
    ) -> None:
        """Replace the links with one per pair of nodes within ``radio_range`` of each other
        (shaped by ``propagation``, which may also leave a pair unlinked, when given)."""
        for a, b in list(self.links):
            self.remove_link(a, b)
        positions = {n: s.pos for n, s in self.nodes.items() if s.pos is not None}
        for a, b in self.pairs_within(positions, radio_range):
            t = template or LinkSpec(a, b)
            if propagation is None:
                self.add_link(LinkSpec(a, b, t.bandwidth_mbps, t.delay_ms, t.loss))
                continue
            spec = propagation.link(a, b, math.dist(positions[a], positions[b]), t)
            if spec is not None:
                self.add_link(spec)

    def pairs_within(
        self, positions: dict[str, tuple[float, float]], radio_range: float
    ) -> list[tuple[str, str]]:
        """The pairs of nodes (in node order, the earlier first) at most ``radio_range``
        apart. Nodes are bucketed in cells one range wide, so only neighbouring cells are
        compared: O(N × degree), not the O(N²) of every pair (0.3 s per mobility step at
        1,000 nodes)."""
        order = self._order
        return pairs_within(
            {order[n]: p for n, p in positions.items() if n in order}, radio_range, self._ids
        )


class LinkModel(Protocol):
    """What shapes a link from its length (:class:`mso.model.propagation.Propagation`)."""

    def link(
        self, a: str, b: str, distance_m: float, template: LinkSpec | None = None
    ) -> LinkSpec | None: ...


def pairs_within(
    points: dict[int, tuple[float, float]], radio_range: float, ids: list[str]
) -> list[tuple[str, str]]:
    """The pairs ``(ids[i], ids[j])``, i < j, of points at most ``radio_range`` apart, sorted
    by (i, j); a grid of cells ``radio_range`` wide keeps it linear in the points."""
    if radio_range <= 0 or not math.isfinite(radio_range):
        return []
    cells: dict[tuple[int, int], list[int]] = {}
    for i, (x, y) in points.items():
        cells.setdefault((math.floor(x / radio_range), math.floor(y / radio_range)), []).append(i)
    r2 = radio_range * radio_range
    found: list[tuple[int, int]] = []
    for (cx, cy), members in cells.items():
        near = [
            j for dx in (-1, 0, 1) for dy in (-1, 0, 1) for j in cells.get((cx + dx, cy + dy), ())
        ]
        for i in members:
            xi, yi = points[i]
            for j in near:
                if j > i:
                    xj, yj = points[j]
                    if (xi - xj) ** 2 + (yi - yj) ** 2 <= r2:
                        found.append((i, j))
    found.sort()
    return [(ids[i], ids[j]) for i, j in found]
