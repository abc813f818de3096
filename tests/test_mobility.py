"""Random-waypoint mobility and relinking by radio range."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from mso.errors import ScenarioError
from mso.model.mobility import RandomWaypoint, WaypointTracks
from mso.scenario import load_scenario, loads_scenario

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


def test_tracks_stay_in_the_area_respect_speed_and_are_seeded() -> None:
    model = RandomWaypoint(
        area=(100.0, 50.0), speed=(1.0, 4.0), pause_s=1.0, seed=3, fixed=frozenset({"B"})
    )
    starts = {"A": (0.0, 0.0), "B": (10.0, 10.0), "C": (50.0, 25.0)}
    a, b = WaypointTracks(model, starts), WaypointTracks(model, starts)
    prev = a.positions(0.0)
    for k in range(1, 400):
        t = k * 0.25
        now = a.positions(t)
        assert now == b.positions(t)  # same seed, same movement
        for n, (x, y) in now.items():
            assert 0 <= x <= 100 and 0 <= y <= 50
            assert math.dist(prev[n], now[n]) <= 4.0 * 0.25 + 1e-9
        assert now["B"] == (10.0, 10.0)
        prev = now
    assert prev["A"] != (0.0, 0.0) and prev["C"] != (50.0, 25.0)


def test_relink_follows_positions() -> None:
    sc = load_scenario(EXAMPLES / "waypoint6.yaml")
    assert sc.mobility is not None and sc.radio_range == 150
    net = sc.network
    assert net.route("R1", "R6") is not None
    added, removed = net.relink({"R1": (0, 0), "R2": (100, 0), "R3": (400, 0)}, 150)
    assert set(net.links) == {("R1", "R2")}
    assert ("R1", "R2") not in added and removed
    assert net.route("R1", "R3") is None


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "nodes: {A: {pos: [0, 0]}}\nmobility: {model: random_waypoint}\n",
            "needs node positions and a 'radio_range'",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}}\nmobility: {model: brownian}\n",
            "s.yaml:3: mobility.model: expected model: one of random_waypoint, gauss_markov, "
            "group, ns2, bonnmotion",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}}\n"
            "mobility: {model: random_waypoint, area: [1, 1], speed: [3, 1]}\n",
            "mobility.speed: expected [min, max] speeds",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}}\n"
            "mobility: {model: gauss_markov, area: [1, 1], speed: [1, 3], alpha: 2}\n",
            "mobility.alpha: expected alpha in [0, 1], got 2.0",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}}\n"
            "mobility: {model: gauss_markov, area: [1, 1], speed: [1, 3], pause_s: 1}\n",
            "mobility.pause_s: unknown attribute 'pause_s'",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}, B: {pos: [1, 1]}}\n"
            "mobility: {model: group, area: [1, 1], speed: [1, 3], groups: [[A, B], [B]]}\n",
            "mobility.groups[1]: node 'B' is in two groups",
        ),
        (
            "radio_range: 10\nnodes: {A: {pos: [0, 0]}}\n"
            "mobility: {model: group, area: [1, 1], speed: [1, 3], groups: [[A, Z]]}\n",
            "mobility.groups[0]: unknown node 'Z'",
        ),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1, down: [A, C]}\n",
            "s.yaml:3: changes[0].down: unknown node 'C'",
        ),
        (
            "nodes: {A: {}, B: {}}\nchanges:\n  - {at: 1}\n",
            "expected exactly one of 'up', 'down', 'fail', 'restart', 'partition'",
        ),
    ],
)
def test_bad_mobility_and_changes(text: str, expected: str) -> None:
    with pytest.raises(ScenarioError) as err:
        loads_scenario(text, file="s.yaml")
    assert expected in str(err.value)
