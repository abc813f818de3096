"""The simulator plays a scenario's timeline (the same player as the emulator): ``mso simulate``,
emulated loss, control frames that wait for routes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from mso.cli import main
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import Send
from mso.protocol import messages as m
from mso.scenario import loads_scenario
from mso.scenario.timeline import Timeline
from mso.sim.play import drive, simulate
from mso.sim.runner import Simulation

MESH = """\
name: mesh6
link_defaults: {delay_ms: 1.0}
nodes: {N1: {battery_wh: 20}, N2: {}, N3: {}, N4: {}, N5: {}, N6: {}}
links: [[N1, N2], [N2, N3], [N3, N6], [N1, N4], [N4, N5], [N5, N6], [N2, N5], [N3, N5]]
"""
APP = """\
name: pipe
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 100,
        output: runtime_vertices:Num}
  mid: {code: runtime_vertices:Double, pinned: N3}
  sink: {code: runtime_vertices:Recorder, pinned: N6}
edges: [[src, mid], [mid, sink]]
"""


def files(tmp_path: Path, changes: str) -> tuple[str, str]:
    sc, app = tmp_path / "mesh.yaml", tmp_path / "pipe.yaml"
    sc.write_text(MESH + changes)
    app.write_text(APP)
    return str(sc), str(app)


def run_cli(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(main, ["simulate", *args])
    return result.exit_code, result.output


def test_simulate_plays_a_restart_and_reports_it(tmp_path: Path) -> None:
    # mid is pinned to N3: while N3 is down its chain is parked, then N3 comes back as a new
    # incarnation and gets mid back
    sc, app = files(tmp_path, "changes:\n  - {at: 2, fail: N3}\n  - {at: 4, restart: N3}\n")
    code, out = run_cli(sc, "--app", app, "--duration", "8", "--json")
    assert code == 0, out
    r: dict[str, Any] = json.loads(out)
    assert r["timeline"] == [[2.0, "fail N3"], [4.0, "restart N3"]]
    assert {f["node"] for f in r["failures"]} == {"N3"}
    assert [(j["node"], j["incarnation"]) for j in r["reconfigurations"]["rejoins"]] == [("N3", 1)]
    assert r["energy"]["N3"]["incarnation"] == 1 and all(e["alive"] for e in r["energy"].values())
    assert r["placement"] == {"src": "N1", "mid": "N3", "sink": "N6"}
    ev = r["events"]
    # parked for about 2 s at 100 events/s: the source kept them (store and forward) and they
    # arrived once mid was back, with what was on the way to N3 when it died (unacknowledged)
    assert ev["given_up"] == 0, ev
    assert ev["emitted"]["src"] >= 790
    assert 0 <= ev["emitted"]["src"] - ev["delivered"]["sink"] <= 20, ev
    # human output: the same figures as tables
    code, text = run_cli(sc, "--app", app, "--duration", "8")
    assert code == 0, text
    assert "N3 rejoined as incarnation 1" in text and "energy per node" in text
    assert "fail N3" in text and "delivered" in text


def test_simulate_is_deterministic_and_loss_is_seeded(tmp_path: Path) -> None:
    sc, app = files(tmp_path, "changes:\n  - {at: 1, loss: 0.2}\n  - {at: 3, loss: 0}\n")
    doc = Path(app).read_text()
    runs = [simulate(loads_scenario(Path(sc).read_text()), doc, app, seed=s, duration=4)
            for s in (1, 1, 2)]  # fmt: skip
    assert runs[0] == runs[1]
    assert runs[0]["events"]["frames_lost_on_links"] > 50
    assert runs[0]["events"]["frames_lost_on_links"] != runs[2]["events"]["frames_lost_on_links"]
    # lost frames are resent: once the loss stops, the sink catches up with the source
    ev = runs[0]["events"]
    assert ev["delivered"]["sink"] >= ev["emitted"]["src"] - 5, ev
    clean = simulate(loads_scenario(MESH), doc, app, duration=4)
    assert clean["events"]["frames_lost_on_links"] == 0


def test_simulate_plays_a_partition_and_its_heal(tmp_path: Path) -> None:
    sc, app = files(
        tmp_path,
        "changes:\n  - {at: 2, partition: [[N1, N2, N3], [N4, N5, N6]]}\n  - {at: 4, heal: true}\n",
    )
    code, out = run_cli(sc, "--app", app, "--duration", "9", "--json")
    assert code == 0, out
    r = json.loads(out)
    # src on N1, mid on N3, the sink on N6: neither side can run the app alone, so neither
    # declares the other (out of reach is not failed; each side used to, and one reset)
    assert r["failures"] == [] and r["reconfigurations"]["rejoins"] == []
    ev = r["events"]
    assert ev["delivered"]["sink"] > 300, ev  # the flow came back after the heal, with
    assert 0 <= ev["emitted"]["src"] - ev["delivered"]["sink"] <= 20, ev  # what was kept


def test_bad_arguments_exit_2_with_a_clear_message(tmp_path: Path) -> None:
    sc, app = files(tmp_path, "")
    code, out = run_cli(sc, "--app", app, "--duration", "0")
    assert code == 2 and "'--duration': expected a finite number > 0, got '0'" in out, out
    code, out = run_cli(sc, "--app", app, "--via", "N9")
    assert code == 2 and "--via: unknown node 'N9'" in out, out
    code, out = run_cli(sc, "--app", str(tmp_path / "none.yaml"))
    assert code == 2 and "none.yaml" in out, out
    code, out = run_cli(sc)
    assert code == 2 and "--app" in out, out
    bad = tmp_path / "bad.yaml"
    bad.write_text(MESH + "changes:\n  - {at: 1, restart: N9}\n")
    code, out = run_cli(str(bad), "--app", app)
    assert code == 2 and "bad.yaml:6: changes[0].restart: unknown node 'N9'" in out, out


def test_a_control_frame_with_no_route_waits_for_one_and_data_does_not() -> None:
    net = Network([NodeSpec("A"), NodeSpec("B")], [])
    sim = Simulation(net, manage=False)
    sim.trace = []
    ack = m.Ack("x", 0, 0, 1)
    sim.apply("A", [Send("B", m.StatusRequest(req=7)), Send("B", ack)])
    assert len(sim.waiting["A"]) == 1 and sim.waiting["A"].dropped == 1  # the ack is data
    drive(sim, Timeline(loads_scenario("nodes: {A: {}, B: {}}\n"), network=net), 0.5)
    assert len(sim.waiting["A"]) == 1  # no route yet: still held
    net.add_link(LinkSpec("A", "B", delay_ms=1.0))
    sim.links_changed()  # routes converge within the wait: it leaves
    assert len(sim.waiting["A"]) == 0
    sim.run_until(sim.now + 0.1)
    got = [(n, src) for _, n, src, kind in sim.trace if kind == "StatusRequest"]
    assert got == [("B", "A")]
    # held longer than the route wait (1 s): given up, not sent when a route finally appears
    net.remove_link("A", "B")
    sim.links_changed()
    sim.apply("A", [Send("B", m.StatusRequest(req=8))])
    sim.run_until(sim.now + 1.5)
    net.add_link(LinkSpec("A", "B", delay_ms=1.0))
    sim.links_changed()
    sim.run_until(sim.now + 0.1)
    assert [k for _, _, _, k in sim.trace].count("StatusRequest") == 1
    assert sim.waiting["A"].dropped == 2


def test_a_robot_whose_battery_empties_stops_and_the_report_says_so(tmp_path: Path) -> None:
    sc, app = files(tmp_path, "")
    Path(sc).write_text(MESH.replace("N2: {}", "N2: {battery_wh: 0.0005}"))  # about 2 s
    code, out = run_cli(sc, "--app", app, "--duration", "8", "--json")
    assert code == 0, out
    r: dict[str, Any] = json.loads(out)
    ((at, what),) = r["timeline"]
    assert what == "fail N2 (battery empty: fail-stop)" and 0.5 < at < 6.0
    assert r["energy"]["N2"]["battery_empty"] and not r["energy"]["N2"]["alive"]
    # N2 ran nothing: out of reach, held unreachable, never declared (nothing needed it)
    assert "N2" not in r["alive"] and r["failures"] == []
    assert r["events"]["delivered"]["sink"] > 0.8 * r["events"]["emitted"]["src"]
    code, text = run_cli(sc, "--app", app, "--duration", "8")
    assert code == 0 and " empty │" in text and "battery empty: fail-stop" in text


def test_a_restarted_source_reports_what_it_emitted_and_what_it_skipped(tmp_path: Path) -> None:
    """The source's own node fails and restarts: its edge numbers on from the bound its old
    process saved, past every number used. What it emitted is what both processes numbered
    (100/s for about 6 of the 8 s), not the highest number (it counted the skipped ones: the
    convoy's laser reported 1,145 for 170 events); the skipped numbers are said apart."""
    sc, app = files(tmp_path, "changes:\n  - {at: 2, fail: N1}\n  - {at: 4, restart: N1}\n")
    code, out = run_cli(sc, "--app", app, "--duration", "8", "--json")
    assert code == 0, out
    ev = json.loads(out)["events"]
    assert 560 <= ev["emitted"]["src"] <= 620 and ev["skipped"]["src"] >= 800, ev
    code, text = run_cli(sc, "--app", app, "--duration", "8")
    assert code == 0 and "sequence numbers a restarted source skipped" in text, text
    # its instances went with its old incarnation before it was declared: the recovery says
    # so (it read "recovery from -", and the move "asked by a recovery after  failed")
    assert "recovery from N1 restarted (its instances gone)" in text, text
