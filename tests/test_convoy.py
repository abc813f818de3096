"""The convoy's vertices on known inputs (mso.examples.convoy): each does what its name says."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
from scipy.sparse import csgraph, lil_matrix

from mso.examples.convoy import (
    BayesFilter,
    BlobDetector,
    BlobFusion,
    CameraSource,
    Image,
    LaserSource,
    Localizer,
    OdometrySource,
    OdomFilter,
    PathPlanner,
    ScanFilter,
    ScanMatcher,
    Storage,
    TargetMap,
    TrajectoryFollower,
)
from mso.examples.convoy.localization import Pose, filtered_ranges, scan_points
from mso.examples.convoy.planning import astar
from mso.examples.convoy.sensors import BEAMS, in_view, scan_ranges
from mso.examples.convoy.storage import summary
from mso.examples.convoy.world import HOT_SPOTS, SURVIVORS, on_straight, true_pose, world

# the stated bound on the straight leg: the planner inflates obstacles by the robot's radius
# (0.3 m), so a pose error below it can never make a plan cut through a wall
LOCALIZATION_BOUND_M = 0.3


def test_the_laser_sees_the_walls_of_the_map() -> None:
    scan = LaserSource()(0, 0.0)
    assert 900 <= len(msgspec.msgpack.encode(scan)) <= 1000  # the paper's 967 B
    r = scan_ranges(scan)
    assert len(r) == BEAMS
    # at the start (2, 3) heading east the right-hand beam (-90°) meets the south wall at
    # y = 0.3 (or rubble on it); the left-hand one (+90°) passes west of the rubble field and
    # the north wall is 12.7 m away, beyond the 10 m range
    assert 1.5 < np.median(r[:3]) <= 2.75
    assert np.median(r[-3:]) > 9.5


def test_scan_filter_removes_dust_and_dropouts() -> None:
    scan = LaserSource()(3, 0.0)
    raw = scan_ranges(scan)
    out = filtered_ranges(ScanFilter()(scan))
    x, y, th = true_pose(3 / 5)
    truth = world(7).cast(x, y, th + -math.pi / 2 + math.pi / BEAMS * np.arange(BEAMS), 10.0)
    ok = np.isfinite(out)
    assert ok.sum() > 0.8 * (truth < 9.9).sum()  # beyond range stays invalid
    # every beam kept is near the truth; the raw scan had outliers (dust or dropouts)
    assert np.abs(out[ok] - truth[ok]).max() < 0.3
    assert (np.abs(raw - truth) > 0.3).any()


def test_scan_points_travel_as_millimetre_ranges_and_lose_under_one() -> None:
    filtered = ScanFilter()(LaserSource()(3, 0.0))
    points = ScanMatcher()(filtered)
    xs, ys = scan_points(points)
    r = filtered_ranges(filtered)[::2]
    a = (-math.pi / 2 + math.pi / BEAMS * np.arange(BEAMS))[::2]
    ok = np.isfinite(r)
    assert len(xs) == ok.sum() > 0
    assert np.abs(xs - r[ok] * np.cos(a[ok])).max() <= 0.0005 + 1e-9
    assert np.abs(ys - r[ok] * np.sin(a[ok])).max() <= 0.0005 + 1e-9
    # two bytes a beam, angles implied: half of what int16 x, y end points took
    assert len(msgspec.msgpack.encode(points)) <= 2 * len(r) + 40


def test_odometry_drifts_and_odom_filter_gives_increments() -> None:
    odo, f = OdometrySource(), OdomFilter()
    assert f(odo(0, 0.0)) is None
    d = f(odo(1, 0.2))
    assert d is not None and 0.09 < d.dx < 0.11 and abs(d.dy) < 0.01
    x, y, _ = true_pose(50.0)  # 25 m along the first leg and round the corner
    late = odo(250, 50.0)
    assert 0.1 < math.hypot(late.x_mm / 1e3 - x, late.y_mm / 1e3 - y) < 2.0
    state = f.get_state()
    g = OdomFilter()
    g.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(state)))
    assert g.last == f.last


def run_localization(loc: Localizer, scans: range) -> list[float]:
    laser, odo, f, filt, match = (
        LaserSource(),
        OdometrySource(),
        OdomFilter(),
        ScanFilter(),
        ScanMatcher(),
    )
    if scans.start > 0:  # the odometry filter's previous reading (its state, in a move)
        f(odo(scans.start - 1, 0.0))
    errors = []
    for k in scans:
        reading = odo(k, k / 5)
        d = f(reading)
        if d is not None:
            loc(d)
        poses = loc(match(filt(laser(k, k / 5))))
        assert len(poses) == 1 and poses[0].seq == k
        pose = poses[0]
        # the odometry pose it carries is the reading's, integrated back from the increments
        ox, oy, oth = pose.odom
        assert math.hypot(ox - reading.x_mm / 1e3, oy - reading.y_mm / 1e3) < 1e-3
        assert abs(oth - reading.theta_mrad / 1e3) < 1e-3
        x, y, _ = true_pose(k / 5)
        errors.append(math.hypot(pose.x - x, pose.y - y))
    return errors


def test_localization_converges_on_a_straight_run() -> None:
    """Started 0.4 m off, the particle filter pulls the estimate to the truth within a few
    metres of the straight leg, and keeps it under the bound while odometry drifts away."""
    loc = Localizer(particles=600)
    loc.p[:, 0] += 0.3
    loc.p[:, 1] -= 0.25
    errors = run_localization(loc, range(0, 200))
    assert all(on_straight(k / 5) for k in range(10, 200))
    assert errors[0] > 0.3
    assert max(errors[40:]) < LOCALIZATION_BOUND_M
    assert np.mean(errors[-50:]) < 0.2


def test_localization_state_moves_with_the_vertex() -> None:
    loc = Localizer(particles=300)
    run_localization(loc, range(0, 20))
    moved = Localizer(particles=10)
    moved.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(loc.get_state())))
    assert moved.n == 300 and np.array_equal(moved.p, loc.p)
    # both continue identically: the random generator moved too
    assert run_localization(moved, range(20, 25)) == run_localization(loc, range(20, 25))


def test_astar_finds_the_shortest_path_on_a_small_grid() -> None:
    free = np.ones((7, 9), dtype=bool)
    free[1:6, 4] = False  # a wall with gaps at the top and bottom rows
    path = astar(free, (3, 0), (3, 8))
    assert path is not None and path[0] == (3, 0) and path[-1] == (3, 8)
    assert all(free[c] for c in path)
    steps = [math.hypot(a[0] - b[0], a[1] - b[1]) for a, b in itertools.pairwise(path)]
    assert all(s in (1.0, math.sqrt(2)) for s in steps)
    # the same grid as a graph (8-connected, no corner cutting): Dijkstra agrees
    rows, cols = free.shape
    g = lil_matrix((rows * cols, rows * cols))
    for r in range(rows):
        for c in range(cols):
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    nr, nc = r + dr, c + dc
                    inside = (dr or dc) and 0 <= nr < rows and 0 <= nc < cols
                    if inside and free[r, c] and free[nr, nc] and free[r, nc] and free[nr, c]:
                        g[r * cols + c, nr * cols + nc] = math.hypot(dr, dc)
    best = csgraph.dijkstra(g.tocsr(), indices=3 * cols)[3 * cols + 8]
    assert sum(steps) == pytest.approx(best)
    assert astar(free, (3, 0), (3, 4)) is None  # into the wall


def test_planner_heads_for_the_next_waypoint_and_keeps_its_state() -> None:
    planner = PathPlanner()
    plan = planner(Pose.of(0, 0.0, 0, (2.0, 3.0, 0.0), 0.05, (2.0, 3.0, 0.0)))
    assert plan.goal == 1 and plan.path
    assert math.hypot(plan.path[-1][0] - 26.0, plan.path[-1][1] - 3.0) < 0.3
    near = planner(
        Pose.of(1, 0.2, 0, (25.5, 3.0, 0.0), 0.05, (25.5, 3.0, 0.0))
    )  # waypoint reached: the next one
    assert near.goal == 2
    again = PathPlanner()
    again.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(planner.get_state())))
    assert again.goal == 2
    cmd = TrajectoryFollower()(plan)
    assert cmd.v > 0 and abs(cmd.w) < 0.5 and 23 < cmd.path_len < 25


CAMERAS = {c: CameraSource(c) for c in ("visible", "infrared")}


def frame(camera: str, seq: int) -> Image:
    """A camera's frame; its odometer only integrates forward, so ask for frames in order (or
    from a fresh camera)."""
    cam = CAMERAS[camera] if CAMERAS[camera].odometer.k <= seq * 10 else CameraSource(camera)
    return cam(seq, seq * 2.0)


def test_blob_detector_finds_a_planted_survivor_and_nothing_on_a_blank_frame() -> None:
    detect = BlobDetector()
    # frame 3: the leader at (5, 3) heading east sees the survivor at (11, 1.2), 17° right
    for camera in ("visible", "infrared"):
        blobs = detect(frame(camera, 3)).blobs
        assert len(blobs) == 1
        assert math.degrees(blobs[0][0]) == pytest.approx(-17, abs=3)
    # frame 8: nothing in view
    assert detect(frame("visible", 8)).blobs == [] and detect(frame("infrared", 8)).blobs == []
    blank = Image(0, 0.0, "visible", 25, 40, bytes(3000), (0.0, 0.0, 0.0))
    assert detect(blank).blobs == []


def test_a_blob_cut_by_the_frame_takes_its_range_from_where_it_meets_the_ground() -> None:
    """Frame 25: the survivor at the frame's right edge shows narrower than it is (its width
    would say 5.0 m); the range from its lowest row is within half a metre of the truth, and
    so is a whole blob's range from its width (frame 24)."""
    detect = BlobDetector()
    for seq in (24, 25):
        img = frame("infrared", seq)
        (truth,) = in_view(world(7), true_pose(seq * 2.0), SURVIVORS)
        ((_, width, _, rng),) = detect(img).blobs
        assert rng == pytest.approx(truth[1], abs=0.5)
    assert 0.35 / math.tan(width / 2) > truth[1] + 0.8  # the cut blob's width misleads


def test_fusion_needs_both_cameras() -> None:
    """The warm pipe at (20, 1.2) shows in infrared only: fusion makes no detection of it."""
    detect, fuse = BlobDetector(), BlobFusion()
    assert fuse(detect(frame("infrared", 12))) is None  # waits for its twin
    det = fuse(detect(frame("visible", 12)))
    assert det is not None and det.infrared == 1 and det.visible == 0 and det.hits == []
    assert fuse.pending == {}
    assert HOT_SPOTS


def test_target_map_finds_every_planted_survivor_and_no_phantom() -> None:
    detect, fuse, bayes, tmap = BlobDetector(), BlobFusion(), BayesFilter(), TargetMap()
    report = None
    for seq in range(0, 67):  # one lap of the route
        fuse(detect(frame("visible", seq)))
        det = fuse(detect(frame("infrared", seq)))
        assert det is not None
        # a detection exactly when a survivor is in view: no phantom on survivor-free frames
        assert bool(det.hits) == bool(in_view(world(7), true_pose(seq * 2.0), SURVIVORS))
        belief = bayes(det)
        assert belief is not None
        report = tmap(belief)
        if seq == 1:  # before any survivor came into view
            assert report.targets == []
        if seq == 20:  # bayes' map moves with the vertex
            moved = BayesFilter()
            moved.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(bayes.get_state())))
            assert np.allclose(moved.logodds, bayes.logodds, atol=1e-5)
    assert report is not None
    found = [(x, y) for x, y, _ in report.targets]
    assert len(found) == len(SURVIVORS)
    for sx, sy in SURVIVORS:
        assert min(math.hypot(sx - x, sy - y) for x, y in found) < 1.5


def test_the_target_map_places_frames_by_the_localized_pose_not_by_drifting_odometry() -> None:
    """Laps two and three: odometry is metres off by then. Fed the localizer's poses (here
    the truth, carrying the odometry reading of the same instant) the map finds every survivor
    and nothing else; the same frames placed by odometry alone miss them and make phantoms."""
    odo = OdometrySource()  # the odometer the cameras carry: frame j is reading 10 j
    detect, fuse = BlobDetector(), BlobFusion()
    bayes, blind, tmap, tmap_blind = BayesFilter(), BayesFilter(), TargetMap(), TargetMap()
    report = report_blind = None
    drift = 0.0
    for seq in range(67, 200):
        k, t = seq * 10, seq * 2.0
        reading = odo(k, t)
        x, y, th = true_pose(t)
        odom = (reading.x_mm / 1e3, reading.y_mm / 1e3, reading.theta_mrad / 1e3)
        drift = max(drift, math.hypot(odom[0] - x, odom[1] - y))
        assert bayes(Pose.of(k, t, k, (x, y, th), 0.1, odom)) is None  # a pose updates, no output
        fuse(detect(frame("visible", seq)))
        det = fuse(detect(frame("infrared", seq)))
        assert det is not None and det.pose == pytest.approx(odom, abs=1e-3)
        belief, belief_blind = bayes(det), blind(det)
        assert belief is not None and belief_blind is not None
        report, report_blind = tmap(belief), tmap_blind(belief_blind)
    assert report is not None and report_blind is not None
    assert drift > 3.0
    found = [(x, y) for x, y, _ in report.targets]
    assert len(found) == len(SURVIVORS)
    for sx, sy in SURVIVORS:
        assert min(math.hypot(sx - x, sy - y) for x, y in found) < 1.5
    # odometry alone gets it wrong: a survivor missed, or a target where there is none
    missed = [
        s for s in SURVIVORS
        if all(math.hypot(s[0] - x, s[1] - y) >= 1.5 for x, y, _ in report_blind.targets)
    ]  # fmt: skip
    phantoms = [
        (x, y) for x, y, _ in report_blind.targets
        if all(math.hypot(sx - x, sy - y) >= 1.5 for sx, sy in SURVIVORS)
    ]  # fmt: skip
    assert missed or phantoms
    # the correction moves with the vertex
    moved = BayesFilter()
    moved.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(bayes.get_state())))
    assert moved.map_odom == pytest.approx(bayes.map_odom) and moved.pose_seq == bayes.pose_seq


def test_storage_rows_carry_what_completeness_and_delay_need(tmp_path: Path) -> None:
    db = tmp_path / "log.sqlite"
    store = Storage(db=str(db))
    store.clock = lambda: 100.0
    traj = TrajectoryFollower()
    planner = PathPlanner()
    for k in (0, 1, 2, 4, 4):  # a gap (3) and a repeat (4)
        store(traj(planner(Pose.of(k, 99.9, k, true_pose(k / 5), 0.05, true_pose(k / 5)))))
    store.close()
    s = summary(db)
    assert s["trajectory"] == {
        "rows": 5, "distinct": 4, "repeats": 1, "gaps": 1, "first": 0, "last": 4
    }  # fmt: skip
    assert s["delay_ms_p50"] == pytest.approx(100.0)
    assert s["localization_error_m_max"] < 1e-9


def test_profile_measures_costs_and_sizes_and_writes_them_back(tmp_path: Path) -> None:
    from mso.model.appfile import load_app
    from mso.runtime.profile import profile, write_back

    src = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples" / "convoy.yaml"
    app_file = tmp_path / "convoy.yaml"
    app_file.write_text(
        src.read_text().replace("cost: 0.", "cost: 9.").replace("size: ", "size: 1")
    )
    prof = profile(load_app(app_file), seconds=4.0, speed=2.0)
    costs, sizes = prof.costs(), prof.sizes()
    assert prof.vertices["laser"].calls == 20 and prof.vertices["visible_camera"].calls == 2
    assert prof.vertices["storage"].calls == 22  # 20 trajectory rows, 2 target rows
    assert all(p.errors == 0 for p in prof.vertices.values())
    assert set(costs) == set(prof.vertices) and all(c > 0 for c in costs.values())
    assert 900 <= sizes[("laser", "scan_filter")] <= 1000
    assert 2900 <= sizes[("visible_camera", "visible_blobs")] <= 3200
    assert write_back(app_file, costs, sizes) == []
    again = load_app(app_file)
    assert again.vertices["localization"].cost == pytest.approx(costs["localization"], rel=0.01)
    assert {(e.src, e.dst): e.size for e in again.edges} == sizes
    assert "# The cooperative-robotics convoy" in app_file.read_text()  # comments kept


def test_localization_merges_its_two_inputs_back_into_time_order() -> None:
    """Odometry and scans come by different paths, so either may run ahead: the filter holds
    what is early and gives the same poses as when both arrive in time order."""
    laser, odo, f = LaserSource(), OdometrySource(), OdomFilter()
    filt, match = ScanFilter(), ScanMatcher()
    deltas = [d for k in range(30) if (d := f(odo(k, k / 5))) is not None]
    scans = [match(filt(laser(k, k / 5))) for k in range(30)]
    in_order, late_odometry = Localizer(particles=200), Localizer(particles=200)
    expected = in_order(scans[0])
    for d, s in zip(deltas, scans[1:], strict=True):
        assert in_order(d) == []
        expected += in_order(s)
    got = []
    for s in scans[:12]:  # the scans run 11 readings ahead of the odometry
        got += late_odometry(s)
    assert [p.seq for p in got] == [0]
    moved = Localizer(particles=10)  # what is held moves with the vertex
    moved.set_state(msgspec.msgpack.decode(msgspec.msgpack.encode(late_odometry.get_state())))
    for d in deltas:
        got += moved(d)
    for s in scans[12:]:
        got += moved(s)
    assert [p.seq for p in got] == list(range(30))
    assert [(p.x, p.y) for p in got] == [(p.x, p.y) for p in expected]


def test_simulating_the_world_is_not_charged_to_the_robot() -> None:
    """A sensor's ray casting and rendering stand in for hardware: the runtime's per-vertex CPU
    time (and so measured CPU energy, and `mso profile`) leaves them out; packing is charged."""
    import time

    from mso.runtime.worker import charged_thread_time, not_charged

    t0, c0 = time.thread_time(), charged_thread_time()
    with not_charged():
        deadline = time.thread_time() + 0.02
        while time.thread_time() < deadline:
            pass
    assert time.thread_time() - t0 >= 0.02
    assert charged_thread_time() - c0 < 0.005

    sources = [LaserSource(), OdometrySource(), CameraSource("visible"), CameraSource("infrared")]
    for source in sources:
        t0, c0 = time.thread_time(), charged_thread_time()
        for seq in range(20):
            source(seq, 0.0)
        total, charged = time.thread_time() - t0, charged_thread_time() - c0
        assert charged < 0.5 * total, type(source).__name__
