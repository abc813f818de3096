"""Target recognition: colour / intensity blob detection with connected components (as CMVision
does: classify each pixel by a box threshold in YUV, then label connected regions), fusion of
the visible and infrared cameras, a Bayesian per-cell target probability map, and the list of
targets found."""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np
import numpy.typing as npt

from mso.examples.convoy.localization import Pose, compose, map_from_odom
from mso.examples.convoy.sensors import CAMERA_HEIGHT_M, CAMERA_RANGE_M, FOV_RAD, Image
from mso.examples.convoy.world import world, wrap

# CMVision-style colour class of a survivor's high-visibility clothing: a box in YUV
ORANGE_YUV = ((60.0, 255.0), (0.0, 100.0), (170.0, 255.0))  # (Y, U, V) ranges
WARM = 150  # infrared intensity of a warm body (ambient ~70)
MIN_AREA = {"visible": 2, "infrared": 3}
FIGURE_HALF_WIDTH_M = 0.35
MAP_CELL_M = 0.5  # the target probability map
PRIOR = 0.01
P_DET_HIT, P_DET_FALSE = 0.9, 0.02  # P(detection | target), P(detection | no target)
FOUND_P = 0.95
RANGE_SIGMA = 0.15  # a detection's range error, relative (its blob's width in whole pixels)


class Blobs(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    camera: str
    pose: tuple[float, float, float]
    # bearing (rad, left +), angular width (rad), pixels, range (m): from the width a figure
    # shows, or — when the frame's left or right edge cuts it, so it shows narrower than it
    # is (5.0 m for one 3.9 m away) — from where it meets the ground (flat ground, the
    # camera's known height)
    blobs: list[tuple[float, float, int, float]]


class Detections(msgspec.Struct, frozen=True):
    """Both cameras' blobs of one frame pair, matched: what both see is a candidate survivor."""

    seq: int
    stamp: float
    pose: tuple[float, float, float]
    hits: list[tuple[float, float]]  # bearing (rad), range estimate (m)
    visible: int  # blobs seen by each camera alone
    infrared: int


class TargetBelief(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    cells: list[tuple[float, float, float]]  # x, y, probability of the cells above 0.5
    max_p: float
    hits: int  # fused detections in the frame pair


class TargetReport(msgspec.Struct, frozen=True):
    seq: int
    stamp: float
    targets: list[tuple[float, float, float]]  # x, y, probability: every target found so far
    hits: int  # matched detections in this frame pair


def classify(img: Image) -> npt.NDArray[np.bool_]:
    """The pixels of the camera's target class (bool mask, rows × cols)."""
    if img.camera == "visible":
        rgb = np.frombuffer(img.pixels, np.uint8).reshape(img.rows, img.cols, 3).astype(float)
        r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
        yuv = (
            0.299 * r + 0.587 * g + 0.114 * b,
            -0.169 * r - 0.331 * g + 0.5 * b + 128,
            0.5 * r - 0.419 * g - 0.081 * b + 128,
        )
        mask = np.ones((img.rows, img.cols), dtype=bool)
        for ch, (lo, hi) in zip(yuv, ORANGE_YUV, strict=True):
            mask &= (ch >= lo) & (ch <= hi)
        return mask
    grey = np.frombuffer(img.pixels, np.uint8).reshape(img.rows, img.cols)
    out: npt.NDArray[np.bool_] = grey >= WARM
    return out


class BlobDetector:
    """Colour or intensity class, connected components (``scipy.ndimage.label``), per-blob
    area and extent, turned into bearings with the camera's field of view."""

    def __init__(self) -> None:
        from scipy import ndimage  # at creation, in the worker: see ScanFilter

        self._ndimage = ndimage

    def __call__(self, img: Image) -> Blobs:
        ndimage = self._ndimage
        mask = classify(img)
        labels, n = ndimage.label(mask)
        blobs: list[tuple[float, float, int, float]] = []
        if n:
            idx = np.arange(1, n + 1)
            areas = ndimage.sum_labels(mask, labels, idx)
            for k, sl in enumerate(ndimage.find_objects(labels)):
                if sl is None or areas[k] < MIN_AREA[img.camera]:
                    continue
                c0, c1 = sl[1].start, sl[1].stop
                centre = (c0 + c1) / 2 / img.cols
                bearing = (0.5 - centre) * FOV_RAD
                width = (c1 - c0) / img.cols * FOV_RAD
                if c0 == 0 or c1 == img.cols:  # cut by the frame: where it meets the ground
                    below = (sl[0].stop - 1 - img.rows // 2) * FOV_RAD / img.cols
                    rng = CAMERA_HEIGHT_M / math.tan(below) if below > 0 else CAMERA_RANGE_M
                else:
                    rng = FIGURE_HALF_WIDTH_M / math.tan(max(width, 1e-3) / 2)
                blobs.append((bearing, width, int(areas[k]), min(rng, CAMERA_RANGE_M)))
        return Blobs(img.seq, img.stamp, img.camera, img.pose, blobs)


class BlobFusion:
    """Pairs the two cameras' blobs of the same frame: a survivor is both coloured and warm.
    Stateful (the frames waiting for their other half)."""

    MATCH_RAD = math.radians(4.0)

    def __init__(self) -> None:
        self.pending: dict[str, Blobs] = {}  # by "camera:seq"

    def __call__(self, b: Blobs) -> Detections | None:
        other = "infrared" if b.camera == "visible" else "visible"
        twin = self.pending.pop(f"{other}:{b.seq}", None)
        if twin is None:
            self.pending[f"{b.camera}:{b.seq}"] = b
            return None
        vis, ir = (b, twin) if b.camera == "visible" else (twin, b)
        hits = []
        for ib, iw, _, rng in ir.blobs:  # the infrared camera's: it has more columns
            if any(abs(ib - vb) < self.MATCH_RAD + max(iw, vw) / 2 for vb, vw, _, _ in vis.blobs):
                hits.append((ib, rng))
        return Detections(
            b.seq, min(b.stamp, twin.stamp), ir.pose, hits, len(vis.blobs), len(ir.blobs)
        )

    def get_state(self) -> list[bytes]:
        return [msgspec.msgpack.encode(v) for v in self.pending.values()]

    def set_state(self, state: list[bytes]) -> None:
        blobs = [msgspec.msgpack.decode(s, type=Blobs) for s in state]
        self.pending = {f"{b.camera}:{b.seq}": b for b in blobs}


class BayesFilter:
    """A per-cell target probability map (log-odds, MAP_CELL_M cells). Every cell the cameras
    see is updated: toward "target" where a fused detection points, toward "none" elsewhere.

    A join: frames carry the odometry pose they were taken at, which drifts (metres within
    minutes); the localizer's poses give the map -> odom correction, and each frame is placed
    in the map by the latest one (it changes by centimetres a second, so the latest is as good
    as one at the frame's own time). Before the first pose, odometry is taken as is: it starts
    at the map's known start. Stateful: the map and the correction move with the vertex."""

    def __init__(self, seed: int = 7) -> None:
        self.world = world(seed)
        rows, cols = self.world.shape
        k = MAP_CELL_M / 0.1
        self.logodds = np.full((round(rows / k), round(cols / k)), math.log(PRIOR / (1 - PRIOR)))
        r, c = np.mgrid[0 : self.logodds.shape[0], 0 : self.logodds.shape[1]]
        self.cx, self.cy = (c.ravel() + 0.5) * MAP_CELL_M, (r.ravel() + 0.5) * MAP_CELL_M
        self.map_odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.pose_seq = -1  # the localizer's estimate the correction comes from

    def __call__(self, event: Detections | Pose) -> TargetBelief | None:
        if isinstance(event, Pose):
            if event.seq > self.pose_seq:
                self.map_odom, self.pose_seq = map_from_odom(event), event.seq
            return None
        return self.update(event)

    def update(self, det: Detections) -> TargetBelief:
        x, y, th = compose(self.map_odom, det.pose)
        d = np.hypot(self.cx - x, self.cy - y)
        bearing = wrap(np.arctan2(self.cy - y, self.cx - x) - th)
        view = np.nonzero((np.abs(bearing) < FOV_RAD / 2) & (d > 0.5) & (d < CAMERA_RANGE_M))[0]
        view = view[self.world.line_of_sight(x, y, self.cx[view], self.cy[view])]
        # how well each cell explains a detection: its bearing within 5°, and its distance
        # within the range error of the blob (whole pixels: ~15 % at range) gets the full
        # evidence, further along the ray a share falling off as a Gaussian — a full share all
        # along a wide window let the same viewpoints, lap after lap, build a phantom a couple
        # of metres behind a survivor
        weight = np.zeros(len(view))
        for b, r in det.hits:
            near = np.abs(wrap(bearing[view] - b)) < math.radians(5.0)
            sigma = max(0.5, RANGE_SIGMA * r)
            off = np.maximum(np.abs(d[view] - r) - sigma, 0.0)
            weight = np.maximum(weight, near * np.exp(-0.5 * (off / sigma) ** 2))
        hit = weight > 0.1
        flat = self.logodds.reshape(-1)
        flat[view[hit]] += weight[hit] * math.log(P_DET_HIT / P_DET_FALSE)
        flat[view[~hit]] += math.log((1 - P_DET_HIT) / (1 - P_DET_FALSE))
        np.clip(flat, -8.0, 8.0, out=flat)
        p = 1.0 / (1.0 + np.exp(-flat))
        above = np.nonzero(p > 0.5)[0]
        cells = [(float(self.cx[i]), float(self.cy[i]), float(p[i])) for i in above]
        return TargetBelief(det.seq, det.stamp, cells, float(p.max()), len(det.hits))

    def get_state(self) -> dict[str, Any]:
        return {
            "logodds": self.logodds.astype("<f4").tobytes(),
            "map_odom": list(self.map_odom),
            "pose_seq": self.pose_seq,
        }

    def set_state(self, state: dict[str, Any]) -> None:
        shape = self.logodds.shape
        self.logodds = (
            np.frombuffer(state["logodds"], dtype="<f4").astype(np.float64).reshape(shape)
        )
        mx, my, mth = (float(v) for v in state["map_odom"])
        self.map_odom, self.pose_seq = (mx, my, mth), int(state["pose_seq"])


class TargetMap:
    """Turns confident cells into targets: neighbouring cells above FOUND_P are one target at
    their probability-weighted centre. A target later seen to be nothing (its cells fall
    back below FOUND_P) is dropped. Stateful (the targets found so far, for status)."""

    LINK_M = MAP_CELL_M * 1.5

    def __init__(self) -> None:
        self.targets: list[tuple[float, float, float]] = []

    def __call__(self, belief: TargetBelief) -> TargetReport:
        clusters: list[list[tuple[float, float, float]]] = []
        for c in (c for c in belief.cells if c[2] >= FOUND_P):
            near = [
                cl
                for cl in clusters
                if any(math.hypot(c[0] - o[0], c[1] - o[1]) <= self.LINK_M for o in cl)
            ]
            for cl in near[1:]:  # c joins clusters: merge them
                near[0].extend(cl)
                clusters.remove(cl)
            if near:
                near[0].append(c)
            else:
                clusters.append([c])
        self.targets = []
        for cl in clusters:
            w = np.array([c[2] for c in cl])
            x = float(np.average([c[0] for c in cl], weights=w))
            y = float(np.average([c[1] for c in cl], weights=w))
            self.targets.append((x, y, float(w.max())))
        return TargetReport(belief.seq, belief.stamp, list(self.targets), belief.hits)

    def get_state(self) -> list[tuple[float, float, float]]:
        return self.targets

    def set_state(self, state: list[Any]) -> None:
        self.targets = [(float(t[0]), float(t[1]), float(t[2])) for t in state]

    def stats(self) -> dict[str, int]:
        return {"targets": len(self.targets)}
