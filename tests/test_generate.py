"""Generated scenarios (``mso scenario generate``): deterministic from a seed, valid scenario
files with the degree asked and connected; Gauss-Markov and group mobility seeded, inside their
bounds, and played by the timeline; bad arguments refused in one line with exit code 2."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.model.mobility import GaussMarkov, GaussMarkovTracks, GroupMobility, GroupTracks
from mso.scenario import load_scenario, loads_scenario
from mso.scenario.generate import Spec, dumps, generate
from mso.scenario.timeline import Timeline


def _text(spec: Spec) -> str:
    return dumps(generate(spec), spec)


def _connected(net_nodes: list[str], neighbours: dict[str, list[str]]) -> bool:
    seen, todo = {net_nodes[0]}, [net_nodes[0]]
    while todo:
        for w in neighbours[todo.pop()]:
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return len(seen) == len(net_nodes)


@pytest.mark.parametrize(
    ("topology", "degree", "low", "high"),
    [("grid", 4, 3.0, 4.0), ("grid", 6, 4.5, 6.0), ("grid", 8, 6.0, 8.0),
     ("geometric", 6, 5.5, 6.5), ("platoon", 6, 5.0, 9.0)],
)  # fmt: skip
def test_generated_topologies_are_seeded_valid_connected_and_of_the_degree_asked(
    topology: str, degree: float, low: float, high: float
) -> None:
    spec = Spec(topology, 120, seed=5, degree=degree)
    text = _text(spec)
    assert text == _text(spec)  # the same seed, the same file
    if topology == "geometric":  # (a lattice is a lattice whatever the seed)
        assert text != _text(Spec(topology, 120, seed=6, degree=degree))
    sc = loads_scenario(text, file="g.yaml")
    net = sc.network
    assert len(net.nodes) == 120 and sc.radio_range is not None
    assert low <= 2 * len(net.links) / len(net.nodes) <= high
    ids = list(net.nodes)
    assert _connected(ids, {n: net.neighbours(n) for n in ids})


@pytest.mark.parametrize("mobility", ["random_waypoint", "gauss_markov", "group"])
def test_generated_mobility_plays_the_same_for_a_seed_and_moves_links(mobility: str) -> None:
    spec = Spec("platoon", 40, seed=3, mobility=mobility, speed=(5.0, 10.0))
    runs = []
    for _ in range(2):
        sc = loads_scenario(_text(spec), file="m.yaml")
        assert sc.mobility is not None
        timeline = Timeline(sc)
        for k in range(1, 121):
            timeline.advance(k * 0.5)
        runs.append((timeline.positions, sorted(sc.network.links), timeline.played))
    assert runs[0] == runs[1]
    assert any(what == "mobility" for _, what in runs[0][2])  # the links did change


def test_gauss_markov_stays_in_the_area_within_its_speeds_and_is_seeded() -> None:
    model = GaussMarkov(area=(200.0, 100.0), speed=(1.0, 3.0), alpha=0.5, interval_s=1.0, seed=4)
    starts = {"A": (10.0, 10.0), "B": (100.0, 50.0), "C": (190.0, 90.0)}
    a, b = GaussMarkovTracks(model, starts), GaussMarkovTracks(model, starts)
    prev = a.positions(0.0)
    assert prev == starts
    for k in range(1, 600):
        t = k * 0.5
        now = a.positions(t)
        assert now == b.positions(t)
        for n, (x, y) in now.items():
            assert 0 <= x <= 200 and 0 <= y <= 100
            assert math.dist(prev[n], now[n]) <= 3.0 * 0.5 + 1e-9
        prev = now
    assert all(prev[n] != starts[n] for n in starts)
    other = GaussMarkovTracks(
        GaussMarkov(area=(200.0, 100.0), speed=(1.0, 3.0), alpha=0.5, seed=5), starts
    )
    assert other.positions(100.0) != GaussMarkovTracks(model, starts).positions(100.0)


def test_group_members_stay_near_their_reference_point() -> None:
    groups = (("A", "B", "C"), ("D", "E"))
    starts = {"A": (0.0, 0.0), "B": (10.0, 0.0), "C": (20.0, 0.0), "D": (500.0, 500.0),
              "E": (510.0, 500.0), "F": (300.0, 300.0)}  # fmt: skip
    model = GroupMobility(area=(1000.0, 1000.0), speed=(5.0, 10.0), groups=groups, radius=4.0)
    tracks = GroupTracks(model, starts)
    for k in range(1, 400):
        now = tracks.positions(k * 0.5)
        for group in groups:  # the members keep their formation, give or take the wander
            first = group[0]
            for n in group[1:]:
                want = (starts[n][0] - starts[first][0], starts[n][1] - starts[first][1])
                got = (now[n][0] - now[first][0], now[n][1] - now[first][1])
                assert math.dist(want, got) <= 2 * 4.0 + 1e-9
        assert now["F"] == starts["F"]  # in no group: stays put
    assert math.dist(now["A"], starts["A"]) > 50  # the group went somewhere


def run(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args))
    return result.exit_code, result.stdout, result.stderr


def test_mso_scenario_generate_writes_a_file_that_loads(tmp_path: Path) -> None:
    out = tmp_path / "g.yaml"
    code, stdout, _ = run(
        "scenario", "generate", "geometric", "-n", "60", "--seed", "2",
        "--mobility", "gauss_markov", "-o", str(out),
    )  # fmt: skip
    assert code == 0 and stdout.startswith(f"wrote {out}: 60 nodes, ") and "mean degree 6" in stdout
    sc = load_scenario(out)
    assert len(sc.network.nodes) == 60 and isinstance(sc.mobility, GaussMarkov)
    code, printed, _ = run("scenario", "generate", "geometric", "-n", "60", "--seed", "2",
                           "--mobility", "gauss_markov")  # fmt: skip
    assert code == 0 and printed == out.read_text()
    code, said, _ = run("scenario", "generate", "grid", "-n", "30", "--degree", "4", "--json",
                        "-o", str(tmp_path / "g.yaml"))  # fmt: skip
    assert code == 0
    assert json.loads(said) == {
        "file": str(tmp_path / "g.yaml"), "name": "grid-30-s0", "nodes": 30, "links": 49,
        "mean_degree": 3.27, "radio_range": 101.0, "mobility": "none",
    }  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["grid", "-n", "1"], "error: --nodes: expected 2 to 10000, got 1"),
        (["grid", "-n", "30", "--degree", "5"], "error: --degree: a grid has degree 4"),
        (["geometric", "-n", "10", "--degree", "12"], "error: --degree: expected 1 to 9, got 12"),
        (["grid", "-n", "30", "--speed", "5", "1"], "error: --speed: expected MIN MAX"),
        (["grid", "-n", "30", "--spacing", "0"], "--spacing"),
        (["grid", "-n", "30", "--spacing", "nan"], "--spacing"),
        (["platoon", "-n", "30", "--platoon", "1"], "error: --platoon: expected 2 to 30, got 1"),
        (["ring", "-n", "30"], "'ring' is not one of 'grid', 'geometric', 'platoon'"),
        (["grid", "-n", "30", "--mobility", "levy"], "'levy' is not one of"),
        (["grid", "-n", "30", "-o", "/nonexistent-dir/x.yaml"], "error: --output: cannot write"),
    ],
)
def test_mso_scenario_generate_refuses_bad_arguments(args: list[str], message: str) -> None:
    code, _, err = run("scenario", "generate", *args)
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1
