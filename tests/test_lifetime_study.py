"""The energy study's code (mso.benchmarks.lifetime) on short runs in virtual time, and the
demo's line in the simulator: what follows from the power model holds, nothing is lost, and the
rules shed work off a draining leader. Relations, not figures: the benchmark measures those."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from mso.benchmarks import lifetime as study
from mso.model.network import Network
from mso.scenario import load_scenario

SECONDS = 30.0  # virtual, per run: enough for the rules' confirmation and many results
# the module's fixture runs eight such simulations (about 15 s of CPU): on a 2-core machine
# at load 20 that took more than the suite's 300 s a test; its own limit is the hang guard
pytestmark = pytest.mark.timeout(900)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("lifetime")
    out = {}
    for accounting in study.ACCOUNTINGS:
        for strategy in study.STRATEGIES:
            db = tmp / f"{accounting}-{strategy}.sqlite"
            out[accounting, strategy] = study.run(
                strategy, SECONDS, db, accounting=accounting, until_leader_dies=False
            )
    return out


def test_every_run_stores_every_result(runs: dict[tuple[str, str], dict[str, Any]]) -> None:
    for key, r in runs.items():
        assert r["complete"], key
        assert r["results_stored"] >= 5 * (SECONDS - 5), key  # a trajectory row per scan
        assert r["virtual_s"] == SECONDS


def test_the_two_accountings_differ_by_idle_power_only(
    runs: dict[tuple[str, str], dict[str, Any]],
) -> None:
    """Static placements run the same events either way: a robot's board drain is its idle
    power plus exactly what the app accounting charges it."""
    idle = study.network_for("board").nodes[study.LEADER].power.idle_w
    for strategy in ("all-on-leader", "algorithm1-kept", "ilp-optimal"):
        board = runs["board", strategy]["average_drain_w"]
        app = runs["app", strategy]["average_drain_w"]
        for node in board:
            assert board[node] - idle == pytest.approx(app[node], rel=0.05, abs=2e-4), (
                strategy,
                node,
            )


def test_offloading_helps_the_leader_far_more_when_idle_is_not_counted(
    runs: dict[tuple[str, str], dict[str, Any]],
) -> None:
    def leader_gain(accounting: str) -> float:
        on = runs[accounting, "all-on-leader"]["average_drain_w"][study.LEADER]
        off = runs[accounting, "algorithm1-kept"]["average_drain_w"][study.LEADER]
        return float(on / off)

    board, app = leader_gain("board"), leader_gain("app")
    assert app > 1.0 and board > 1.0  # Algorithm 1 takes work off the leader either way
    idle = study.network_for("board").nodes[study.LEADER].power.idle_w
    on_app = runs["app", "all-on-leader"]["average_drain_w"][study.LEADER]
    assert board <= (idle + on_app) / idle + 1e-3  # no placement beats idle + all the app
    assert app > board


def test_the_rules_move_only_for_a_margin_or_off_a_draining_node(
    runs: dict[tuple[str, str], dict[str, Any]],
) -> None:
    for (accounting, strategy), r in runs.items():
        if strategy not in study.RULES:
            assert r["relocations"] == [], (accounting, strategy)
        for _, what in r["relocations"]:
            assert "draining" in what or "inf better" in what or "% better" in what, what
    # equal boards and batteries under the board accounting: nobody drains, nothing moves
    for rules in study.RULES:
        assert runs["board", rules]["relocations"] == []


def demo_network() -> Network:
    """The demo's line with CPU energy from the vertices' profiled costs: the simulator
    runs vertex code without measuring it (the demo itself measures)."""
    net = load_scenario(study.EXAMPLES / "convoy-demo.yaml").network
    nodes = [
        dataclasses.replace(n, power=dataclasses.replace(n.power, cpu_energy="modelled"))
        for n in net.nodes.values()
    ]
    return Network(nodes, list(net.links.values()))


def test_the_demo_leader_drains_and_the_rules_move_work_off_it(tmp_path: Path) -> None:
    r = study.run(
        "mso-rules", 15.0, tmp_path / "demo.sqlite", network=demo_network(),
        until_leader_dies=False, step_s=1.0,
    )  # fmt: skip
    assert r["complete"]
    # the leader's (N3, nearly empty, sheds its own too)
    off = [(t, w) for t, w in r["relocations"] if f"{study.LEADER} draining" in w]
    assert off, f"no relocation off the leader in 15 s: {r['relocations']}"
    t, what = off[0]
    assert t < 15.0
    vertex = what.split(" ")[1].split("/")[1]  # "relocate convoy/scan_filter -> N2 (...)"
    assert vertex == "scan_filter"  # its laser pipeline, whose CPU shows in its drain
    assert r["placement_deployed"][vertex] == study.LEADER != r["placement_final"][vertex]
