"""Scenarios: the network an app runs on and what happens to it over time.

``format`` parses scenario files (docs/scenario-format.md); ``timeline`` plays their scripted
changes and mobility, driven by the emulator's clock or the simulator's virtual one.
"""

from mso.scenario.format import (
    Change,
    Heal,
    LinkChange,
    LossChange,
    NodeFailure,
    NodeRestart,
    Partition,
    Scenario,
    load_scenario,
    loads_scenario,
    scenario_from_document,
)

__all__ = [
    "Change",
    "Heal",
    "LinkChange",
    "LossChange",
    "NodeFailure",
    "NodeRestart",
    "Partition",
    "Scenario",
    "load_scenario",
    "loads_scenario",
    "scenario_from_document",
]
