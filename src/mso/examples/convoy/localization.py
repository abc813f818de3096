"""The navigation front end: scan filtering, scan end points, odometry increments, and a
vectorised particle filter that localises the leader against the map (likelihood field model,
Thrun et al., *Probabilistic Robotics*, §6.4 and §8.3).
"""

from __future__ import annotations

import json
import math
from collections import deque
from typing import Any

import msgspec
import numpy as np

from mso.examples.convoy.sensors import (
    RANGE_MAX_M,
    LaserScan,
    Odometry,
    beam_angles,
    scan_ranges,
)
from mso.examples.convoy.world import Array, true_pose, world, wrap


class FilteredScan(msgspec.Struct, frozen=True, array_like=True):
    """The scan with spikes and dropouts removed. Ranges travel as whole millimetres (uint16,
    0 = invalid): the laser's own noise is 20 mm, and half the bytes of float32 is half the
    radio energy wherever the next vertex runs on another robot."""

    seq: int
    stamp: float
    ranges_mm: bytes  # uint16 millimetres, 0 where the beam is invalid (dropout, dust)


class ScanPoints(msgspec.Struct, frozen=True, array_like=True):
    """Every ``step``-th beam of the filtered scan, what the particle filter matches to the map.
    Ranges travel as uint16 millimetres (0 = invalid) with the beam angles implied, as a
    laser driver sends them: end points as int16 x, y pairs took twice the bytes, and this
    edge crosses the radio at 5 Hz wherever the localizer runs off the leader. The consumer
    turns them into end points (:func:`scan_points`)."""

    seq: int
    stamp: float
    step: int  # beam i of this scan is beam i * step of the laser
    ranges_mm: bytes  # uint16 millimetres, 0 where the beam is invalid


def filtered_ranges(scan: FilteredScan) -> Array:
    """A filtered scan's ranges in metres, NaN where invalid."""
    mm = np.frombuffer(scan.ranges_mm, dtype="<u2")
    out: Array = np.where(mm == 0, np.nan, mm / 1e3)
    return out


def scan_points(scan: ScanPoints) -> tuple[Array, Array]:
    """A scan's valid end points in metres (robot frame)."""
    a = beam_angles()[:: max(1, scan.step)]
    mm = np.frombuffer(scan.ranges_mm, dtype="<u2")[: len(a)]  # extra ranges: no such beam
    a = a[: len(mm)]
    ok = mm > 0
    r = mm[ok] / 1e3
    xs: Array = r * np.cos(a[ok])
    ys: Array = r * np.sin(a[ok])
    return xs, ys


class OdomDelta(msgspec.Struct, frozen=True, array_like=True):
    """Motion since the previous odometry reading, in that reading's robot frame. Encoded as
    an array (no field names): it and Pose cross the radio at 5 Hz, a third of their bytes
    were names."""

    seq: int
    stamp: float
    dx: float
    dy: float
    dtheta: float


class Pose(msgspec.Struct, frozen=True, array_like=True):
    """The localizer's estimate. Travels as whole millimetres and milliradians, as Odometry
    does (about 33 bytes instead of 76: it crosses the radio at 5 Hz on two edges); read it
    in metres and radians through the properties, build it with :meth:`of`."""

    seq: int  # the laser scan this estimate answers
    stamp: float  # that scan's time at the source
    odom_seq: int  # the last odometry reading it includes
    x_mm: int
    y_mm: int
    theta_mrad: int
    spread_mm: int  # standard deviation of the particle positions
    # the odometry pose (dead reckoning, drift included) at ``odom_seq``: with the estimate it
    # gives the map -> odom correction, so a consumer puts odometry-stamped data (a camera
    # frame) in the map frame — what ROS's amcl publishes as its map -> odom transform
    odom_mm: tuple[int, int, int]  # x, y (mm), theta (mrad)

    @classmethod
    def of(
        cls,
        seq: int,
        stamp: float,
        odom_seq: int,
        pose: tuple[float, float, float],
        spread: float,
        odom: tuple[float, float, float],
    ) -> Pose:
        """From metres and radians."""
        return cls(seq, stamp, odom_seq, *_milli(pose), round(spread * 1e3), _milli(odom))

    @property
    def x(self) -> float:
        return self.x_mm / 1e3

    @property
    def y(self) -> float:
        return self.y_mm / 1e3

    @property
    def theta(self) -> float:
        return self.theta_mrad / 1e3

    @property
    def spread(self) -> float:
        return self.spread_mm / 1e3

    @property
    def odom(self) -> tuple[float, float, float]:
        x, y, th = self.odom_mm
        return (x / 1e3, y / 1e3, th / 1e3)


def _milli(pose: tuple[float, float, float]) -> tuple[int, int, int]:
    return (round(pose[0] * 1e3), round(pose[1] * 1e3), round(pose[2] * 1e3))


def map_from_odom(pose: Pose) -> tuple[float, float, float]:
    """The transform taking odometry-frame poses to the map frame: estimate ∘ odom⁻¹."""
    return compose((pose.x, pose.y, pose.theta), inverse(pose.odom))


def inverse(t: tuple[float, float, float]) -> tuple[float, float, float]:
    """The 2-D rigid transform that undoes ``t``."""
    c, s = math.cos(t[2]), math.sin(t[2])
    return (-(c * t[0] + s * t[1]), s * t[0] - c * t[1], -t[2])


def compose(
    t: tuple[float, float, float], p: tuple[float, float, float]
) -> tuple[float, float, float]:
    """``t`` applied to the pose ``p`` (2-D rigid transforms)."""
    c, s = math.cos(t[2]), math.sin(t[2])
    return (t[0] + c * p[0] - s * p[1], t[1] + s * p[0] + c * p[1], float(wrap(t[2] + p[2])))


class ScanFilter:
    """Removes isolated spikes (dust) with a median over 5 beams and marks dropouts invalid."""

    def __init__(self) -> None:
        # scipy at creation, in the worker: not at import (see mso.examples.convoy), and not at
        # the first scan either, where its ~150 ms import held up the flow and every remap
        # waiting for it to drain
        from scipy import ndimage

        self._median = ndimage.median_filter

    def __call__(self, scan: LaserScan) -> FilteredScan:
        r = scan_ranges(scan)
        smooth = self._median(r, size=5, mode="nearest")
        bad = (smooth >= RANGE_MAX_M * 0.99) | (smooth < 0.15) | (np.abs(r - smooth) > 0.3)
        mm = np.where(bad, 0, np.clip(np.rint(smooth * 1e3), 1, 65535)).astype("<u2")
        return FilteredScan(scan.seq, scan.stamp, mm.tobytes())


class ScanMatcher:
    """Thins the filtered scan to every ``step``-th beam for the particle filter: 1° apart,
    neighbouring beams end in the same 0.1 m map cell out to 5.7 m, so the beams in between
    add cost more than information."""

    def __init__(self, step: int = 2) -> None:
        self.step = step

    def __call__(self, scan: FilteredScan) -> ScanPoints:
        mm = np.frombuffer(scan.ranges_mm, dtype="<u2")[:: self.step]
        return ScanPoints(scan.seq, scan.stamp, self.step, mm.tobytes())


class OdomFilter:
    """Cumulative odometry to increments; stateful (the previous reading)."""

    def __init__(self) -> None:
        self.last: tuple[float, float, float] | None = None

    def __call__(self, odo: Odometry) -> OdomDelta | None:
        pose = (odo.x_mm / 1e3, odo.y_mm / 1e3, odo.theta_mrad / 1e3)
        last, self.last = self.last, pose
        if last is None:
            return None
        dxw, dyw = pose[0] - last[0], pose[1] - last[1]
        c, s = math.cos(last[2]), math.sin(last[2])
        return OdomDelta(
            odo.seq,
            odo.stamp,
            c * dxw + s * dyw,
            -s * dxw + c * dyw,
            float(wrap(pose[2] - last[2])),
        )

    def get_state(self) -> list[float] | None:
        return None if self.last is None else list(self.last)

    def set_state(self, state: list[float] | None) -> None:
        self.last = None if state is None else (state[0], state[1], state[2])


class Localizer:
    """A particle filter: odometry increments move the particles (with noise wide enough for the
    odometer's drift), each scan weighs them by how well its end points fall on the map's
    obstacles, and low-variance resampling keeps the set healthy. Stateful: the particle set
    moves with the vertex."""

    SIGMA_HIT = 0.15  # metres: the likelihood field's spread
    MAX_DIST = 0.5  # a point further than this from any obstacle counts as noise

    def __init__(self, seed: int = 7, particles: int = 1000) -> None:
        self.world = world(seed)
        self.rng = np.random.default_rng([seed, 9])
        self.n = particles
        x, y, th = true_pose(0.0)  # the convoy starts at a known spot: pose tracking
        self.p: Array = np.column_stack(
            (
                x + self.rng.normal(0, 0.1, particles),
                y + self.rng.normal(0, 0.1, particles),
                th + self.rng.normal(0, math.radians(3), particles),
            )
        )
        self.w: Array = np.full(particles, 1.0 / particles)
        self.odom_seq = 0  # reading 0 is the start: no motion before it
        # the odometry pose, integrated from the increments: odometry starts at the same spot
        self.odom: tuple[float, float, float] = (x, y, th)
        self.scan_seq = -1  # the last scan weighed
        # the two inputs come by different paths (over different robots), so either may run
        # ahead: they are merged back into time order (odometry j moves the particles from
        # scan j-1 to scan j) before the filter sees them
        self.odoms: deque[OdomDelta] = deque()
        self.scans: deque[ScanPoints] = deque()

    MAX_WAITING = 50  # scans held for their odometry at most (10 s at 5 Hz)

    def __call__(self, event: OdomDelta | ScanPoints) -> list[Pose]:
        if isinstance(event, OdomDelta):
            self.odoms.append(event)
        else:
            self.scans.append(event)
        poses = []
        while True:
            if self.odoms and self.odoms[0].seq <= self.scan_seq + 1:
                self.predict(self.odoms.popleft())
            elif self.scans and (
                self.scans[0].seq <= self.odom_seq or len(self.scans) > self.MAX_WAITING
            ):
                scan = self.scans.popleft()
                self.update(scan)
                self.scan_seq = scan.seq
                poses.append(self.estimate(scan))
            else:
                return poses

    def predict(self, d: OdomDelta) -> None:
        n, p = self.n, self.p
        ds = math.hypot(d.dx, d.dy)
        dx = d.dx + self.rng.normal(0, 0.04 * ds + 0.003, n)
        dy = d.dy + self.rng.normal(0, 0.02 * ds + 0.003, n)
        dth = d.dtheta + self.rng.normal(0, 0.05 * abs(d.dtheta) + 0.01 * ds + 0.002, n)
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        p[:, 0] += c * dx - s * dy
        p[:, 1] += s * dx + c * dy
        p[:, 2] = wrap(p[:, 2] + dth)
        if d.seq > self.odom_seq:
            self.odom = compose(self.odom, (d.dx, d.dy, d.dtheta))
        self.odom_seq = max(self.odom_seq, d.seq)

    def update(self, scan: ScanPoints) -> None:
        xs, ys = scan_points(scan)
        if len(xs) == 0:
            return
        p = self.p
        c, s = np.cos(p[:, 2:3]), np.sin(p[:, 2:3])
        wx = p[:, 0:1] + c * xs[None, :] - s * ys[None, :]
        wy = p[:, 1:2] + s * xs[None, :] + c * ys[None, :]
        r, col = self.world.cell(wx, wy)
        dist = np.minimum(self.world.distance[r, col], self.MAX_DIST)
        # the beams are not independent: temper the joint likelihood (one tenth per beam)
        loglik = -0.5 * ((dist / self.SIGMA_HIT) ** 2).sum(axis=1) / 10.0
        logw = np.log(self.w + 1e-300) + loglik
        w = np.exp(logw - logw.max())
        self.w = w / w.sum()
        if 1.0 / float(np.sum(self.w**2)) < self.n / 2:
            self.resample()

    def resample(self) -> None:
        """Low-variance (systematic) resampling."""
        positions = (self.rng.random() + np.arange(self.n)) / self.n
        idx = np.minimum(np.searchsorted(np.cumsum(self.w), positions), self.n - 1)
        self.p = self.p[idx].copy()
        self.w = np.full(self.n, 1.0 / self.n)

    def estimate(self, scan: ScanPoints) -> Pose:
        w, p = self.w, self.p
        x, y = float(w @ p[:, 0]), float(w @ p[:, 1])
        th = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
        spread = math.sqrt(float(w @ ((p[:, 0] - x) ** 2 + (p[:, 1] - y) ** 2)))
        return Pose.of(scan.seq, scan.stamp, self.odom_seq, (x, y, th), spread, self.odom)

    def get_state(self) -> dict[str, Any]:
        return {
            "p": self.p.astype("<f8").tobytes(),
            "w": self.w.astype("<f8").tobytes(),
            "odom_seq": self.odom_seq,
            "odom": list(self.odom),
            "scan_seq": self.scan_seq,
            "odoms": [msgspec.msgpack.encode(e) for e in self.odoms],
            "scans": [msgspec.msgpack.encode(e) for e in self.scans],
            "rng": json.dumps(self.rng.bit_generator.state),  # 128-bit ints: not msgpack
        }

    def set_state(self, state: dict[str, Any]) -> None:
        self.p = np.frombuffer(state["p"], dtype="<f8").reshape(-1, 3).copy()
        self.w = np.frombuffer(state["w"], dtype="<f8").copy()
        self.n = len(self.w)
        self.odom_seq = int(state["odom_seq"])
        ox, oy, oth = (float(v) for v in state["odom"])
        self.odom = (ox, oy, oth)
        self.scan_seq = int(state["scan_seq"])
        self.odoms = deque(msgspec.msgpack.decode(r, type=OdomDelta) for r in state["odoms"])
        self.scans = deque(msgspec.msgpack.decode(r, type=ScanPoints) for r in state["scans"])
        self.rng.bit_generator.state = json.loads(state["rng"])
