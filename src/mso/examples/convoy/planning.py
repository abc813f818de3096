"""Path planning and trajectory: A* on a coarse, obstacle-inflated copy of the map toward the
route's next waypoint, then a pure-pursuit command along that path."""

from __future__ import annotations

import heapq
import math
from typing import Any

import msgspec
import numpy as np
import numpy.typing as npt

from mso.examples.convoy.localization import Pose
from mso.examples.convoy.world import RESOLUTION_M, SPEED_M_S, World, world, wrap

PLAN_CELL_M = 0.2  # the planning grid
ROBOT_RADIUS_M = 0.3  # obstacles are inflated by this much
WAYPOINT_REACHED_M = 1.0

Grid = npt.NDArray[np.bool_]
Cell = tuple[int, int]


class PathPlan(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    odom_seq: int
    pose: tuple[float, float, float]
    goal: int  # index of the route waypoint the plan leads to
    path: list[tuple[float, float]]  # metres, from the pose to the goal (empty: no path)


class Trajectory(msgspec.Struct, frozen=True):
    """What the trailing robot stores for each scan: the pose and the command derived from it."""

    seq: int
    stamp: float
    odom_seq: int
    x: float
    y: float
    theta: float
    v: float  # m/s
    w: float  # rad/s
    goal: int
    path_len: float  # metres still to go to the goal


def astar(free: Grid, start: Cell, goal: Cell) -> list[Cell] | None:
    """A* over an 8-connected grid (octile distance: admissible and consistent, so the first
    path to reach the goal is a shortest one). ``free[r, c]`` is True where the robot may be."""
    rows, cols = free.shape
    if not (free[start] and free[goal]):
        return None
    sq2 = math.sqrt(2.0)

    def h(c: Cell) -> float:
        dr, dc = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return float(max(dr, dc) + (sq2 - 1) * min(dr, dc))

    moves = [(-1, 0, 1.0), (1, 0, 1.0), (0, -1, 1.0), (0, 1, 1.0)]
    moves += [(-1, -1, sq2), (-1, 1, sq2), (1, -1, sq2), (1, 1, sq2)]
    g: dict[Cell, float] = {start: 0.0}
    came: dict[Cell, Cell] = {}
    heap: list[tuple[float, float, Cell]] = [(h(start), 0.0, start)]
    closed: set[Cell] = set()
    while heap:
        _, gc, cur = heapq.heappop(heap)
        if cur == goal:
            path = [cur]
            while cur in came:
                cur = came[cur]
                path.append(cur)
            return path[::-1]
        if cur in closed:
            continue
        closed.add(cur)
        r, c = cur
        for dr, dc, step in moves:
            nr, nc = r + dr, c + dc
            if not (0 <= nr < rows and 0 <= nc < cols) or not free[nr, nc]:
                continue
            if dr and dc and not (free[r, nc] and free[nr, c]):
                continue  # no cutting corners past an obstacle
            ng = gc + step
            nxt = (nr, nc)
            if ng < g.get(nxt, math.inf):
                g[nxt] = ng
                came[nxt] = cur
                heapq.heappush(heap, (ng + h(nxt), ng, nxt))
    return None


def planning_grid(w: World) -> Grid:
    """The map at PLAN_CELL_M, a cell blocked if any fine cell in it is, inflated by the
    robot's radius."""
    from scipy import ndimage  # not at import: see mso.examples.convoy

    k = round(PLAN_CELL_M / RESOLUTION_M)
    rows, cols = w.shape
    occ = w.occupied[: rows - rows % k, : cols - cols % k]
    coarse = occ.reshape(rows // k, k, cols // k, k).any(axis=(1, 3))
    radius = math.ceil(ROBOT_RADIUS_M / PLAN_CELL_M)
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disk = (xx**2 + yy**2) <= radius**2
    free: Grid = ~ndimage.binary_dilation(coarse, structure=disk)
    return free


class PathPlanner:
    """Plans from the estimated pose to the route's next waypoint; stateful (which waypoint is
    next, and how many laps were driven)."""

    def __init__(self, seed: int = 7) -> None:
        self.world = world(seed)
        self.free = planning_grid(self.world)
        self.goal = 1  # the route's first waypoint is the start
        self.laps = 0

    def cell(self, x: float, y: float) -> Cell:
        rows, cols = self.free.shape
        r = min(max(int(y / PLAN_CELL_M), 0), rows - 1)
        c = min(max(int(x / PLAN_CELL_M), 0), cols - 1)
        return r, c

    def nearest_free(self, cell: Cell) -> Cell:
        """The pose may sit in the inflated margin: start from the closest free cell."""
        if self.free[cell]:
            return cell
        rr, cc = np.nonzero(self.free)
        k = int(np.argmin((rr - cell[0]) ** 2 + (cc - cell[1]) ** 2))
        return int(rr[k]), int(cc[k])

    def __call__(self, pose: Pose) -> PathPlan:
        route = self.world.route
        gx, gy = route[self.goal]
        if math.hypot(gx - pose.x, gy - pose.y) < WAYPOINT_REACHED_M:
            self.goal = (self.goal + 1) % len(route)
            self.laps += self.goal == 1
            gx, gy = route[self.goal]
        start = self.nearest_free(self.cell(pose.x, pose.y))
        cells = astar(self.free, start, self.nearest_free(self.cell(gx, gy))) or []
        path = [((c + 0.5) * PLAN_CELL_M, (r + 0.5) * PLAN_CELL_M) for r, c in cells]
        return PathPlan(
            pose.seq, pose.stamp, pose.odom_seq, (pose.x, pose.y, pose.theta), self.goal, path
        )

    def get_state(self) -> dict[str, Any]:
        return {"goal": self.goal, "laps": self.laps}

    def set_state(self, state: dict[str, Any]) -> None:
        self.goal, self.laps = int(state["goal"]), int(state["laps"])


class TrajectoryFollower:
    """Pure pursuit: steer toward the path point ``lookahead`` metres ahead."""

    def __init__(self, lookahead: float = 1.0) -> None:
        self.lookahead = lookahead

    def __call__(self, plan: PathPlan) -> Trajectory:
        x, y, th = plan.pose
        pts = np.array(plan.path, dtype=float).reshape(-1, 2)
        if len(pts) < 2:
            return Trajectory(
                plan.seq, plan.stamp, plan.odom_seq, x, y, th, 0.0, 0.0, plan.goal, 0.0
            )
        seg = np.hypot(*np.diff(pts, axis=0).T)
        along = np.concatenate(([0.0], np.cumsum(seg)))
        tx, ty = pts[min(int(np.searchsorted(along, self.lookahead)), len(pts) - 1)]
        alpha = float(wrap(math.atan2(ty - y, tx - x) - th))
        curvature = 2 * math.sin(alpha) / self.lookahead
        v = SPEED_M_S * max(0.2, math.cos(alpha))
        return Trajectory(
            plan.seq, plan.stamp, plan.odom_seq, x, y, th, v, v * curvature, plan.goal,
            float(along[-1]),
        )  # fmt: skip
