"""Node mobility: where each node is at time t. Pure and seeded, so the emulator and the
simulator see the same movement for the same scenario.

Random waypoint: each mobile node picks a uniform point in the area and a uniform speed, moves
there in a straight line, pauses, and repeats. Nodes listed in ``fixed`` do not move.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field


@dataclass(frozen=True)
class RandomWaypoint:
    area: tuple[float, float]
    speed: tuple[float, float]
    pause_s: float = 0.0
    seed: int = 0
    fixed: frozenset[str] = frozenset()


@dataclass
class _Leg:
    start: float
    end: float
    src: tuple[float, float]
    dst: tuple[float, float]
    pause_until: float


@dataclass
class WaypointTracks:
    """Positions over time under a :class:`RandomWaypoint` model; ask in non-decreasing time."""

    model: RandomWaypoint
    start_positions: dict[str, tuple[float, float]]
    _legs: dict[str, _Leg] = field(default_factory=dict)
    _rngs: dict[str, random.Random] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for i, (node, pos) in enumerate(sorted(self.start_positions.items())):
            self._rngs[node] = random.Random(self.model.seed * 1_000_003 + i)
            self._legs[node] = _Leg(0.0, 0.0, pos, pos, 0.0)

    def _next_leg(self, node: str, t: float, here: tuple[float, float]) -> _Leg:
        rng = self._rngs[node]
        w, h = self.model.area
        dst = (rng.uniform(0, w), rng.uniform(0, h))
        lo, hi = self.model.speed
        speed = max(rng.uniform(lo, hi), 1e-6)
        end = t + math.dist(here, dst) / speed
        return _Leg(t, end, here, dst, end + self.model.pause_s)

    def positions(self, t: float) -> dict[str, tuple[float, float]]:
        out: dict[str, tuple[float, float]] = {}
        for node, leg in self._legs.items():
            if node in self.model.fixed:
                out[node] = self.start_positions[node]
                continue
            while t >= leg.pause_until:
                leg = self._legs[node] = self._next_leg(node, leg.pause_until, leg.dst)
            if t >= leg.end or leg.end <= leg.start:
                out[node] = leg.dst
            else:
                f = (t - leg.start) / (leg.end - leg.start)
                out[node] = (
                    leg.src[0] + f * (leg.dst[0] - leg.src[0]),
                    leg.src[1] + f * (leg.dst[1] - leg.src[1]),
                )
        return out


Waypoint = tuple[float, float, float]
"""``(t, x, y)``: the node is at ``(x, y)`` at ``t`` seconds."""


@dataclass(frozen=True)
class Trace:
    """Movement recorded by another tool (ns-2 ``setdest``, BonnMotion): per node, waypoints in
    time order; between two, the node moves in a straight line at constant speed; before the
    first and after the last it stays put. Two waypoints at one time are a jump."""

    waypoints: dict[str, tuple[Waypoint, ...]]
    source: str = ""

    @property
    def end(self) -> float:
        """When the last node stops moving (0 for a trace of fixed nodes)."""
        return max((w[-1][0] for w in self.waypoints.values() if w), default=0.0)

    def start_positions(self) -> dict[str, tuple[float, float]]:
        return {n: (w[0][1], w[0][2]) for n, w in self.waypoints.items() if w}


@dataclass
class TraceTracks:
    """Positions over time under a :class:`Trace`; nodes the trace does not list stay at their
    start position. Any time order works (a binary search per node)."""

    model: Trace
    start_positions: dict[str, tuple[float, float]]

    def positions(self, t: float) -> dict[str, tuple[float, float]]:
        out = dict(self.start_positions)
        for node, ws in self.model.waypoints.items():
            if ws:
                out[node] = _at(ws, t)
        return out


def _at(ws: tuple[Waypoint, ...], t: float) -> tuple[float, float]:
    if t <= ws[0][0]:
        return (ws[0][1], ws[0][2])
    if t >= ws[-1][0]:
        return (ws[-1][1], ws[-1][2])
    lo, hi = 0, len(ws) - 1  # invariant: ws[lo].t <= t < ws[hi].t
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ws[mid][0] <= t:
            lo = mid
        else:
            hi = mid
    (t0, x0, y0), (t1, x1, y1) = ws[lo], ws[hi]
    f = (t - t0) / (t1 - t0)
    return (x0 + f * (x1 - x0), y0 + f * (y1 - y0))


Mobility = RandomWaypoint | Trace
Tracks = WaypointTracks | TraceTracks


def tracks_for(model: Mobility, starts: dict[str, tuple[float, float]]) -> Tracks:
    """The position source for a scenario's mobility model."""
    if isinstance(model, Trace):
        return TraceTracks(model, starts)
    return WaypointTracks(model, starts)
