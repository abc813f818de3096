"""Stand-in vertex code and event formats for the robotics convoy app (paper Fig. 6).

The sizes match the paper's data: laser scans of 967 B and odometry of 38 B at 5 events/s,
camera frames of about 3 KB at 0.5 events/s. The processing is deliberately simple; it exists
so the app runs end to end and so stateful vertices have state worth moving.
"""

from __future__ import annotations

import math

import msgspec


class LaserScan(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    ranges: bytes  # 180 beams, quantised


class Odometry(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    x: float
    y: float
    theta: float


class Pose(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    x: float
    y: float
    theta: float
    quality: float


class PathPlan(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    waypoints: list[tuple[float, float]]


class Image(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    camera: str
    pixels: bytes


class Blobs(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    camera: str
    blobs: list[tuple[float, float, float]]  # x, y, area


class TargetBelief(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    probability: float


class Record(msgspec.Struct, frozen=True):
    kind: str
    seq: int
    stamp: float
    payload: bytes


class LaserSource:
    """Synthetic laser scanner: a scan of a corridor that drifts slowly."""

    def __call__(self, seq: int, now: float) -> LaserScan:
        ranges = bytes((100 + int(50 * math.sin((seq + i) / 20.0))) % 256 for i in range(926))
        return LaserScan(seq=seq, stamp=now, ranges=ranges)


class OdometrySource:
    def __call__(self, seq: int, now: float) -> Odometry:
        return Odometry(seq=seq, stamp=now, x=0.1 * seq, y=0.0, theta=0.0)


class CameraSource:
    def __init__(self, camera: str = "visible") -> None:
        self.camera = camera

    def __call__(self, seq: int, now: float) -> Image:
        return Image(seq=seq, stamp=now, camera=self.camera, pixels=bytes(2960))


class Passthrough:
    """An operator that forwards what it gets (filters, smoothing stand-ins)."""

    def __call__(self, event: msgspec.Struct) -> msgspec.Struct:
        return event


class Localizer:
    """Fuses odometry and scans into a pose; stateful (the last pose and a counter)."""

    def __init__(self) -> None:
        self.count = 0
        self.pose = (0.0, 0.0, 0.0)

    def __call__(self, event: LaserScan | Odometry) -> Pose | None:
        self.count += 1
        if isinstance(event, Odometry):
            self.pose = (event.x, event.y, event.theta)
            return None
        quality = sum(event.ranges[:32]) / (32 * 255)
        x, y, t = self.pose
        return Pose(seq=event.seq, stamp=event.stamp, x=x, y=y, theta=t, quality=quality)

    def get_state(self) -> dict[str, object]:
        return {"count": self.count, "pose": list(self.pose)}

    def set_state(self, state: dict[str, object]) -> None:
        self.count = int(state["count"])  # type: ignore[call-overload]
        pose = state["pose"]
        assert isinstance(pose, list)
        self.pose = (float(pose[0]), float(pose[1]), float(pose[2]))


class PathPlanner:
    def __call__(self, pose: Pose) -> PathPlan:
        return PathPlan(
            seq=pose.seq, stamp=pose.stamp, waypoints=[(pose.x + k, pose.y) for k in range(5)]
        )


class BlobDetector:
    def __call__(self, image: Image) -> Blobs:
        return Blobs(seq=image.seq, stamp=image.stamp, camera=image.camera, blobs=[(1.0, 2.0, 3.0)])


class BayesFilter:
    """Bayesian target estimate; stateful (the prior)."""

    def __init__(self) -> None:
        self.prior = 0.01

    def __call__(self, blobs: Blobs) -> TargetBelief:
        likelihood = 0.6 if blobs.blobs else 0.1
        self.prior = likelihood * self.prior / (likelihood * self.prior + 0.3 * (1 - self.prior))
        return TargetBelief(seq=blobs.seq, stamp=blobs.stamp, probability=self.prior)

    def get_state(self) -> float:
        return self.prior

    def set_state(self, state: float) -> None:
        self.prior = float(state)


class Storage:
    """The trailing robot's log: counts what arrives per kind."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def __call__(self, event: msgspec.Struct) -> None:
        kind = type(event).__name__
        self.counts[kind] = self.counts.get(kind, 0) + 1
