"""The link model: loss (and the user-space backend's delay) from distance through log-distance
path loss or a loss curve, deterministic with a seed, in scenario files and as nodes move."""

from __future__ import annotations

import math

import pytest

from mso.errors import ScenarioError
from mso.model.network import LinkSpec
from mso.model.propagation import Propagation
from mso.scenario import loads_scenario
from mso.scenario.timeline import Timeline


def test_loss_grows_with_distance_and_is_half_at_the_sensitivity() -> None:
    model = Propagation(tx_dbm=15, ref_loss_db=40, exponent=3, sensitivity_dbm=-82, width_db=2)
    losses = [model.loss(d) for d in (10, 40, 60, 80, 100, 150)]
    assert losses == sorted(losses) and losses[0] < 1e-5 and losses[-1] > 0.98
    # received power equals the sensitivity where 40 + 30 log10(d) = 97: d = 10^1.9
    assert model.loss(10**1.9) == pytest.approx(0.5)
    assert model.received_dbm(10) == pytest.approx(15 - 40 - 30)
    # the default radio range is where the loss reaches max_loss (0.9)
    assert model.loss(model.range_m()) == pytest.approx(0.9)
    # a retrying link layer: loss 0.5 costs one retransmission on average
    assert Propagation(retry_delay_ms=4).delay_ms(1.0, 0.5) == pytest.approx(5.0)
    assert model.link("A", "B", 200) is None  # loses more than max_loss: no link
    spec = model.link("A", "B", 10**1.9, LinkSpec("", "", 11.0, 1.0))
    assert spec == LinkSpec("A", "B", 11.0, 1.0, 0.5)


def test_a_loss_curve_is_interpolated_and_flat_beyond_its_ends() -> None:
    model = Propagation(model="curve", curve=((50, 0.0), (100, 0.2), (150, 0.8)), max_loss=0.5)
    assert [model.loss(d) for d in (0, 50, 75, 100, 125, 150, 400)] == pytest.approx(
        [0.0, 0.0, 0.1, 0.2, 0.5, 0.8, 0.8]
    )
    assert model.range_m() == 100  # the furthest point within max_loss


def test_shadowing_is_fixed_per_link_by_the_seed() -> None:
    a = Propagation(shadowing_db=6, seed=1)
    same = Propagation(shadowing_db=6, seed=1)
    other = Propagation(shadowing_db=6, seed=2)
    pairs = [("R1", "R2"), ("R2", "R3"), ("R1", "R3")]
    assert [a.loss(70, x, y) for x, y in pairs] == [same.loss(70, x, y) for x, y in pairs]
    assert a.loss(70, "R1", "R2") == a.loss(70, "R2", "R1")  # one draw per link
    assert [a.loss(70, x, y) for x, y in pairs] != [other.loss(70, x, y) for x, y in pairs]
    assert len({a.loss(70, x, y) for x, y in pairs}) == 3  # links of one length differ
    assert Propagation().shadow_db("R1", "R2") == 0.0


SCENARIO = """\
name: lossy
link_defaults: {bandwidth_mbps: 11, delay_ms: 1.0}
propagation: {model: log_distance, tx_dbm: 15, exponent: 3, sensitivity_dbm: -82,
              retry_delay_ms: 2}
nodes:
  R1: {pos: [0, 0]}
  R2: {pos: [40, 0]}
  R3: {pos: [120, 0]}
"""


def test_a_scenario_gets_each_links_loss_and_delay_from_its_length() -> None:
    sc = loads_scenario(SCENARIO)
    model = sc.propagation
    assert model is not None and sc.radio_range == pytest.approx(model.range_m())
    links = sc.network.links
    # R1-R2 (40 m) is nearly clean, R2-R3 (80 m) loses about half; R1-R3 (120 m) is no link
    assert set(links) == {("R1", "R2"), ("R2", "R3")}
    near, far = links[("R1", "R2")], links[("R2", "R3")]
    assert near.loss < 0.02 and 0.3 < far.loss < 0.7
    assert far.loss == pytest.approx(model.loss(80), abs=1e-4)
    assert far.delay_ms == pytest.approx(1.0 + 2 * far.loss / (1 - far.loss), abs=1e-3)
    assert far.bandwidth_mbps == 11


def test_moving_nodes_change_their_links_loss() -> None:
    text = SCENARIO + (
        "mobility: {model: random_waypoint, area: [150, 10], speed: [20, 30], pause_s: 0,"
        " seed: 3, step_s: 0.5}\n"
    )
    sc = loads_scenario(text)
    tl = Timeline(sc)
    seen: set[float] = set()
    for step in range(1, 41):
        tl.advance(step * 0.5)
        for (a, b), spec in sc.network.links.items():
            pa, pb = tl.positions[a], tl.positions[b]
            assert spec.loss == pytest.approx(sc.propagation.loss(math.dist(pa, pb)), abs=1e-4)  # type: ignore[union-attr]
            seen.add(spec.loss)
    assert len(seen) > 10  # the loss followed the distance


@pytest.mark.parametrize(
    ("block", "why"),
    [
        ("{model: ray_tracing}", "unknown model 'ray_tracing'"),
        ("{exponent: 0}", "expected a number > 0"),
        ("{max_loss: 1.0}", "expected a loss in \\(0, 1\\)"),
        ("{seed: 1.5}", "expected an integer seed"),
        ("{model: curve}", "expected a list of \\[distance_m, loss\\] points"),
        ("{model: curve, curve: [[100, 0.1], [50, 0.5]]}", "distances must increase"),
        ("{model: curve, curve: [[100, 1.5]]}", "expected a loss in \\[0, 1\\]"),
        ("{model: curve, curve: [[100, 0.95]]}", "links no pair of nodes"),
        ("{curve: [[100, 0.1]]}", "'curve' goes with 'model: curve'"),
        ("{tx_power: 3}", "unknown attribute 'tx_power'"),
    ],
)
def test_bad_propagation_blocks_are_located_errors(block: str, why: str) -> None:
    text = f"name: x\npropagation: {block}\nnodes: {{A: {{pos: [0, 0]}}}}\n"
    with pytest.raises(ScenarioError, match=why) as err:
        loads_scenario(text, file="x.yaml")
    assert "x.yaml:2" in str(err.value)
    listed = "name: x\npropagation: {}\nnodes: {A: {pos: [0, 0]}, B: {}}\nlinks: [[A, B]]\n"
    with pytest.raises(ScenarioError):
        loads_scenario(listed)
