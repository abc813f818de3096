"""The simulated disaster site the convoy drives through: a generated occupancy grid, the
leader's route, and the survivors planted in it.

Everything is a pure function of a seed, so the leader's sources (on one robot) and the
vertices that need the map (localization, planning, the target map — on whichever robot the
overlay puts them) build the same world without sending it around, and a test or the demo's
summary can recompute the ground truth from the seed alone.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

RESOLUTION_M = 0.1  # one occupancy cell
WIDTH_M, HEIGHT_M = 30.0, 16.0
SPEED_M_S = 0.5  # the leader's cruising speed along its route
# the route: a loop around the central rubble field; its first leg is the straight part
ROUTE: tuple[tuple[float, float], ...] = (
    (2.0, 3.0),
    (26.0, 3.0),
    (26.0, 12.5),
    (2.0, 12.5),
)
# survivors, lying beside the route where a forward camera sees them on the way past
SURVIVORS: tuple[tuple[float, float], ...] = ((11.0, 1.2), (27.8, 7.5), (16.0, 14.3))
# things that look like a survivor to one camera only: fusion must reject them
HOT_SPOTS: tuple[tuple[float, float], ...] = ((20.0, 1.2),)  # warm, not coloured (a pipe)
ORANGE_THINGS: tuple[tuple[float, float], ...] = ((7.0, 14.3),)  # coloured, cold (a barrel)

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class World:
    seed: int
    occupied: npt.NDArray[np.bool_]  # [row=y, col=x], True = obstacle
    distance: Array  # metres from each cell to the nearest obstacle (the likelihood field)
    route: tuple[tuple[float, float], ...]
    survivors: tuple[tuple[float, float], ...]

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.occupied.shape
        return rows, cols

    def cell(self, x: Array | float, y: Array | float) -> tuple[npt.NDArray[np.intp], ...]:
        """Grid indices (row, col) of points, clipped to the map."""
        rows, cols = self.shape
        c = np.clip((np.asarray(x) / RESOLUTION_M).astype(np.intp), 0, cols - 1)
        r = np.clip((np.asarray(y) / RESOLUTION_M).astype(np.intp), 0, rows - 1)
        return r, c

    def blocked(self, x: Array, y: Array) -> npt.NDArray[np.bool_]:
        r, c = self.cell(x, y)
        out: npt.NDArray[np.bool_] = self.occupied[r, c]
        return out

    def cast(
        self, x: float, y: float, angles: Array, max_range: float, step: float = 0.05
    ) -> Array:
        """Ray casting: the range to the first obstacle along each angle (max_range if none)."""
        steps = np.arange(step, max_range + step, step)
        xs = x + np.cos(angles)[:, None] * steps[None, :]
        ys = y + np.sin(angles)[:, None] * steps[None, :]
        hit = np.asarray(self.blocked(xs, ys), dtype=bool)
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), len(steps) - 1)
        ranges: Array = np.where(hit.any(axis=1), steps[first], max_range)
        return ranges

    def line_of_sight(
        self, x0: float, y0: float, x1: Array | float, y1: Array | float
    ) -> npt.NDArray[np.bool_]:
        """Whether each target point is visible from (x0, y0): no obstacle strictly between."""
        tx, ty = np.atleast_1d(x1), np.atleast_1d(y1)
        t = np.linspace(0.0, 1.0, 40)[None, 1:-4]  # stop short of the target's own cell
        xs = x0 + (tx[:, None] - x0) * t
        ys = y0 + (ty[:, None] - y0) * t
        seen = np.asarray(~self.blocked(xs, ys).any(axis=1), dtype=bool)
        return seen


@functools.lru_cache(maxsize=4)
def world(seed: int = 7) -> World:
    """The disaster site of a seed: outer walls, a rubble field inside the loop, scattered
    debris and pillars along the corridors (features the laser can localise against)."""
    rng = np.random.default_rng(seed)
    cols, rows = round(WIDTH_M / RESOLUTION_M), round(HEIGHT_M / RESOLUTION_M)
    occ = np.zeros((rows, cols), dtype=bool)

    def block(x0: float, y0: float, x1: float, y1: float) -> None:
        r0, r1 = round(y0 / RESOLUTION_M), round(y1 / RESOLUTION_M)
        c0, c1 = round(x0 / RESOLUTION_M), round(x1 / RESOLUTION_M)
        occ[max(r0, 0) : r1, max(c0, 0) : c1] = True

    block(0, 0, WIDTH_M, 0.3)  # outer walls
    block(0, HEIGHT_M - 0.3, WIDTH_M, HEIGHT_M)
    block(0, 0, 0.3, HEIGHT_M)
    block(WIDTH_M - 0.3, 0, WIDTH_M, HEIGHT_M)
    block(5.0, 5.5, 23.0, 10.0)  # the collapsed building inside the loop
    # rubble along the walls and pillars beside the corridors: the along-track features
    for x in np.arange(3.0, 26.0, 2.5):
        x0 = float(x + rng.uniform(-0.4, 0.4))
        block(x0, 0.3, x0 + float(rng.uniform(0.3, 0.8)), 0.3 + float(rng.uniform(0.3, 0.7)))
        x1 = float(x + rng.uniform(-0.4, 0.4))
        block(x1, 15.7 - float(rng.uniform(0.3, 0.7)), x1 + float(rng.uniform(0.3, 0.8)), 15.7)
    for y in np.arange(4.0, 12.0, 2.0):
        y0 = float(y + rng.uniform(-0.3, 0.3))
        block(29.7 - float(rng.uniform(0.3, 0.6)), y0, 29.7, y0 + float(rng.uniform(0.3, 0.7)))
    for _ in range(25):  # debris on the rubble field's edge
        x = float(rng.uniform(5.0, 23.0))
        y = float(rng.choice([5.5 - 0.3, 10.0]))
        block(x, y, x + 0.3, y + 0.3)
    for sx, sy in SURVIVORS + HOT_SPOTS + ORANGE_THINGS:  # keep a survivor's own cell free
        r0, r1 = round((sy - 0.4) / RESOLUTION_M), round((sy + 0.4) / RESOLUTION_M)
        c0, c1 = round((sx - 0.4) / RESOLUTION_M), round((sx + 0.4) / RESOLUTION_M)
        occ[r0:r1, c0:c1] = False
    from scipy import ndimage  # not at import: see __init__

    distance = ndimage.distance_transform_edt(~occ) * RESOLUTION_M
    return World(seed, occ, distance, ROUTE, SURVIVORS)


# -- the leader's ground truth ------------------------------------------------------------------
def _legs() -> tuple[Array, Array]:
    pts = np.array((*ROUTE, ROUTE[0]), dtype=float)
    lengths = np.hypot(*(pts[1:] - pts[:-1]).T)
    return pts, np.concatenate(([0.0], np.cumsum(lengths)))


def route_length() -> float:
    return float(_legs()[1][-1])


def true_pose(t: float) -> tuple[float, float, float]:
    """Where the leader is at time t: driving the route's loop at SPEED_M_S, forever."""
    pts, cum = _legs()
    s = (SPEED_M_S * t) % cum[-1]
    leg = int(np.searchsorted(cum, s, side="right") - 1)
    a, b = pts[leg], pts[leg + 1]
    f = (s - cum[leg]) / (cum[leg + 1] - cum[leg])
    x, y = a + f * (b - a)
    return float(x), float(y), math.atan2(b[1] - a[1], b[0] - a[0])


def on_straight(t: float) -> bool:
    """Whether time t is on the route's first leg (the straight part), away from its ends."""
    cum = _legs()[1]
    s = float((SPEED_M_S * t) % cum[-1])
    return 1.0 <= s <= float(cum[1]) - 1.0


def wrap(angle: Array | float) -> Array:
    out: Array = (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi
    return out
