"""Placement along a probed route (paper §3.3, Algorithm 1). Pure: no I/O, no clock.

For each chain, in dependency order:

1. Its head is already placed (pinned, placed as the tail of an earlier chain, or an unpinned
   source put on the ``origin`` node). Vertices already placed inside the chain (pinned ones, or a
   merge vertex an earlier chain ended at) are *anchors*; between two anchors the chain follows
   the route from one anchor's node to the next.
2. After the last anchor, a probe explores the route toward the furthest pinned vertex
   downstream (normally a sink), collecting each hop's capacity.
3. The chain is given the shortest prefix of that route whose share of the route's capacity
   reaches the chain's share of cost: ``cost(chain) / (cost(chain) + cost(chains after it on the
   way to that sink))`` — the paper's cost fraction.
4. Vertices are laid along the allocated nodes in chain order, each node taking a slice of the
   chain's cost proportional to its capacity; a vertex goes to the node its cost midpoint falls
   in, so a chain never goes back along its route.

:func:`place_chain` is the step the head's node runs in a distributed deployment with the hops a
real probe collected; :func:`plan` runs all chains centrally for ``mso plan`` and simulations.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

from mso.errors import PlanningError
from mso.model.app import PLANNERS, App
from mso.model.capabilities import Candidate, offered, resolve
from mso.model.chains import Chain, chain_dependencies, chain_order, form_chains
from mso.model.gcpause import paused_gc
from mso.model.network import Network
from mso.planning.bytesplit import Hop as Hop  # re-exported: what a probe collects
from mso.planning.bytesplit import Traffic, assign_bytes, carries, carry_prefix, compute_uj
from mso.planning.objectives import edge_bytes
from mso.planning.objectives import vertex_rates as vertex_rates
from mso.planning.probes import Capacity as Capacity
from mso.planning.probes import Probe as Probe
from mso.planning.probes import cpu_capacity as cpu_capacity
from mso.planning.probes import network_probe as network_probe
from mso.planning.probes import probed_hops as probed_hops
from mso.planning.reach import Downstream

DEFAULT_PLANNER = "bytes"


@dataclass
class Plan:
    """A placement with the chains, the order they were placed in, and each chain's probe."""

    placement: dict[str, str]
    chains: list[Chain]
    order: list[int]
    routes: dict[int, list[str]] = field(default_factory=dict)
    planner: str = DEFAULT_PLANNER  # how chains were split along their routes
    # each vertex placed by capability: the nodes that qualify, best first (it is on the first)
    capable: dict[str, list[str]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "placement": dict(self.placement),
            "capable": {v: list(ns) for v, ns in self.capable.items()},
            "chains": [list(c.vertices) for c in self.chains],
            "order": list(self.order),
            "routes": [self.routes.get(c.index, []) for c in self.chains],
        }


def allocate_prefix(capacities: Sequence[float], fraction: float) -> int:
    """How many route nodes (from the start) a chain gets: the fewest whose capacity share
    reaches ``fraction``; at least one."""
    if not capacities:
        raise ValueError("a route has at least one node")
    total = sum(capacities)
    if total <= 0:
        capacities, total = [1.0] * len(capacities), float(len(capacities))
    acc = 0.0
    for k, c in enumerate(capacities, start=1):
        acc += c
        if acc / total >= fraction - 1e-9:
            return k
    return len(capacities)


def assign_along(
    costs: Sequence[float], capacities: Sequence[float], lead: float = 0.0, trail: float = 0.0
) -> list[int]:
    """Node index for each vertex: node j takes a slice of the total cost proportional to its
    capacity; ``lead``/``trail`` are the costs of anchors already on the first/last node.
    The result never decreases, so vertices never go back along the route."""
    if not capacities:
        raise ValueError("a route has at least one node")
    caps = list(capacities) if sum(capacities) > 0 else [1.0] * len(capacities)
    total_cap = sum(caps)
    weights = list(costs)
    if lead + sum(weights) + trail <= 0:  # all free: spread by count
        weights, lead, trail = [1.0] * len(weights), 0.0, 0.0
    total = lead + sum(weights) + trail
    bounds, acc = [], 0.0
    for c in caps:
        acc += c
        bounds.append(total * acc / total_cap)
    out, pos = [], lead
    for w in weights:
        mid = pos + w / 2
        out.append(min(bisect.bisect_right(bounds, mid), len(caps) - 1))
        pos += w
    return out


def vertex_loads(
    app: App,
    topo: Sequence[str] | None = None,
    pred: Mapping[str, Sequence[str]] | None = None,
) -> dict[str, float]:
    """Each vertex's CPU load in ms per second at ``cpu: 1.0``: its cost times its event rate
    (a source's ``rate``, 1/s if not given; any other vertex's the sum of its inputs').
    ``topo``/``pred``: the app's topological order and predecessors, if the caller has them."""
    rate = vertex_rates(app, topo, pred)
    return {v: rate[v] * float(app.vertices[v].cost) for v in app.vertices}


class _Graph:
    """The app's adjacency and vertex order, computed once per plan."""

    def __init__(self, app: App) -> None:
        self.succ = app.successors()
        self.pred = app.predecessors()
        self.order = {v: i for i, v in enumerate(app.vertices)}


def place_chain(
    chain: Chain,
    cost: Mapping[str, float],
    placed: Mapping[str, str],
    probe: Probe,
    *,
    target: str | None = None,
    downstream_cost: float = 0.0,
    planner: str = "paper",
    traffic: Traffic | None = None,
) -> tuple[dict[str, str], list[str]]:
    """Place the unplaced vertices of ``chain``; returns (assignments, the last probed route).

    ``placed`` must hold the head. ``target`` is the node the final probe heads for (the node of
    the furthest pinned vertex downstream), and ``downstream_cost`` the cost of the chains after
    this one on the way there; with no target the free tail end stays on the last anchor's node.
    ``planner`` splits each segment: ``paper`` by cost and capacity, ``bytes`` by energy with
    ``traffic`` (required then) giving edge sizes and loads.
    """
    if planner not in PLANNERS:
        raise PlanningError(f"unknown planner {planner!r} (known: {', '.join(PLANNERS)})")
    if planner == "bytes" and traffic is None:
        raise PlanningError("the bytes planner needs the app's traffic (edge sizes and loads)")

    def split(
        seg: Sequence[str], hops: Sequence[Hop], to_end: bool, out_bytes: float, tail: bool
    ) -> list[int]:
        assert traffic is not None
        pulls: list[tuple[int, float]] = []
        if tail and traffic.tail_placed:
            at = {h.node: p for p, h in enumerate(hops)}
            pulls = [(at.get(n, 0), b) for n, b in traffic.tail_placed]
        sizes = [traffic.edge_bytes.get(ab, 0.0) for ab in itertools.pairwise(seg)]
        rates = traffic.rates
        return assign_bytes(
            [cost[v] for v in seg[1:]],
            [traffic.load.get(v, 0.0) for v in seg[1:]],
            [*sizes, out_bytes],
            hops,
            [traffic.used.get(h.node, 0.0) for h in hops],
            to_end=to_end,
            pulls=pulls,
            events=[rates.get(v, 1.0) for v in seg] if rates else (),
        )

    verts = chain.vertices
    if verts[0] not in placed:
        raise PlanningError(f"chain {chain.name}: its head {verts[0]!r} is not placed yet")
    out: dict[str, str] = {}
    anchors = [i for i, v in enumerate(verts) if v in placed]
    route: list[str] = [placed[verts[0]]]
    for i, j in itertools.pairwise(anchors):
        if j == i + 1:
            continue  # nothing between two placed vertices: no route to explore
        a, b = placed[verts[i]], placed[verts[j]]
        hops = _probe(probe, a, b, chain)
        route = [h.node for h in hops]
        interior = verts[i + 1 : j]
        if planner == "bytes":
            assert traffic is not None
            nxt = traffic.edge_bytes.get((verts[j - 1], verts[j]), 0.0)
            idx = split(verts[i:j], hops, True, nxt, False)
            out.update({v: hops[k].node for v, k in zip(interior, idx, strict=True)})
            continue
        idx = assign_along(
            [cost[v] for v in interior],
            [h.capacity for h in hops],
            lead=cost[verts[i]],
            trail=cost[verts[j]],
        )
        out.update({v: hops[k].node for v, k in zip(interior, idx, strict=True)})
    last = anchors[-1]
    rest = verts[last + 1 :]
    if rest:
        start = placed[verts[last]]
        hops = _probe(probe, start, target, chain) if target is not None else [Hop(start, 1.0)]
        route = [h.node for h in hops]
        if planner == "bytes":
            assert traffic is not None
            idx = split(verts[last:], hops, target is not None, traffic.tail_bytes, True)
            out.update({v: hops[n].node for v, n in zip(rest, idx, strict=True)})
            return out, route
        segment_cost = sum(cost[v] for v in verts[last:])
        denom = segment_cost + downstream_cost
        fraction = segment_cost / denom if denom > 0 else 1.0
        k = allocate_prefix([h.capacity for h in hops], fraction)
        idx = assign_along(
            [cost[v] for v in rest], [h.capacity for h in hops[:k]], lead=cost[verts[last]]
        )
        out.update({v: hops[n].node for v, n in zip(rest, idx, strict=True)})
    return out, route


def _probe(probe: Probe, a: str, b: str, chain: Chain) -> Sequence[Hop]:
    hops = probe(a, b)
    if not hops:
        raise PlanningError(f"chain {chain.name}: no route from {a} to {b}")
    return hops


class Layout:
    """What every node derives from the app document alone, identically: the chains, their
    order and deployment dependencies, costs and pinned vertices.

    A chain is deployed once every chain ending at its head has been placed (Algorithm 1) and,
    when its tail is a merge vertex, once that vertex's *placer* (the first chain in order ending
    there) has placed it; so chains placed concurrently on different nodes reach the same
    placement as the central :func:`plan`.
    """

    @paused_gc()
    def __init__(
        self,
        app: App,
        origin: str,
        planner: str | None = None,
        resolved: Mapping[str, str] | None = None,
    ) -> None:
        """``resolved``: the node chosen for each vertex placed by capability (every one of
        them, :mod:`mso.model.capabilities`); they are placed as if pinned there."""
        self.app = app
        self.origin = origin
        self.planner = planner or app.planner or DEFAULT_PLANNER
        if self.planner not in PLANNERS:
            raise PlanningError(f"unknown planner {self.planner!r} (known: {', '.join(PLANNERS)})")
        self.chains = form_chains(app)
        leading = chain_dependencies(self.chains)
        self.order = chain_order(self.chains, leading)
        self.graph = _Graph(app)
        self.cost = {v.id: float(v.cost) for v in app.vertices.values()}
        self.pinned = {v.id: v.pinned for v in app.vertices.values() if v.pinned is not None}
        self.resolved = {  # only vertices placed by capability (the input is a message's)
            v: n
            for v, n in (resolved or {}).items()
            if v in app.vertices and app.vertices[v].constrained
        }
        unresolved = [v.id for v in app.vertices.values() if v.constrained]
        unresolved = [v for v in unresolved if v not in self.resolved]
        if unresolved:
            raise PlanningError(
                f"vertex {unresolved[0]!r}: its node is chosen by capability, and was not"
            )
        self.pinned.update(self.resolved)
        self.edge_bytes: dict[tuple[str, str], float] = {}
        for e in app.edges:
            k = (e.src, e.dst)
            self.edge_bytes[k] = self.edge_bytes.get(k, 0.0) + edge_bytes(e)
        self.topo = app.topological_order()
        self.rates = vertex_rates(app, self.topo, self.graph.pred)
        self.load = {v: self.rates[v] * self.cost[v] for v in app.vertices}
        self.out_bytes: dict[str, list[tuple[str, float]]] = {v: [] for v in app.vertices}
        self.in_bytes: dict[str, list[tuple[str, float]]] = {v: [] for v in app.vertices}
        for (a, b), size in self.edge_bytes.items():
            self.out_bytes[a].append((b, size))
            self.in_bytes[b].append((a, size))
        self.downstream = self._downstream()
        self._flow: dict[str, dict[str, float]] = {}  # target -> bottleneck()
        self._replicas: dict[str, int] | None = None
        self._leading = leading  # (the deployment dependencies: deps)
        # vertices whose chain runs between two vertices pinned to one node have nowhere else
        # to go: their load is reserved there before any chain is split
        self.forced: dict[str, str] = {}
        for c in self.chains:
            verts = c.vertices
            at = self.pinned.get(verts[0]) if len(verts) > 2 else None
            if at is not None and at == self.pinned.get(verts[-1]):
                self.forced.update({v: at for v in verts[1:-1] if v not in self.pinned})

    # What a deploying node needs and the central plan does not: made on first use (the
    # largest allowed app spent a third of its planning on them). None depends on where a
    # vertex is pinned (repin), only on which vertices are.

    @cached_property
    def kinds(self) -> dict[str, str]:
        """Each vertex's kind: the node looks them up per hosted vertex."""
        return self.app.kinds()

    @cached_property
    def _inputs(self) -> Counter[str]:
        """Each vertex's number of input edges."""
        return Counter(e.dst for e in self.app.edges)

    @cached_property
    def merges(self) -> frozenset[str]:
        """Vertices of two inputs or more: their outputs carry their provenance."""
        return frozenset(v for v, n in self._inputs.items() if n >= 2)

    @cached_property
    def forwarders(self) -> frozenset[str]:
        """A merge's direct consumers, which pass its provenance on (mso.protocol.provenance)."""
        edges, merges, inputs = self.app.edges, self.merges, self._inputs
        produces = {e.src for e in edges}
        return frozenset(
            e.dst for e in edges if e.src in merges and inputs[e.dst] == 1 and e.dst in produces
        )

    @cached_property
    def forks(self) -> frozenset[str]:
        """Vertices of two consumers or more: their consumers may hold outputs of different
        lost instances, numbered alike; each says what it has in the input's terms (seed 5040)."""
        outputs = Counter(e.src for e in self.app.edges)
        return frozenset(v for v, n in outputs.items() if n >= 2 and v in self._inputs)

    @cached_property
    def stamped(self) -> frozenset[str]:
        """Vertices whose outputs carry a header."""
        return self.merges | self.forwarders | self.forks

    @cached_property
    def out_edges(self) -> dict[str, list[int]]:
        """Vertex -> its output edges (indices in app.edges): what its outputs are sent on."""
        out: dict[str, list[int]] = {}
        for i, e in enumerate(self.app.edges):
            out.setdefault(e.src, []).append(i)
        return out

    @cached_property
    def in_edges(self) -> dict[str, list[int]]:
        """Vertex -> its input edges (indices in app.edges): what it is fed on."""
        ins: dict[str, list[int]] = {}
        for i, e in enumerate(self.app.edges):
            ins.setdefault(e.dst, []).append(i)
        return ins

    @cached_property
    def edge_chain(self) -> list[int]:
        """The chain each edge lies in (every edge lies in exactly one, §3.2)."""
        index = {(e.src, e.dst): i for i, e in enumerate(self.app.edges)}
        out = [-1] * len(self.app.edges)
        for c in self.chains:
            for a, b in itertools.pairwise(c.vertices):
                out[index[(a, b)]] = c.index
        return out

    @cached_property
    def placer(self) -> dict[str, int]:
        """Each merge vertex's placer: the first chain in order ending there."""
        placer: dict[str, int] = {}
        for ci in self.order:
            verts = self.chains[ci].vertices
            if len(verts) > 1:
                placer.setdefault(verts[-1], ci)
        return placer

    @cached_property
    def deps(self) -> list[set[int]]:
        """The chains each chain waits for before it is placed (the class's docstring)."""
        deps: list[set[int]] = []
        placer = self.placer
        for c, first in zip(self.chains, self._leading, strict=True):
            d = set(first)
            tail = c.vertices[-1]
            p = placer.get(tail)
            if p is not None and p != c.index and tail not in self.pinned:
                d.add(p)
            deps.append(d)
        if self.planner == "bytes":
            # the bytes planner weighs where a chain's neighbours went and what load is left
            # on each node: chains are placed one after another, each knowing every earlier one
            for before, ci in itertools.pairwise(self.order):
                deps[ci].add(before)
        return deps

    def initial_placement(self) -> dict[str, str]:
        """Pinned vertices, and unpinned heads no chain leads to (sources) on the origin."""
        placed = dict(self.pinned)
        ends = {c.tail for c in self.chains if len(c) > 1}
        for c in self.chains:
            if c.head not in ends:
                placed.setdefault(c.head, self.origin)
        return placed

    def ready(self, chain: int, placed_chains: set[int]) -> bool:
        return self.deps[chain] <= placed_chains

    def target(
        self, chain: int, placed: Mapping[str, str], distances: Mapping[str, int]
    ) -> tuple[str | None, float]:
        """The node of the furthest pinned vertex downstream of the chain's last anchor (by
        ``distances``, hops from that anchor's node), and the cost of the chains after this one
        on the way to it.

        Only pinned vertices count: every node knows them before deployment starts."""
        c = self.chains[chain]
        verts = c.vertices
        last = len(verts) - 1
        while last > 0 and verts[last] not in placed:  # (the head: place_chain checks it)
            last -= 1
        if last == len(verts) - 1:
            return None, 0.0
        best = self.downstream.furthest_pinned(c.tail, distances, verts[: last + 1])
        if best is None:
            return None, 0.0
        if self.planner != "paper":
            return self.pinned[best], 0.0  # the cost fraction is the paper split's only
        return self.pinned[best], self.downstream.cost_between(c.tail, best, chain)

    def traffic(
        self,
        chain: int,
        placed: Mapping[str, str],
        target: str | None,
        used: Mapping[str, float] | None = None,
    ) -> Traffic:
        """The bytes planner's view of one chain: edge sizes, loads, the load this app already
        put on each node (and the load reserved for :attr:`forced` vertices), and what its tail
        exchanges: with vertices already placed (their nodes pull it), and toward ``target``
        (the bytes that must still get to vertices pinned there, :meth:`bottleneck`). Every
        earlier chain is in ``placed``: with this planner chains are placed one at a time.
        ``used``: the load ``placed`` puts on each node, if the caller keeps it (``plan``)."""
        if used is None:
            used = self.loads(placed)
        busy = used
        if self.forced:
            busy = dict(used)
            for v, n in self.forced.items():
                if v not in placed:
                    busy[n] = busy.get(n, 0.0) + self.load[v]
        verts = self.chains[chain].vertices
        tail = verts[-1]
        tail_bytes = 0.0
        tail_placed: list[tuple[str, float]] = []
        if tail not in placed:
            for u, size in self.in_bytes[tail]:
                node = placed.get(u)
                if u != verts[-2] and node is not None:
                    tail_placed.append((node, size))  # a merge's other inputs pull it too
            flow = self.bottleneck(target) if target is not None else {}
            for w, size in self.out_bytes[tail]:
                node = placed.get(w)
                if node is not None:
                    tail_placed.append((node, size))
                else:
                    tail_bytes += min(size, flow.get(w, 0.0))
        return Traffic(self.edge_bytes, self.load, busy, tail_bytes, tuple(tail_placed), self.rates)

    def loads(self, placed: Mapping[str, str]) -> dict[str, float]:
        """The load (ms/s at cpu 1.0) the vertices in ``placed`` put on each node."""
        used: dict[str, float] = {}
        for v, n in placed.items():
            used[n] = used.get(n, 0.0) + self.load[v]
        return used

    def replicas(self) -> dict[str, int]:
        """Replicas kept of each vertex's state, for the vertices that keep any (a copy):
        found once per Layout, which a simulation's nodes share -- each node taking each app
        looked every vertex's code up again (12% of a 1,000-node start-up)."""
        if self._replicas is None:
            kinds, app = self.kinds, self.app
            found = {v: app.replicas(v, kinds[v]) for v in app.vertices}
            self._replicas = {v: n for v, n in found.items() if n > 0}
        return dict(self._replicas)

    def _downstream(self) -> Downstream:
        return Downstream(
            self.topo,
            self.graph.succ,
            self.graph.pred,
            self.pinned,
            self.graph.order,
            self.chains,
            self.cost,
        )

    def repin(self, vertex: str, node: str) -> None:
        """A vertex placed by capability goes to ``node`` (its first choice failed): what
        was derived from the pins is derived again."""
        self.resolved[vertex] = self.pinned[vertex] = node
        self._flow.clear()
        self.downstream = self._downstream()

    def bottleneck(self, target: str) -> dict[str, float]:
        """For every vertex: the bytes per event that must still travel from it to the
        vertices pinned to ``target`` when every later vertex may sit anywhere on the way. A
        path can be cut at its smallest edge, so an edge carries at most what lies beyond it;
        0 with no path there, infinite at such a vertex. One pass per target, kept (plain
        loops: twice as fast as generators or a walk from the vertices asked for)."""
        flow = self._flow.get(target)
        if flow is None:
            flow = self._flow[target] = {}
            out_bytes, pinned, inf = self.out_bytes, self.pinned, math.inf
            for v in reversed(self.topo):
                if pinned.get(v) == target:
                    flow[v] = inf
                    continue
                carried = 0.0
                for w, size in out_bytes[v]:
                    beyond = flow[w]
                    carried += size if size < beyond else beyond
                flow[v] = carried
        return flow

    def walk_energy(
        self, chain: int, assign: Mapping[str, str], walk: Sequence[Hop]
    ) -> float | None:
        """µJ per event of one chain placed as ``assign`` along ``walk`` (its probed routes,
        end to end): each vertex's CPU energy on its node, each edge's bytes times the tx+rx
        µJ per byte between its ends along the walk, and its time on the air at the links'
        rates (the bytes planner's own objective, :func:`carry_prefix`). None if a vertex's
        node is not on the walk (it cannot be judged from these probes)."""
        at: dict[str, int] = {}
        acc = carry_prefix(walk)
        for p, h in enumerate(walk):
            at.setdefault(h.node, p)
        verts = self.chains[chain].vertices
        if any(assign.get(v) not in at for v in verts):
            return None
        total = 0.0
        for v in verts[1:]:  # the head is not this chain's to place
            total += compute_uj(self.cost[v], walk[at[assign[v]]])
        for a, b in itertools.pairwise(verts):
            size = self.edge_bytes.get((a, b), 0.0)
            total += size * abs(acc[at[assign[a]]] - acc[at[assign[b]]])
        return total

    def overloads_link(self, chain: int, assign: Mapping[str, str], walk: Sequence[Hop]) -> bool:
        """Whether an edge of the chain placed as ``assign`` crosses a link of ``walk`` whose
        rate cannot carry it (:data:`LINK_SHARE` of it), as the bytes split never plans."""
        at: dict[str, int] = {}
        for p, h in enumerate(walk):
            at.setdefault(h.node, p)
        for a, b in itertools.pairwise(self.chains[chain].vertices):
            pa, pb = at.get(assign.get(a, "")), at.get(assign.get(b, ""))
            if pa is None or pb is None:
                continue
            bits = self.edge_bytes.get((a, b), 0.0) * self.rates[a] * 8
            lo, hi = min(pa, pb), max(pa, pb)
            if any(not carries(walk[p], bits) for p in range(lo + 1, hi + 1)):
                return True
        return False

    def keep_current(
        self,
        chain: int,
        new: Mapping[str, str],
        current: Mapping[str, str],
        walk: Sequence[Hop],
        *,
        alive: Callable[[str], bool],
        others: Mapping[str, str],
        margin: float,
    ) -> tuple[dict[str, str], str]:
        """A remap starts from the current placement: the chain keeps its vertices where they
        run (a move the rules made included) and takes ``new``'s node only for a vertex whose
        node is gone, unless a node it keeps would be over capacity (with ``others``, the rest
        of the app as placed), or ``new`` costs less than ``1 - margin`` of the energy the
        kept placement would. Returns (placement, why)."""
        verts = self.chains[chain].vertices
        kept = {v: current[v] if alive(current.get(v, "")) else new[v] for v in verts}
        if kept == dict(new):
            return dict(new), "unchanged" if all(new[v] == current.get(v) for v in verts) else (
                "only what was lost moves"
            )
        caps = {h.node: h.capacity for h in walk}
        load: dict[str, float] = {}
        for v, n in [*((u, m) for u, m in others.items() if u not in kept), *kept.items()]:
            load[n] = load.get(n, 0.0) + self.load[v]
        if any(n in caps and load[n] > 1000.0 * caps[n] + 1e-9 for n in set(kept.values())):
            return dict(new), "a node it runs on would be over capacity"
        if self.overloads_link(chain, kept, walk):
            return dict(new), "a link it uses cannot carry its edge at the link's rate"
        e_new, e_now = self.walk_energy(chain, new, walk), self.walk_energy(chain, kept, walk)
        if e_new is None or e_now is None:
            return dict(new), "its current nodes are off the probed route"
        if e_new < e_now * (1.0 - margin):
            return dict(new), f"the new plan saves {1 - e_new / max(e_now, 1e-12):.0%}"
        return kept, "kept: the new plan does not beat the current one by the margin"

    def last_anchor_node(self, chain: int, placed: Mapping[str, str]) -> str:
        for v in reversed(self.chains[chain].vertices):  # (a chain never repeats a vertex)
            if v in placed:
                return placed[v]
        raise PlanningError(f"chain {self.chains[chain].name}: none of its vertices is placed")

    def probes_needed(
        self, chain: int, placed: Mapping[str, str], target: str | None
    ) -> list[tuple[str, str]]:
        """The (from, to) routes :meth:`place` will ask its probe for, in order."""
        verts = self.chains[chain].vertices
        anchors = [i for i, v in enumerate(verts) if v in placed]
        pairs = [
            (placed[verts[i]], placed[verts[j]])
            for i, j in itertools.pairwise(anchors)
            if j > i + 1
        ]
        if anchors[-1] < len(verts) - 1 and target is not None:
            pairs.append((placed[verts[anchors[-1]]], target))
        return pairs

    def place(
        self,
        chain: int,
        placed: Mapping[str, str],
        probe: Probe,
        distances: Mapping[str, int],
        used: Mapping[str, float] | None = None,
    ) -> tuple[dict[str, str], list[str]]:
        """Place one chain whose dependencies are met: (assignments incl. anchors, route).
        ``used``: :meth:`loads` of ``placed``, if the caller keeps it as it goes."""
        target, downstream = self.target(chain, placed, distances)
        traffic = None
        if self.planner == "bytes":
            traffic = self.traffic(chain, placed, target, used)
        assigned, route = place_chain(
            self.chains[chain],
            self.cost,
            placed,
            probe,
            target=target,
            downstream_cost=downstream,
            planner=self.planner,
            traffic=traffic,
        )
        full = {v: assigned.get(v) or placed[v] for v in self.chains[chain].vertices}
        return full, route


def candidates(network: Network, anchors: Sequence[str] = ()) -> list[Candidate]:
    """Every node of a known network as a capability candidate, with its hops to ``anchors``
    (what the nodes' answers to a deployment's query carry)."""
    hops = {a: network.distances(a) for a in anchors if a in network.nodes}
    return [
        Candidate(
            n.id,
            offered(n.capabilities, n.cpu),
            n.battery_wh,
            {a: d[n.id] for a, d in hops.items() if n.id in d},
        )
        for n in network.nodes.values()
    ]


def resolve_capabilities(app: App, network: Network) -> tuple[dict[str, str], dict[str, list[str]]]:
    """The node of each vertex placed by capability on a known network, and its ranked
    candidates (:func:`mso.model.capabilities.resolve`); PlanningError if one cannot be met."""
    needs = app.needs()
    if not needs:
        return {}, {}
    pinned = {v.id: v.pinned for v in app.vertices.values() if v.pinned is not None}
    anchors = list(network.nodes) if any(n.near for n in needs) else []
    return resolve(needs, pinned, candidates(network, anchors))


def with_pins(app: App, resolved: Mapping[str, str]) -> App:
    """A copy of ``app`` with each vertex placed by capability pinned where it was resolved:
    what the baselines (which know only ``pinned``) place."""
    if not resolved:
        return app
    out = App(app.name, slo_ms=app.slo_ms, policy=app.policy, planner=app.planner)
    out.edges = list(app.edges)
    for v in app.vertices.values():
        node = resolved.get(v.id)
        out.vertices[v.id] = (
            v if node is None else replace(v, pinned=node, requires={}, near=None, apart_from=None)
        )
    return out


@paused_gc()
def plan(
    app: App,
    network: Network,
    *,
    capacity: Capacity = cpu_capacity,
    origin: str | None = None,
    probe: Probe | None = None,
    planner: str | None = None,
) -> Plan:
    """Algorithm 1 run centrally: place every chain in dependency order.

    ``origin`` hosts unpinned sources (default: the network's first node), as the deploying
    node does in a distributed deployment. ``planner`` overrides the app's (``planner:``).
    """
    if not network.nodes:
        raise PlanningError("the network has no nodes")
    origin = origin or next(iter(network.nodes))
    if origin not in network.nodes:
        raise PlanningError(f"origin node {origin!r} is not in the network")
    for v in app.vertices.values():
        if v.pinned is not None and v.pinned not in network.nodes:
            raise PlanningError(
                f"vertex {v.id!r} is pinned to node {v.pinned!r}, which is not in the network "
                f"(nodes: {', '.join(network.nodes)})"
            )
    probe = probe or network_probe(network, capacity)
    resolved, capable = resolve_capabilities(app, network)
    layout = Layout(app, origin, planner, resolved)
    placed = layout.initial_placement()
    routes: dict[int, list[str]] = {}
    distances: dict[str, dict[str, int]] = {}  # chains often start at one node
    used = layout.loads(placed)  # kept as chains are placed, not summed again for each
    chains = layout.chains
    for ci in layout.order:
        verts = chains[ci].vertices
        if all(v in placed for v in verts):
            # nothing to place (most chains of a large app run between two vertices placed
            # already): place_chain would probe nothing and return the head's node as route
            routes[ci] = [placed[verts[0]]]
            continue
        start = layout.last_anchor_node(ci, placed)
        if start not in distances:
            distances[start] = network.distances(start)
        assigned, route = layout.place(ci, placed, probe, distances[start], used)
        for u, n in assigned.items():
            if u not in placed:
                used[n] = used.get(n, 0.0) + layout.load[u]
        placed.update(assigned)
        routes[ci] = route
    placement = {v: placed[v] for v in app.vertices}
    return Plan(
        placement=placement,
        chains=layout.chains,
        order=layout.order,
        routes=routes,
        planner=layout.planner,
        capable=capable,
    )
