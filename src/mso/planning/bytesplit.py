"""The ``bytes`` planner's split of one chain segment along its probed route (issue 25): the
cheapest in energy per event, computing weighed against carrying each edge's bytes over each
hop (its energy, and its time at the link's rate), within each node's CPU and each link's rate.
Pure: no I/O, no clock. :mod:`.placement` calls it per segment."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from mso.model.network import PowerModel

_POWER = PowerModel()

LINK_SHARE = 0.8
"""The share of a link's rate one edge may fill: an edge whose bytes per second (size times
its events per second) need more is not carried over that link (radios lose the rest to
contention and framing; a queue that grows without end is never the cheapest)."""

CARRY_UJ_PER_MS = 1.0
"""How the time of carrying an edge is weighed against energy: 1 µJ per ms an event spends on
the air at the links' rates. Energy stays the objective: the time decides between splits whose
energy differs by less than that, and what a slow link cannot carry at all is refused by
:data:`LINK_SHARE`, not weighed."""


@dataclass(frozen=True)
class Hop:
    """What a probe collects at one node of its route: its capacity and, for the ``bytes``
    planner, its power figures (a node that does not report them is taken at the defaults)
    and the rate of the link it was reached over from the hop before (Mb/s; None: not known,
    or the route's first node), as the node before it knew it."""

    node: str
    capacity: float
    cpu_w: float = _POWER.cpu_w
    tx_uj_per_byte: float = _POWER.tx_uj_per_byte
    rx_uj_per_byte: float = _POWER.rx_uj_per_byte
    rate_mbps: float | None = None

    def weighted(self, factor: float) -> Hop:
        """The same hop with its capacity scaled (a remap's lifetime weight)."""
        return replace(self, capacity=self.capacity * factor)


@dataclass(frozen=True)
class Traffic:
    """What the ``bytes`` planner knows of an app besides costs: bytes per event of each edge
    (parallel edges summed), each vertex's CPU load in ms per second at ``cpu: 1.0`` (cost times
    its event rate), and the load already placed on each node."""

    edge_bytes: Mapping[tuple[str, str], float]
    load: Mapping[str, float]
    used: Mapping[str, float] = field(default_factory=dict)
    tail_bytes: float = 0.0  # what the chain's tail sends on toward the probe's target
    # what the tail sends to vertices already placed: (their node, bytes per event)
    tail_placed: tuple[tuple[str, float], ...] = ()
    # events per second each vertex sends on (a source's rate; 1/s when not known)
    rates: Mapping[str, float] = field(default_factory=dict)


def compute_uj(cost: float, hop: Hop) -> float:
    """µJ of CPU one event of a vertex of ``cost`` takes on ``hop`` (the energy objective's)."""
    if cost == 0:
        return 0.0
    if hop.capacity <= 0:
        return math.inf
    return cost / hop.capacity * hop.cpu_w * 1e3


def carry_prefix(hops: Sequence[Hop]) -> list[float]:
    """µJ-equivalent per byte from position 0 to each position of a route: each hop's tx+rx
    energy plus the time a byte takes at the link's rate, weighed by :data:`CARRY_UJ_PER_MS`."""
    acc = [0.0]
    for a, b in itertools.pairwise(hops):
        t_ms = 8e-3 / b.rate_mbps if b.rate_mbps else 0.0  # ms per byte at rate Mb/s
        acc.append(acc[-1] + a.tx_uj_per_byte + b.rx_uj_per_byte + CARRY_UJ_PER_MS * t_ms)
    return acc


def carries(hop: Hop, bits_per_s: float) -> bool:
    """Whether the link into ``hop`` can carry an edge of ``bits_per_s`` (unknown rate: yes)."""
    return not hop.rate_mbps or bits_per_s <= hop.rate_mbps * 1e6 * LINK_SHARE + 1e-9


def assign_bytes(
    costs: Sequence[float],
    loads: Sequence[float],
    sizes: Sequence[float],
    hops: Sequence[Hop],
    used: Sequence[float] | None = None,
    *,
    to_end: bool,
    pulls: Sequence[tuple[int, float]] = (),
    events: Sequence[float] = (),
) -> list[int]:
    """Route position of each vertex of a chain segment, the cheapest in energy per event.

    The segment's vertices follow an anchor at position 0; ``sizes[i]`` is the bytes per event
    into vertex ``i`` and ``sizes[-1]`` those out of the last one, which travel to the route's
    end when ``to_end`` (an anchor or the probe's target lies there); ``pulls`` are further
    (position, bytes) the last vertex sends to vertices already placed. Computing vertex ``i`` at
    ``p`` costs its CPU energy there; an edge from ``q`` to ``p`` costs its bytes times the
    tx+rx µJ per byte of hops ``q..p``, plus the time it takes at each link's rate
    (:func:`carry_prefix`), so the chain is cut at its small edges. Positions never decrease (a
    chain never goes back along its route). A node takes vertices only while their load
    (``loads``, ms/s at cpu 1.0) fits what its capacity leaves (``capacity * 1000 - used``),
    and a link carries an edge only if its bytes per second (``sizes[i] * events[i]``, the
    events per second into vertex ``i``, ``events[-1]`` out of the last; 1/s when not given)
    fit :data:`LINK_SHARE` of the link's rate. Within a segment no two edges share a link
    (positions never decrease); edges of other chains over the same link are not counted.

    A dynamic programme over (vertex, position) with a running minimum over earlier positions:
    O(len(costs) * len(hops)). Each state keeps the load of its cheapest path only, so capacity
    is respected by every answer though the answer may miss a costlier-to-reach feasible
    optimum; with no feasible split at all, capacity and link rates are ignored (the paper's
    split ignores both always).
    """
    k, r = len(costs), len(hops)
    if r == 0:
        raise ValueError("a route has at least one node")
    if k == 0:
        return []
    acc = carry_prefix(hops)  # acc[p]: µJ per byte from position 0 to p
    left = [h.capacity * 1e3 - (used[p] if used else 0.0) for p, h in enumerate(hops)]
    ev = list(events) if len(events) == k + 1 else [1.0] * (k + 1)
    # slow[i][p]: the link into position p cannot carry the edge into vertex i (i == k: out)
    slow = (
        [
            [p > 0 and not carries(h, s * e * 8) for p, h in enumerate(hops)]
            for s, e in zip(sizes, ev, strict=True)
        ]
        if any(h.rate_mbps for h in hops)
        else None
    )
    # what the last vertex's pulls cost at each position (the same for both passes)
    pulled = [sum(b * abs(acc[p] - acc[q]) for q, b in pulls) for p in range(r)] if pulls else None
    for limited in (True, False):
        out = _bytes_dp(
            costs,
            loads,
            sizes,
            hops,
            acc,
            left if limited else None,
            to_end,
            pulled,
            slow if limited else None,
        )
        if out is not None:
            return out
    return [0] * k  # every split costs infinite energy (no CPU anywhere): stay on the anchor


def _bytes_dp(
    costs: Sequence[float],
    loads: Sequence[float],
    sizes: Sequence[float],
    hops: Sequence[Hop],
    acc: Sequence[float],
    left: Sequence[float] | None,
    to_end: bool,
    pulled: Sequence[float] | None,
    slow: Sequence[Sequence[bool]] | None,
) -> list[int] | None:
    k, r, inf = len(costs), len(hops), math.inf
    # µJ per unit of cost on each hop (compute_uj's, hoisted out of the loop)
    per_cost = [h.cpu_w * 1e3 / h.capacity if h.capacity > 0 else inf for h in hops]
    prev_val = [inf] * r
    prev_load = [0.0] * r
    parent: list[list[int]] = []
    for i in range(k):
        val, load, par = [inf] * r, [0.0] * r, [-1] * r
        best, best_q = (0.0, 0) if i == 0 else (inf, -1)  # the anchor sits at position 0
        cost_i, load_i, size_i = costs[i], loads[i], sizes[i]
        slow_i = slow[i] if slow is not None else None
        for p in range(r):
            if slow_i is not None and slow_i[p]:
                best, best_q = inf, -1  # edge i cannot come over the link into p from before
            compute = cost_i * per_cost[p] if cost_i else 0.0
            if compute != inf:
                if best_q >= 0 and (left is None or load_i <= left[p] + 1e-9):
                    val[p] = best + size_i * acc[p] + compute  # arrive from q < p
                    load[p], par[p] = load_i, best_q
                stay = prev_load[p] + load_i  # after vertex i-1 on the same node
                fits = left is None or stay <= left[p] + 1e-9
                if i > 0 and fits and prev_val[p] + compute <= val[p]:
                    val[p], load[p], par[p] = prev_val[p] + compute, stay, p
            if i > 0 and prev_val[p] - size_i * acc[p] < best:
                best, best_q = prev_val[p] - size_i * acc[p], p
        prev_val, prev_load = val, load
        parent.append(par)
        if val.count(inf) == r:
            return None  # no position for vertex i: none for the vertices after it either
    out_size, last = sizes[k], acc[r - 1]
    end = [v + out_size * (last - acc[p]) for p, v in enumerate(prev_val)] if to_end else prev_val
    if to_end and slow is not None and out_size:
        blocked = False  # a link after p cannot carry the tail's output to the route's end
        end = list(end)
        for p in range(r - 1, -1, -1):
            end[p] = inf if blocked else end[p]
            blocked = blocked or slow[k][p]
    if pulled is not None:
        end = [v + c for v, c in zip(end, pulled, strict=True)]
    p = min(range(r), key=lambda q: (end[q], q))
    if math.isinf(end[p]):
        return None
    out = [0] * k
    for i in range(k - 1, -1, -1):
        out[i] = p
        p = parent[i][p]
    return out
