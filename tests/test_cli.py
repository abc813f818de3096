"""The `mso` command: JSON outputs, the demo, and clear one-line errors with exit code 2."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


def run(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args))
    return result.exit_code, result.stdout, result.stderr


def test_chains_json_fig2() -> None:
    code, out, _ = run("chains", str(EXAMPLES / "fig2.yaml"), "--json")
    assert code == 0
    assert json.loads(out) == {
        "chains": [
            ["A", "B", "C", "D"],
            ["D", "E"],
            ["F", "G"],
            ["G", "D"],
            ["G", "H", "I"],
        ]
    }


def test_plan_json_section33() -> None:
    code, out, _ = run(
        "plan",
        str(EXAMPLES / "section33.yaml"),
        "--scenario",
        str(EXAMPLES / "line4.yaml"),
        "--planner",
        "paper",
        "--json",
    )
    assert code == 0
    doc = json.loads(out)
    placement = doc["placement"]
    assert placement["A"] == "N1" and placement["F"] == "N4"
    # A-B-C-D is allocated N1-N2-N3 (paper §3.3): D must not reach N4.
    assert {placement[v] for v in "BCD"} <= {"N1", "N2", "N3"}
    assert placement["D"] == "N3"
    chains = [tuple(c) for c in doc["chains"]]
    order = [chains[i] for i in doc["order"]]
    assert order.index(("A", "B", "C", "D")) < order.index(("D", "F"))
    assert order.index(("E", "D")) < order.index(("D", "F"))


def test_minimal_yaml_is_enough_for_planning(tmp_path: Path) -> None:
    app = tmp_path / "fig2.yaml"
    app.write_text("name: fig2\nvertices:\n  A: {pinned: N1}\n  B: {}\nedges:\n  - [A, B]\n")
    code, out, _ = run("plan", str(app), "--scenario", str(EXAMPLES / "line4.yaml"), "--json")
    assert code == 0
    assert json.loads(out)["placement"] == {"A": "N1", "B": "N1"}


@pytest.mark.slow
def test_demo_prints_chains_and_placement_and_runs_the_app() -> None:
    code, out, err = run("demo", "--duration", "12")  # on the run's clock: the start included
    assert code == 0, f"{err}\n{out[-3000:]}"  # (exit 2 once at load 17, and nothing said why)
    assert "laser@N1" in out and "storage@N4" in out
    assert re.search(r"deployed in \d+ ms", out)
    # every robot's battery and drain on one line, even in a pipe (80 columns), with what its
    # vertex code's CPU takes once there are two samples
    line = r"t=\s*\d+\.\ds\s+N1\s+\d+\.\d% [\d.]+ W .*N4\s+\d+\.\d% [\d.]+ W( \(CPU \d+ mW\))?\n"
    assert re.search(line, out)
    assert "(a chain remap, §3.4.2)" in out and "(a recovery: the global remap, §3.4.3)" in out
    # the summary read back from SQLite: every scan emitted is a stored row, and no more
    got = re.search(r"trajectory rows stored / laser events emitted\D+(\d+) / (\d+)", out)
    assert got and int(got[1]) == int(got[2]) > 5


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "name: x\nvertices:\n  A: {cost: -1}\n",
            "bad.yaml:3: vertices.A.cost: expected a non-negative",
        ),
        (
            "name: x\nvertices:\n  A: {}\nedges:\n  - [A, Z]\n",
            "bad.yaml:5: edges[0]: unknown vertex 'Z'",
        ),
        ("name: x\nvertices: [1, 2\n", "bad.yaml:2: malformed YAML"),
        (
            "name: x\nvertices:\n  A: {colour: red}\n",
            "bad.yaml:3: vertices.A.colour: unknown attribute",
        ),
    ],
)
def test_bad_app_is_one_line_and_exit_2(tmp_path: Path, text: str, expected: str) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    code, out, err = run("chains", str(bad))
    assert code == 2
    assert out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert expected in err


def test_bad_scenario_is_reported(tmp_path: Path) -> None:
    scen = tmp_path / "scen.yaml"
    scen.write_text("nodes:\n  N1: {}\n  N2: {cpu: 0}\nlinks:\n  - [N1, N2]\n")
    code, _, err = run("plan", str(EXAMPLES / "fig2.yaml"), "--scenario", str(scen))
    assert code == 2
    assert "scen.yaml:3: nodes.N2.cpu: expected a number > 0, got 0" in err


def test_unknown_pinned_node_is_a_planning_error() -> None:
    code, _, err = run(
        "plan",
        str(EXAMPLES / "convoy.yaml"),
        "--scenario",
        str(EXAMPLES / "line4.yaml"),
        "--origin",
        "N9",
    )
    assert code == 2
    assert "N9" in err


def test_missing_file() -> None:
    code, _, err = run("validate", "/nonexistent/app.yaml")
    assert code == 2
    assert "cannot read file" in err


def test_node_config_errors(tmp_path: Path) -> None:
    cfg = tmp_path / "node.yaml"
    cfg.write_text("id: N1\nlisten: 127.0.0.1:1\ncolour: red\n")
    code, _, err = run("node", "--config", str(cfg))
    assert code == 2
    assert "node.yaml:3: colour: unknown attribute 'colour'" in err
    code, _, err = run("node")
    assert code == 2 and "needs an id" in err


def test_bad_scenario_for_emulate_starts_nothing(tmp_path: Path) -> None:
    scen = tmp_path / "scen.yaml"
    scen.write_text("nodes:\n  N1: {}\nlinks:\n  - [N1, N9]\n")
    code, _, err = run("emulate", str(scen), "--duration", "1")
    assert code == 2
    assert "scen.yaml:4: links[0]: unknown node 'N9'" in err


def test_plan_with_a_baseline_and_compare() -> None:
    app, scen = str(EXAMPLES / "convoy.yaml"), str(EXAMPLES / "convoy-line.yaml")
    code, out, _ = run("plan", app, "--scenario", scen, "--planner", "source", "--json")
    assert code == 0
    doc = json.loads(out)
    assert set(doc["placement"].values()) == {"N1", "N4"}  # all at the source, storage pinned
    code, out, _ = run("compare", app, "--scenario", scen, "--json")
    assert code == 0
    rows = json.loads(out)
    assert rows["optimal:energy"]["energy"] <= rows["algorithm1"]["energy"] + 1e-12
    assert rows["optimal:max_load"]["max_load"] <= rows["algorithm1"]["max_load"] + 1e-12
    assert rows["algorithm1"]["max_load"] < rows["source"]["max_load"]  # offloading helps


def test_help_explains_the_concepts_and_completion_is_there() -> None:
    code, out, _ = run("--help")
    assert code == 0
    for word in ("chains", "overlay", "relocate", "remap", "--dashboard", "completion"):
        assert word in out
    code, out, _ = run("completion", "bash")
    assert code == 0 and "_MSO_COMPLETE=bash_complete" in out
    code, _, err = run("completion", "tcsh")
    assert code == 2 and "tcsh" in err


def test_every_reporting_command_has_json() -> None:
    import click

    shows = {"node", "dashboard", "completion", "demo", "bench", "emulator"}  # serve, print, act
    commands = list(main.commands.items())  # type: ignore[attr-defined]
    for name, cmd in commands:
        if name in shows:
            continue
        if isinstance(cmd, click.Group):  # (mso scenario generate): its commands each
            commands += [(f"{name} {n}", c) for n, c in cmd.commands.items()]
            continue
        flags = {o for p in cmd.params if isinstance(p, click.Option) for o in p.opts}
        assert "--json" in flags, name
    code, out, _ = run("validate", str(EXAMPLES / "fig2.yaml"), "--json")
    assert code == 0 and json.loads(out) == {"app": "fig2", "vertices": 9, "edges": 8}


def test_the_status_path_imports_no_planner_rich_or_asyncio() -> None:
    """`mso status` starts fast because its whole path (parse, ask a node, render) imports
    neither numpy, scipy, the planner, rich nor asyncio; the time itself is measured by
    bench/cli_startup.py. The node asked is a closed loopback port, so the command fails after
    it has tried to connect."""
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "from mso.cli import main\n"
        "try:\n"
        "    main(['status', '--via', '127.0.0.1:1'])\n"
        "except SystemExit as exc:\n"
        "    print('exit', exc.code)\n"
        "heavy = {'numpy', 'scipy', 'yaml', 'mso.planning.placement', 'mso.model.app', 'rich',\n"
        "         'asyncio'}\n"
        "print(sorted(heavy & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == ["exit 2", "[]"], out
    assert "cannot reach node at 127.0.0.1:1" in out.stderr


def test_status_watch_needs_a_positive_period() -> None:
    code, _, err = run("status", "--watch", "0", "--via", "127.0.0.1:9")
    assert code == 2 and "--watch: expected seconds > 0" in err


def test_plan_and_compare_name_the_planner() -> None:
    app, scen = str(EXAMPLES / "camera.yaml"), str(EXAMPLES / "camera-line.yaml")
    code, out, _ = run("plan", app, "--scenario", scen, "--planner", "bytes", "--json")
    assert code == 0
    doc = json.loads(out)
    assert doc["split"] == "bytes" and doc["placement"]["downscale"] == "R1"
    code, out, _ = run("plan", app, "--scenario", scen, "--json")
    assert json.loads(out)["split"] == "bytes"  # the default
    code, out, _ = run("plan", app, "--scenario", scen, "--planner", "paper", "--json")
    assert json.loads(out)["split"] == "paper" and json.loads(out)["placement"]["downscale"] == "R2"
    code, out, _ = run("compare", app, "--scenario", scen, "--json")
    assert code == 0
    rows = json.loads(out)
    assert rows["algorithm1"] == rows["algorithm1:bytes"]
    assert rows["algorithm1:bytes"]["energy"] < rows["algorithm1:paper"]["energy"] / 2
    # the optimum respects capacity: the camera robot is not loaded beyond its CPU
    assert rows["optimal:energy"]["energy"] <= rows["algorithm1:bytes"]["energy"] + 1e-12
    code, out, err = run("deploy", app, "--planner", "fastest")
    assert code != 0 and "fastest" in out + err


def test_the_progress_line_says_when_the_app_runs_nowhere() -> None:
    from mso.cli.render import sink_line

    sink = {"kind": "sink", "processed": 7}
    nodes = {"N4": {"node": "N4", "apps": {"pipe": {"vertices": {"sink": sink}}}}}
    assert sink_line(nodes, "pipe") == "sink@N4: 7 events"
    assert sink_line(nodes, "convoy") == "convoy runs nowhere (undeployed?); running: pipe"
