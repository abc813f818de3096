"""ns-2 setdest scripts and BonnMotion movement files as scenario mobility: parsing (on
samples written by hand from the formats), errors with their line, and the timeline playing
the imported movement."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import pytest

from mso.errors import ScenarioError
from mso.model.mobility import Trace, TraceTracks
from mso.scenario import load_scenario
from mso.scenario.mobility_import import load_trace, parse_bonnmotion, parse_ns2
from mso.scenario.timeline import LinksChanged, Timeline

NS2 = """\
#
# nodes: 2, pause: 0.00, max speed: 10.00, max x: 100.00, max y: 100.00
#
$node_(0) set X_ 0.0
$node_(0) set Y_ 0.0
$node_(0) set Z_ 0.000000000000
$node_(1) set X_ 0.0
$node_(1) set Y_ 0.0
$node_(1) set Z_ 0.0
$god_ set-dist 0 1 16777215
$ns_ at 1.0 "$node_(0) setdest 10.0 0.0 2.0"
$ns_ at 0.0 "$node_(1) setdest 100.0 0.0 10.0"
$ns_ at 5.0 "$node_(1) setdest 50.0 50.0 5.0"
$ns_ at 2.5 "$god_ set-dist 0 1 2"
$ns_ at 20.0 "$node_(1) set X_ 0.0"
#
# Destination Unreachables: 0
"""


def _close(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return math.dist(a, b) < 1e-9


def test_ns2_setdest_moves_interrupts_and_jumps() -> None:
    trace = parse_ns2(NS2, ["A", "B"], file="m.tcl")
    tracks = TraceTracks(trace, {})
    pos = tracks.positions
    assert _close(pos(0.0)["A"], (0, 0)) and _close(pos(1.0)["A"], (0, 0))  # waits for t=1
    assert _close(pos(3.5)["A"], (5, 0))  # 2 m/s from t=1
    assert _close(pos(6.0)["A"], (10, 0)) and _close(pos(100)["A"], (10, 0))  # arrived, stays
    assert _close(pos(2.0)["B"], (20, 0))
    assert _close(pos(5.0)["B"], (50, 0))  # the second setdest cuts the first short here
    assert _close(pos(10.0)["B"], (50, 25))  # ... and heads up at 5 m/s
    assert _close(pos(15.0)["B"], (50, 50)) and _close(pos(19.9)["B"], (50, 50))
    assert _close(pos(20.0)["B"], (0, 50))  # set X_ puts it there
    assert trace.end == 20.0


def test_tracks_answer_any_time_order() -> None:
    tracks = TraceTracks(parse_ns2(NS2, ["A", "B"]), {"C": (7.0, 7.0)})
    late, early = tracks.positions(10.0), tracks.positions(2.0)
    assert _close(late["B"], (50, 25)) and _close(early["B"], (20, 0))
    assert late["C"] == (7.0, 7.0)  # not in the trace: stays where it started


def test_bonnmotion_waypoints_2d_and_3d() -> None:
    text = "0.0 0.0 0.0 10.0 100.0 0.0 20.0 100.0 100.0\n5.0 1.0 1.0\n\n"
    trace = parse_bonnmotion(text, ["A", "B", "C"], file="m.movements")
    assert set(trace.waypoints) == {"A", "B"}  # C is not in the file
    tracks = TraceTracks(trace, {})
    assert _close(tracks.positions(5.0)["A"], (50, 0))
    assert _close(tracks.positions(15.0)["A"], (100, 50))
    assert _close(tracks.positions(99.0)["A"], (100, 100))
    assert _close(tracks.positions(0.0)["B"], (1, 1))
    three = parse_bonnmotion("0 0 0 0 10 10 0 5\n", ["A"], dim=3)
    assert three.waypoints["A"] == ((0, 0, 0), (10, 10, 0))


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("proc go {} { exec rm -rf / }\n", "m.tcl:1: expected '$node_(i) set X_|Y_|Z_ v'"),
        ("$node_(0) set X_ 1\n$node_(0) set Q_ 2\n", "m.tcl:2: expected"),
        ('$ns_ at -1 "$node_(0) setdest 1 1 1"\n', "m.tcl:1: expected a time >= 0"),
        ('$ns_ at 1 "$node_(0) setdest 1 1 -3"\n', "m.tcl:1: expected a speed >= 0"),
        ('$ns_ at 1 "$node_(0) setdest 1 nan 3"\n', "m.tcl:1: expected"),
        ('$ns_ at 1 "$node_(2) setdest 1 1 3"\n', "has 3 nodes but only 2 node ids"),
        ("# only a comment\n", "no node found"),
    ],
)
def test_ns2_errors_name_the_line(text: str, expected: str) -> None:
    with pytest.raises(ScenarioError) as err:
        parse_ns2(text, ["A", "B"], file="m.tcl")
    assert expected in str(err.value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0 0 0 10 5\n", "m.movements:1: node 0: expected groups of 3 numbers (t x y), got 5"),
        ("0 0 0\n0 0 0 x 1 1\n", "m.movements:2: expected a number, got 'x'"),
        ("0 0 0 10 1 1 5 2 2\n", "m.movements:1: node 0: waypoint 2: time 5 goes back"),
        ("0 0 0\n0 0 0\n0 0 0\n", "has 3 nodes but only 2 node ids"),
        ("\n", "no node found"),
    ],
)
def test_bonnmotion_errors_name_the_line(text: str, expected: str) -> None:
    with pytest.raises(ScenarioError) as err:
        parse_bonnmotion(text, ["A", "B"], file="m.movements")
    assert expected in str(err.value)


def test_gzipped_bonnmotion_file(tmp_path: Path) -> None:
    p = tmp_path / "run.movements.gz"
    p.write_bytes(gzip.compress(b"0 0 0 4 4 0\n"))
    trace = load_trace(p, "bonnmotion", ["A"])
    assert isinstance(trace, Trace) and trace.waypoints["A"][-1] == (4.0, 4.0, 0.0)
    (tmp_path / "bad.gz").write_bytes(b"not gzip")
    with pytest.raises(ScenarioError, match="cannot read the movement file"):
        load_trace(tmp_path / "bad.gz", "bonnmotion", ["A"])


def _scenario(tmp_path: Path, mobility: str, move: str, name: str) -> Path:
    (tmp_path / name).write_text(move)
    p = tmp_path / "s.yaml"
    p.write_text(
        "radio_range: 30\nnodes:\n  A: {pos: [0, 0]}\n  B: {}\n  C: {}\n"
        f"mobility: {mobility}\n"
    )
    return p


@pytest.mark.parametrize(
    ("mobility", "move", "name"),
    [
        (
            "{model: ns2, file: b.tcl, nodes: [B, C], step_s: 0.5}",
            "$node_(0) set X_ 20\n$node_(0) set Y_ 0\n$node_(1) set X_ 40\n$node_(1) set Y_ 0\n"
            '$ns_ at 1.0 "$node_(0) setdest 100 0 10"\n',
            "b.tcl",
        ),
        (
            "{model: bonnmotion, file: b.movements, nodes: [B, C], step_s: 0.5}",
            "0 20 0 1 20 0 9 100 0\n0 40 0\n",
            "b.movements",
        ),
    ],
)
def test_scenario_plays_an_imported_trace(
    tmp_path: Path, mobility: str, move: str, name: str
) -> None:
    sc = load_scenario(_scenario(tmp_path, mobility, move, name))
    # start positions come from the trace: A-B and B-C are within 30 m, A-C is not
    assert sc.network.nodes["B"].pos == (20.0, 0.0)
    assert {tuple(sorted(k)) for k in sc.network.links} == {("A", "B"), ("B", "C")}
    tl = Timeline(sc)
    events: list[tuple[float, set[tuple[str, str]]]] = []
    for _ in range(100):
        at = tl.next_at()
        if at is None:
            break
        for action in tl.advance(at):
            assert isinstance(action, LinksChanged)
            events.append((action.at, set(action.removed)))
    # B leaves A's range (x > 30) at t = 2 and C's range (x > 70) at t = 6
    assert events == [(2.5, {("A", "B")}), (6.5, {("B", "C")})]
    assert tl.next_at() is None  # the trace is over: the timeline ends


@pytest.mark.parametrize(
    ("mobility", "expected"),
    [
        ("{model: ns2}", "s.yaml:6: mobility.file: expected the path of a movement file"),
        ("{model: ns2, file: b.tcl, nodes: [B, Z]}", "mobility.nodes: expected a list of node"),
        ("{model: ns2, file: b.tcl, nodes: [B, B]}", "listed twice"),
        ("{model: ns2, file: b.tcl, dim: 3}", "'dim' goes with model: bonnmotion only"),
        ("{model: ns2, file: b.tcl, area: [1, 1]}", "mobility.area: unknown attribute"),
        ("{model: ns2, file: missing.tcl}", "missing.tcl: cannot read the movement file"),
    ],
)
def test_scenario_trace_errors(tmp_path: Path, mobility: str, expected: str) -> None:
    with pytest.raises(ScenarioError) as err:
        load_scenario(_scenario(tmp_path, mobility, "$node_(0) set X_ 1\n", "b.tcl"))
    assert expected in str(err.value)


def test_the_simulator_plays_an_imported_trace(tmp_path: Path) -> None:
    """A relay walks away (BonnMotion file): the simulator's links follow it and the flow
    stops; a second relay walks in (ns-2 would do the same) and it resumes."""
    from mso.sim.play import simulate

    # R2 leaves the line between t=2 and t=4; R4 arrives at the same spot from t=5 to t=7
    (tmp_path / "walk.movements").write_text(
        "0 100 0 2 100 0 4 100 400\n0 100 400 5 100 400 7 100 0\n"
    )
    sc_file = tmp_path / "s.yaml"
    sc_file.write_text(
        "radio_range: 120\nnodes:\n  R1: {pos: [0, 0]}\n  R2: {}\n  R4: {}\n"
        "  R3: {pos: [200, 0]}\n"
        "mobility: {model: bonnmotion, file: walk.movements, nodes: [R2, R4], step_s: 0.5}\n"
    )
    app = (
        "name: pipe\nvertices:\n"
        "  src: {code: runtime_vertices:CountingSource, pinned: R1, rate: 50,\n"
        "        output: runtime_vertices:Num}\n"
        "  sink: {code: runtime_vertices:Recorder, pinned: R3}\n"
        "edges: [[src, sink]]\n"
    )
    r = simulate(load_scenario(sc_file), app, "pipe.yaml", duration=10.0)
    moves = [t for t, what in r["timeline"] if what == "mobility"]
    assert moves and min(moves) <= 3.0 and max(moves) >= 6.0  # links went and came back
    ev = r["events"]
    # 50 events/s: nothing got through during the gap, but the source kept what it made
    # meanwhile (store and forward) and every event arrived once R4 linked them again
    assert ev["delivered"]["sink"] == ev["emitted"]["src"] >= 450, ev
    assert ev["given_up"] == 0
