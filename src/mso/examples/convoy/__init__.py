"""The robotics convoy of the MSO paper (§4, Fig. 6) as real processing on generated data.

A leader robot drives a loop through a generated disaster site (``world``) carrying a laser
scanner, odometry and two cameras (``sensors``). Its navigation pipeline filters scans, localises
with a particle filter (``localization``), plans with A* and follows the path (``planning``);
its target pipeline detects coloured and warm blobs, fuses both cameras, keeps a Bayesian
per-cell target map (``vision``); the trailing robot logs every result in SQLite (``storage``).

The app files name these by ``mso.examples.convoy:Name``; everything is re-exported here.
Importing this package stays cheap (no scipy at import time): a node resolves an app's import
paths on its control plane when it validates the app, and a second spent importing there would
hold its heartbeats back long enough for its neighbours to declare it failed. The heavy work
(building the world, importing scipy) happens when a vertex is created, in its worker.
"""

from mso.examples.convoy.localization import (
    FilteredScan,
    Localizer,
    OdomDelta,
    OdomFilter,
    Pose,
    ScanFilter,
    ScanMatcher,
    ScanPoints,
)
from mso.examples.convoy.planning import PathPlan, PathPlanner, Trajectory, TrajectoryFollower
from mso.examples.convoy.sensors import (
    CameraSource,
    Image,
    LaserScan,
    LaserSource,
    Odometry,
    OdometrySource,
)
from mso.examples.convoy.storage import Storage
from mso.examples.convoy.vision import (
    BayesFilter,
    BlobDetector,
    BlobFusion,
    Blobs,
    Detections,
    TargetBelief,
    TargetMap,
    TargetReport,
)

__all__ = [
    "BayesFilter",
    "BlobDetector",
    "BlobFusion",
    "Blobs",
    "CameraSource",
    "Detections",
    "FilteredScan",
    "Image",
    "LaserScan",
    "LaserSource",
    "Localizer",
    "OdomDelta",
    "OdomFilter",
    "Odometry",
    "OdometrySource",
    "PathPlan",
    "PathPlanner",
    "Pose",
    "ScanFilter",
    "ScanMatcher",
    "ScanPoints",
    "Storage",
    "TargetBelief",
    "TargetMap",
    "TargetReport",
    "Trajectory",
    "TrajectoryFollower",
]
