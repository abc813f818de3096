"""The Python API's ways in: an app built in Python (or given as text) deploys as a file does,
an overlay is found by its name, and an emulation or a simulation runs from plain code."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest

from mso import App
from mso.api import deploy_request, resolve_address
from mso.emu.overlays import overlays_dir, state_file
from mso.emu.session import Emulation, simulate
from mso.errors import MsoError
from mso.model.appfile import load_app, loads_app
from runtime_vertices import CountingSource, Double, Num, Recorder, pipe_app

TESTS = Path(__file__).resolve().parent
EXAMPLES = TESTS.parent / "examples"
LINE = """
name: line
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""


def built_pipe() -> App:
    """The tests' pipe app, built in Python with the classes themselves."""
    app = App("pipe")
    app.vertex("src", CountingSource, pinned="N1", rate=200, output=Num)
    app.vertex("mid", Double, output=Num, cost=0.5)
    app.vertex("sink", Recorder, pinned="N4")
    app.edge("src", "mid", size=40)
    app.edge("mid", "sink", keep_last=10, qos="best_effort")
    return app


def test_an_app_built_in_python_is_sent_as_the_file_it_would_be() -> None:
    req = deploy_request(built_pipe())
    sent = loads_app(req.document, file=req.file)
    assert sent.vertices["src"].code == "runtime_vertices:CountingSource"
    assert sent.vertices["src"].output is Num  # resolved from "runtime_vertices:Num"
    assert "runtime_vertices:Num" in req.document
    assert sent.vertices["mid"].cost == 0.5 and sent.vertices["src"].rate == 200
    assert [(e.src, e.dst, e.size, e.keep_last, e.qos) for e in sent.edges] == [
        ("src", "mid", 40, None, "reliable"),
        ("mid", "sink", None, 10, "best_effort"),
    ]
    # a file's app goes through unchanged: its document loads to the same app
    convoy = load_app(EXAMPLES / "convoy.yaml")
    from mso.model.appdoc import app_document

    assert loads_app(app_document(convoy)) == convoy


def test_an_app_as_text_or_path_and_code_no_node_can_import() -> None:
    assert loads_app(deploy_request(pipe_app(5)).document).name == "pipe"
    assert deploy_request(EXAMPLES / "fig2.yaml").file.endswith("fig2.yaml")
    with pytest.raises(MsoError, match=r"<app text>:\d+"):  # text errors point at its lines
        deploy_request("name: x\nvertices: {A: {cost: -1}}\n")

    class Local(msgspec.Struct):
        n: int

    app = built_pipe()
    app.vertices["mid"].output = Local
    with pytest.raises(MsoError, match=r"vertices\.mid\.output: .*Local is defined inside a func"):
        deploy_request(app)


@pytest.fixture
def run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))  # overlays of other tests out of sight
    yield tmp_path


def test_an_overlay_is_found_by_its_name(run_dir: Path) -> None:
    overlays_dir().mkdir(parents=True, exist_ok=True)
    nodes = {"N1": "127.0.1.1:7001", "N2": "127.0.1.2:7001"}
    for name, pid in (("convoy-line", os.getpid()), ("other", os.getpid())):
        state_file(name).write_text(json.dumps({"name": name, "pid": pid, "nodes": nodes}))
    assert resolve_address("convoy-line") == "127.0.1.1:7001"
    assert resolve_address("N2", "other") == "127.0.1.2:7001"  # a node of the overlay named
    with pytest.raises(MsoError, match="unknown node or overlay 'nope'"):
        resolve_address("nope")


def test_a_simulation_from_python() -> None:
    from mso.scenario import loads_scenario

    report = simulate(loads_scenario(LINE), built_pipe(), duration=3.0)
    assert report["deploy"]["ok"]
    assert report["events"]["delivered"]["sink"] == report["events"]["emitted"]["src"] > 0


@pytest.mark.slow
def test_an_emulation_from_python(run_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", str(TESTS))  # the node processes import the test vertices
    from mso.scenario import loads_scenario

    with Emulation(loads_scenario(LINE), app=built_pipe()) as emu:
        assert emu.deployed is not None and emu.deployed.ok
        overlay = emu.overlay
        assert overlay.apps() == ["pipe"]
        assert emu.fail("N3").startswith("N3 failed")  # the emulator's command, in words
        assert "N3" not in emu.emulator.live()
        overlay.undeploy("pipe")
        with pytest.raises(MsoError, match="no running app named 'pipe'"):
            overlay.undeploy("pipe")  # a second undeploy is an error, as `mso undeploy` exits 2
    with pytest.raises(MsoError, match="not running"):
        emu.status()
