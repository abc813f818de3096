"""The leader's sensors (paper §4): a 180-beam laser scanner (ray casting in the map, ~967 B a
scan at 5 Hz), odometry with drift (~38 B at 5 Hz), and a visible and an infrared camera (~3 KB
frames at 0.5 Hz) in which the planted survivors appear when in view.

A source's simulated time is its sequence number over its rate, so every reading is a pure
function of (seed, seq): the world's clock is the sensor's, not the host's. Simulating the world
(ray casting, rendering a frame, integrating the true motion) is the hardware's part and runs
inside ``not_charged``: a robot is charged only for packing the reading, as a real driver would.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from mso.examples.convoy.world import (
    HOT_SPOTS,
    ORANGE_THINGS,
    SURVIVORS,
    Array,
    World,
    true_pose,
    world,
    wrap,
)
from mso.runtime.worker import not_charged

BEAMS = 180
ANGLE_MIN = -math.pi / 2
ANGLE_STEP = math.pi / BEAMS
RANGE_MAX_M = 10.0
LASER_HZ = 5.0
CAMERA_HZ = 0.5
FOV_RAD = math.radians(60.0)
CAMERA_RANGE_M = 8.0
CAMERA_HEIGHT_M = 0.5
# frame geometry: ~3 KB a frame either way
VISIBLE_SHAPE = (25, 40, 3)  # rows, columns, RGB
INFRARED_SHAPE = (50, 60)


class LaserScan(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    ranges: bytes  # BEAMS float32 metres, from ANGLE_MIN counter-clockwise by ANGLE_STEP
    intensity: bytes  # BEAMS uint8 return strengths


class Odometry(msgspec.Struct, frozen=True, array_like=True):
    """Dead reckoning, cumulative since the start: millimetres and milliradians."""

    seq: int
    stamp: float
    x_mm: int
    y_mm: int
    theta_mrad: int
    v_mm_s: int
    w_mrad_s: int


class Image(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    camera: str  # "visible" (RGB) or "infrared" (8-bit intensity)
    rows: int
    cols: int
    pixels: bytes
    pose: tuple[float, float, float]  # the odometry pose the frame was taken at


def scan_ranges(scan: LaserScan) -> Array:
    out: Array = np.frombuffer(scan.ranges, dtype="<f4").astype(np.float64)
    return out


def beam_angles() -> Array:
    out: Array = ANGLE_MIN + ANGLE_STEP * np.arange(BEAMS, dtype=np.float64)
    return out


class Odometer:
    """Integrates the true motion with a wheel-scale error, a heading bias and noise: the
    dead-reckoning drift the localization has to correct."""

    SCALE_ERROR = 0.02  # wheels 2% larger than calibrated
    HEADING_BIAS = math.radians(0.3)  # per metre driven
    NOISE_DS, NOISE_DTH = 0.004, math.radians(0.15)

    def __init__(self, seed: int, hz: float = LASER_HZ) -> None:
        self.seed, self.hz = seed, hz
        self.k = 0
        self.pose = true_pose(0.0)
        self.v = self.w = 0.0

    def at(self, k: int) -> tuple[float, float, float]:
        """The odometry pose at reading k (integrating forward; readings only go forward)."""
        while self.k < k:
            self.k += 1
            t0, t1 = (self.k - 1) / self.hz, self.k / self.hz
            a, b = true_pose(t0), true_pose(t1)
            ds = math.hypot(b[0] - a[0], b[1] - a[1])
            dth = float(wrap(b[2] - a[2]))
            noise = np.random.default_rng([self.seed, 1, self.k]).normal(size=2)
            ds_m = ds * (1 + self.SCALE_ERROR) + self.NOISE_DS * noise[0] * (ds > 0)
            dth_m = dth + self.HEADING_BIAS * ds + self.NOISE_DTH * noise[1] * (ds > 0)
            x, y, th = self.pose
            mid = th + dth_m / 2
            self.pose = (
                float(x + ds_m * math.cos(mid)),
                float(y + ds_m * math.sin(mid)),
                float(wrap(th + dth_m)),
            )
            self.v, self.w = float(ds_m * self.hz), float(dth_m * self.hz)
        return self.pose


class LaserSource:
    """The laser scanner: ray casting from the leader's true pose, with range noise, dropouts
    (max range) and dust (spurious short returns) for the scan filter to remove."""

    def __init__(self, seed: int = 7, hz: float = LASER_HZ) -> None:
        self.world: World = world(seed)
        self.seed, self.hz = seed, hz

    def __call__(self, seq: int, now: float) -> LaserScan:
        with not_charged():  # the scanner's hardware
            x, y, th = true_pose(seq / self.hz)
            ranges = self.world.cast(x, y, th + beam_angles(), RANGE_MAX_M)
            rng = np.random.default_rng([self.seed, 2, seq])
            ranges = ranges + rng.normal(0.0, 0.02, BEAMS)
            ranges[rng.random(BEAMS) < 0.02] = RANGE_MAX_M  # dropouts
            dust = rng.random(BEAMS) < 0.02
            ranges[dust] = rng.uniform(0.1, 1.0, int(dust.sum()))
            ranges = np.clip(ranges, 0.0, RANGE_MAX_M)
            noise = rng.normal(0, 5, BEAMS)
            intensity = np.clip(200 - 15 * ranges + noise, 0, 255).astype(np.uint8)
        return LaserScan(
            seq=seq,
            stamp=now,
            ranges=ranges.astype("<f4").tobytes(),
            intensity=intensity.tobytes(),
        )


class OdometrySource:
    def __init__(self, seed: int = 7, hz: float = LASER_HZ) -> None:
        self.odometer = Odometer(seed, hz)

    def __call__(self, seq: int, now: float) -> Odometry:
        with not_charged():  # the wheel encoders
            x, y, th = self.odometer.at(seq)
        o = self.odometer
        return Odometry(
            seq=seq,
            stamp=now,
            x_mm=round(x * 1e3),
            y_mm=round(y * 1e3),
            theta_mrad=round(th * 1e3),
            v_mm_s=round(o.v * 1e3),
            w_mrad_s=round(o.w * 1e3),
        )


def in_view(
    w: World, pose: tuple[float, float, float], points: tuple[tuple[float, float], ...]
) -> list[tuple[float, float]]:
    """(bearing, distance) of each point the forward cameras see from ``pose``."""
    x, y, th = pose
    out = []
    for px, py in points:
        d = math.hypot(px - x, py - y)
        b = float(wrap(math.atan2(py - y, px - x) - th))
        if abs(b) < FOV_RAD / 2 and 0.5 < d < CAMERA_RANGE_M and w.line_of_sight(x, y, px, py)[0]:
            out.append((b, d))
    return out


class CameraSource:
    """A forward camera, visible (RGB) or infrared: a survivor is an orange, warm patch; the
    scene also holds a warm pipe and an orange barrel, each seen by one camera only."""

    def __init__(self, camera: str = "visible", seed: int = 7, hz: float = CAMERA_HZ) -> None:
        if camera not in ("visible", "infrared"):
            raise ValueError(f"camera: expected 'visible' or 'infrared', got {camera!r}")
        self.camera, self.seed, self.hz = camera, seed, hz
        self.world = world(seed)
        self.odometer = Odometer(seed)

    def objects(self) -> tuple[tuple[float, float], ...]:
        extra = ORANGE_THINGS if self.camera == "visible" else HOT_SPOTS
        return SURVIVORS + extra

    def __call__(self, seq: int, now: float) -> Image:
        with not_charged():  # the camera's sensor
            pixels, odo = self._render(seq)
        rows, cols = VISIBLE_SHAPE[:2] if self.camera == "visible" else INFRARED_SHAPE
        return Image(seq, now, self.camera, rows, cols, pixels, odo)

    def _render(self, seq: int) -> tuple[bytes, tuple[float, float, float]]:
        t = seq / self.hz
        pose = true_pose(t)
        rng = np.random.default_rng([self.seed, 3 if self.camera == "visible" else 4, seq])
        shape = VISIBLE_SHAPE if self.camera == "visible" else INFRARED_SHAPE
        rows, cols = shape[0], shape[1]
        if self.camera == "visible":  # rubble: grey-brown with texture
            img = np.array([110.0, 100.0, 90.0]) + rng.normal(0, 12, shape)
        else:  # ambient temperature
            img = 70.0 + rng.normal(0, 8, shape)
        for b, d in in_view(self.world, pose, self.objects()):
            half_w = math.atan2(0.35, d) / FOV_RAD * cols  # a 0.7 m wide figure
            centre = (0.5 - b / FOV_RAD) * cols  # bearing left (+) is image left
            c0, c1 = max(0, round(centre - half_w)), min(cols, round(centre + half_w) + 1)
            top = rows // 2 + round(math.atan2(CAMERA_HEIGHT_M - 0.4, d) / FOV_RAD * cols)
            bottom = rows // 2 + round(math.atan2(CAMERA_HEIGHT_M, d) / FOV_RAD * cols) + 1
            r0, r1 = max(0, top), min(rows, bottom)
            patch = (slice(r0, r1), slice(c0, c1))
            if self.camera == "visible":
                img[patch] = np.array([230.0, 110.0, 40.0]) + rng.normal(0, 8, img[patch].shape)
            else:
                img[patch] = 200.0 + rng.normal(0, 8, img[patch].shape)
        pixels = np.clip(img, 0, 255).astype(np.uint8).tobytes()
        return pixels, self.odometer.at(round(t * LASER_HZ))
