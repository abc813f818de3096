"""The resource graph: nodes with capacities and an energy model, links, shortest-path routes.

Pure data and graph queries; the scenario loader (``mso.scenario``) builds it from YAML, and the
emulator and simulator change its links as nodes move.
"""

from __future__ import annotations

import math
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


class Network:
    """Nodes and links; routes are hop-count shortest paths, ties broken by node order."""

    def __init__(self, nodes: list[NodeSpec], links: list[LinkSpec] | None = None) -> None:
        self.nodes: dict[str, NodeSpec] = {}
        for n in nodes:
            if n.id in self.nodes:
                raise ValueError(f"duplicate node id {n.id!r}")
            self.nodes[n.id] = n
        self._order = {n: i for i, n in enumerate(self.nodes)}
        self.links: dict[tuple[str, str], LinkSpec] = {}
        self._adj: dict[str, list[str]] = {n: [] for n in self.nodes}
        self._bfs: dict[str, dict[str, str | None]] = {}
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
        if k not in self.links:
            self._adj[link.a].append(link.b)
            self._adj[link.b].append(link.a)
            for end in (link.a, link.b):
                self._adj[end].sort(key=self._order.__getitem__)
        self.links[k] = link
        self._bfs.clear()

    def remove_link(self, a: str, b: str) -> None:
        if self.links.pop(_key(a, b), None) is not None:
            self._adj[a].remove(b)
            self._adj[b].remove(a)
            self._bfs.clear()

    # -- queries ----------------------------------------------------------------------------
    def link(self, a: str, b: str) -> LinkSpec | None:
        return self.links.get(_key(a, b))

    def neighbours(self, node: str) -> list[str]:
        return list(self._adj[node])

    def _tree(self, src: str) -> dict[str, str | None]:
        tree = self._bfs.get(src)
        if tree is None:
            tree = {src: None}
            queue = deque([src])
            while queue:
                u = queue.popleft()
                for w in self._adj[u]:
                    if w not in tree:
                        tree[w] = u
                        queue.append(w)
            self._bfs[src] = tree
        return tree

    def route(self, src: str, dst: str) -> list[str] | None:
        """Nodes from ``src`` to ``dst`` inclusive, or None when unreachable (or unknown)."""
        if dst not in self._adj:
            return None
        tree = self._tree(dst)  # walk from src toward dst: next hops are parents in dst's tree
        if src not in tree:
            return None
        path = [src]
        while path[-1] != dst:
            parent = tree[path[-1]]
            assert parent is not None
            path.append(parent)
        return path

    def next_hop(self, src: str, dst: str) -> str | None:
        """The neighbour of ``src`` on the route to ``dst`` (what a routing table answers)."""
        if src == dst:
            return src
        return self._tree(dst).get(src)

    def hops(self, src: str, dst: str) -> int | None:
        r = self.route(src, dst)
        return None if r is None else len(r) - 1

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
        ids = list(self.nodes)
        want = set()
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                near = a in positions and b in positions
                if near and math.dist(positions[a], positions[b]) <= radio_range:
                    want.add(_key(a, b))
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
        ids = list(self.nodes)
        for i, a in enumerate(ids):
            pa = self.nodes[a].pos
            for b in ids[i + 1 :]:
                pb = self.nodes[b].pos
                if pa is None or pb is None or math.dist(pa, pb) > radio_range:
                    continue
                t = template or LinkSpec(a, b)
                if propagation is None:
                    self.add_link(LinkSpec(a, b, t.bandwidth_mbps, t.delay_ms, t.loss))
                elif (spec := propagation.link(a, b, math.dist(pa, pb), t)) is not None:
                    self.add_link(spec)


class LinkModel(Protocol):
    """What shapes a link from its length (:class:`mso.model.propagation.Propagation`)."""

    def link(
        self, a: str, b: str, distance_m: float, template: LinkSpec | None = None
    ) -> LinkSpec | None: ...
