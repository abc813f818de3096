"""Node mobility: where each node is at time t. Pure and seeded, so the emulator and the
simulator see the same movement for the same scenario.

Random waypoint: each mobile node picks a uniform point in the area and a uniform speed, moves
there in a straight line, pauses, and repeats. Gauss-Markov: speed and direction drift, each
interval a weighted mean of the last value, the node's mean and a Gaussian draw (``alpha`` the
memory), steered back toward the centre near the area's edges. Reference-point group mobility:
each group's reference point does random waypoint and its members keep their place around it,
each wandering within ``radius`` of that place. Nodes listed in ``fixed`` do not move.
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


@dataclass(frozen=True)
class GaussMarkov:
    """Gauss-Markov mobility (Liang and Haas): ``speed`` is the [min, max] range whose middle
    is the mean speed; ``alpha`` in [0, 1] how much of the last speed and direction is kept
    each ``interval_s``."""

    area: tuple[float, float]
    speed: tuple[float, float]
    alpha: float = 0.75
    interval_s: float = 1.0
    seed: int = 0
    fixed: frozenset[str] = frozenset()


@dataclass(frozen=True)
class GroupMobility:
    """Reference-point group mobility (Hong et al.): each group's reference point moves by
    random waypoint over ``area`` (``speed``, ``pause_s``); a member stays at its start offset
    from the group's centre plus a wander within ``radius``, drawn anew every ``interval_s``.
    Nodes in no group do not move."""

    area: tuple[float, float]
    speed: tuple[float, float]
    groups: tuple[tuple[str, ...], ...]
    radius: float = 10.0
    pause_s: float = 0.0
    interval_s: float = 1.0
    seed: int = 0


def _rng(seed: int, i: int) -> random.Random:
    return random.Random(seed * 1_000_003 + i)


@dataclass
class _Drift:
    """One node's Gauss-Markov state at the start of its current interval."""

    t: float
    pos: tuple[float, float]
    nxt: tuple[float, float]  # where it is at the end of the interval
    speed: float
    heading: float
    mean_heading: float


@dataclass
class GaussMarkovTracks:
    """Positions over time under :class:`GaussMarkov`; ask in non-decreasing time. Within an
    interval a node moves in a straight line; it stays inside the area (a step that would
    leave it is clamped to the edge)."""

    model: GaussMarkov
    start_positions: dict[str, tuple[float, float]]
    _state: dict[str, _Drift] = field(default_factory=dict)
    _rngs: dict[str, random.Random] = field(default_factory=dict)

    def __post_init__(self) -> None:
        lo, hi = self.model.speed
        for i, (node, pos) in enumerate(sorted(self.start_positions.items())):
            rng = self._rngs[node] = _rng(self.model.seed, i)
            heading = rng.uniform(-math.pi, math.pi)
            d = _Drift(0.0, pos, pos, (lo + hi) / 2, heading, heading)
            d.nxt = self._step(d.pos, d.speed, d.heading)
            self._state[node] = d

    def _step(self, pos: tuple[float, float], speed: float, heading: float) -> tuple[float, float]:
        w, h, dt = self.model.area[0], self.model.area[1], self.model.interval_s
        x = min(max(pos[0] + speed * math.cos(heading) * dt, 0.0), w)
        return (x, min(max(pos[1] + speed * math.sin(heading) * dt, 0.0), h))

    def _advance(self, node: str, d: _Drift) -> None:
        m, rng = self.model, self._rngs[node]
        lo, hi = m.speed
        a, b = m.alpha, math.sqrt(max(0.0, 1 - m.alpha**2))
        w, h = m.area
        x, y = d.nxt
        mean = d.mean_heading
        if min(x, w - x) < 0.1 * w or min(y, h - y) < 0.1 * h:  # near an edge: turn inward
            mean = math.atan2(h / 2 - y, w / 2 - x)
        speed = a * d.speed + (1 - a) * (lo + hi) / 2 + b * rng.gauss(0, (hi - lo) / 2 or 0.1)
        speed = min(max(speed, lo), hi)
        heading = a * d.heading + (1 - a) * mean + b * rng.gauss(0, math.pi / 4)
        d.t, d.pos, d.speed, d.heading = d.t + m.interval_s, d.nxt, speed, heading
        d.nxt = self._step(d.pos, speed, heading)

    def positions(self, t: float) -> dict[str, tuple[float, float]]:
        out: dict[str, tuple[float, float]] = {}
        dt = self.model.interval_s
        for node, d in self._state.items():
            if node in self.model.fixed:
                out[node] = self.start_positions[node]
                continue
            while t >= d.t + dt:
                self._advance(node, d)
            f = (t - d.t) / dt
            out[node] = (d.pos[0] + f * (d.nxt[0] - d.pos[0]), d.pos[1] + f * (d.nxt[1] - d.pos[1]))
        return out


@dataclass
class GroupTracks:
    """Positions over time under :class:`GroupMobility`; ask in non-decreasing time."""

    model: GroupMobility
    start_positions: dict[str, tuple[float, float]]
    _refs: WaypointTracks = field(init=False)
    _offsets: dict[str, tuple[str, tuple[float, float]]] = field(default_factory=dict)
    _wander: dict[str, tuple[int, tuple[float, float], tuple[float, float]]] = field(
        default_factory=dict
    )
    _rngs: dict[str, random.Random] = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = self.model
        centres: dict[str, tuple[float, float]] = {}
        for g, members in enumerate(m.groups):
            at = [self.start_positions[n] for n in members if n in self.start_positions]
            if not at:
                continue
            ref = f"group{g}"
            centres[ref] = (sum(p[0] for p in at) / len(at), sum(p[1] for p in at) / len(at))
            for n in members:
                if n in self.start_positions:
                    p = self.start_positions[n]
                    self._offsets[n] = (ref, (p[0] - centres[ref][0], p[1] - centres[ref][1]))
        self._refs = WaypointTracks(RandomWaypoint(m.area, m.speed, m.pause_s, m.seed), centres)
        for i, n in enumerate(sorted(self._offsets)):
            self._rngs[n] = _rng(m.seed + 1, i)
            self._wander[n] = (0, (0.0, 0.0), self._draw(n))

    def _draw(self, node: str) -> tuple[float, float]:
        rng, r = self._rngs[node], self.model.radius
        angle, dist = rng.uniform(-math.pi, math.pi), r * math.sqrt(rng.random())
        return (dist * math.cos(angle), dist * math.sin(angle))

    def positions(self, t: float) -> dict[str, tuple[float, float]]:
        out = dict(self.start_positions)
        refs = self._refs.positions(t)
        dt = self.model.interval_s
        for n, (ref, (ox, oy)) in self._offsets.items():
            k, a, b = self._wander[n]
            while t >= (k + 1) * dt:
                k, a, b = k + 1, b, self._draw(n)
            self._wander[n] = (k, a, b)
            f = (t - k * dt) / dt
            rx, ry = refs[ref]
            out[n] = (rx + ox + a[0] + f * (b[0] - a[0]), ry + oy + a[1] + f * (b[1] - a[1]))
        return out


Mobility = RandomWaypoint | Trace | GaussMarkov | GroupMobility
Tracks = WaypointTracks | TraceTracks | GaussMarkovTracks | GroupTracks


def tracks_for(model: Mobility, starts: dict[str, tuple[float, float]]) -> Tracks:
    """The position source for a scenario's mobility model."""
    if isinstance(model, Trace):
        return TraceTracks(model, starts)
    if isinstance(model, GaussMarkov):
        return GaussMarkovTracks(model, starts)
    if isinstance(model, GroupMobility):
        return GroupTracks(model, starts)
    return WaypointTracks(model, starts)
