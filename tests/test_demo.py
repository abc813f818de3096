"""`mso demo`'s line shows each of the paper's three reconfigurations for a reason the viewer
sees (checked on the same node code in virtual time; the demo itself runs it emulated), and
each move it tells keeps the words of whoever asked."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from mso.examples.convoy.demo import (
    APP_FILE,
    PLANNER,
    SCENARIO_FILE,
    CpuWatts,
    _story,
    kind_of,
)
from mso.model.appfile import with_planner
from mso.model.network import Network
from mso.node.moves import MoveLog
from mso.protocol.events import Happened
from mso.scenario import load_scenario
from mso.sim.play import simulate


@pytest.fixture(scope="module")
def report() -> dict[str, Any]:
    scenario = load_scenario(SCENARIO_FILE)
    net = scenario.network
    nodes = [  # the simulator runs vertex code without measuring it: profiled costs instead
        dataclasses.replace(n, power=dataclasses.replace(n.power, cpu_energy="modelled"))
        for n in net.nodes.values()
    ]
    scenario = dataclasses.replace(scenario, network=Network(nodes, list(net.links.values())))
    document = with_planner(APP_FILE.read_text(), PLANNER, file=str(APP_FILE))  # as the demo
    return simulate(scenario, document, str(APP_FILE), duration=56.0)


def test_the_demo_line_relocates_remaps_and_recovers_losing_nothing(
    report: dict[str, Any],
) -> None:
    rc = report["reconfigurations"]
    told = " | ".join(rc["management"])
    assert "N1 draining" in told  # the rules relocate off the draining leader
    assert "N1: 13.0 relocate convoy/scan_filter -> N2" in told  # CPU that shows, not 0.01 ms
    assert "remap convoy chain" in told and "its route changed" in told
    # the route change leaves a vertex off its chain's new route: the remap moves it
    remapped = [mv for mv in rc["moves"] if 8.0 < mv["at"] < 13.0]
    assert remapped and all(mv["from"] == "N3" for mv in remapped)
    # N3's battery empties (fail-stop) and what it held is recovered on the others
    assert "N3" not in report["alive"]
    assert any("battery empty" in str(line) for line in report["timeline"])
    (recovery,) = rc["recoveries"]
    assert recovery["ok"] and recovery["failed"] == ["N3"] and recovery["moved"]
    assert recovery["at"] < 50.0  # the demo runs 56 s: the viewer sees it and what follows
    events = report["events"]
    # a trajectory row per scan, a target report per frame pair: none lost
    emitted = events["emitted"]
    assert events["delivered"]["storage"] == emitted["laser"] + emitted["visible_camera"] > 300


def test_the_demo_says_what_to_watch_for_from_its_scenario() -> None:
    lines = _story(load_scenario(SCENARIO_FILE))
    assert len(lines) == 3
    assert "relocation" in lines[0] and "chain remap" in lines[1] and "recovery" in lines[2]


def test_moves_are_counted_by_kind_as_the_nodes_word_them() -> None:
    assert kind_of("convoy: odom_filter N1 -> N2 in 12 ms, asked by the relocation rule") == (
        "relocation"
    )
    assert kind_of("convoy: remap path_planning->N4 in 10 ms, asked by the route rule") == "remap"
    assert kind_of("convoy: recovery blob_fusion->N2 in 6 ms, asked by a recovery after N3") == (
        "recovery"
    )


def test_cpu_watts_come_from_the_monitors_cpu_energy() -> None:
    watts = CpuWatts()
    mon = {"N1": {"monitor": {"cpu_energy_j": 1.0}}}
    assert watts.sample(mon, 10.0) == {}  # one sample: no rate yet
    assert watts.sample({"N1": {"monitor": {"cpu_energy_j": 1.3}}}, 13.0) == {
        "N1": pytest.approx(0.1)
    }


def test_two_remaps_asked_at_once_keep_each_its_own_words() -> None:
    log = MoveLog()
    log.asking("convoy", "", "the route rule on N2: chain 2's route changed")
    log.asking("convoy", "", "the route rule on N2: chain 3's route changed")
    first = log.happened(Happened("remap", "convoy", by="rule", detail="unchanged"), 1.0)
    second = log.happened(Happened("remap", "convoy", by="rule", detail="a->N4"), 1.1)
    assert first.asked.endswith("chain 2's route changed")
    assert second.asked.endswith("chain 3's route changed")
    third = log.happened(Happened("remap", "convoy", by="rule"), 2.0)
    assert third.asked == "the rules of the coordinating node"  # none asked: the kind only
