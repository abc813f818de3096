"""Errors blamed where they belong: an output that does not fit its edge's declared format is
counted at the producer, named by the edge's vertices; status and the emulator's console show
it."""

from __future__ import annotations

from mso.sim.runner import Simulation
from mso.statusview import error_alarms, status_text
from test_runtime_sim import PIPE, deploy, line


def test_a_wrong_output_is_counted_at_its_producer_naming_the_edge() -> None:
    sim = Simulation(line(4))
    assert deploy(sim, PIPE.replace("runtime_vertices:Double", "runtime_vertices:WrongOutput")).ok
    sim.run_until(sim.now + 2.0)
    nodes = {n: core.status(sim.now) for n, core in sim.cores.items()}
    vertices = {
        v: st
        for node in nodes.values()
        for v, st in node["apps"].get("pipe", {"vertices": {}})["vertices"].items()
    }
    mid, sink = vertices["mid"], vertices["sink"]
    assert mid["errors"] >= 100 and sink["errors"] == 0, (mid, sink)
    assert mid["last_error"].startswith(
        "output dict does not match Num, the format of edge mid -> sink: "
    ), mid["last_error"]
    assert sink["processed"] == 0  # nothing wrong went out
    text = status_text(nodes)
    assert "crashes" in text and "stats" in text
    assert "  mid: last error: output dict does not match Num" in text, text
    seen: dict[str, int] = {}
    (alarm,) = error_alarms(seen, nodes, "pipe")
    assert alarm.startswith("vertex mid on N") and "new errors" in alarm, alarm
    assert error_alarms(seen, nodes, "pipe") == []  # no growth since: no alarm
