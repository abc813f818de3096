"""``mso sweep``: a tiny study (2 seeds × 2 policies) on local processes gathered into one
table, summary and plots; the same study on Ray when it is installed; its arguments refused
in one line with exit code 2."""

from __future__ import annotations

import csv
import importlib.util
import json
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.scenario.generate import Spec, dumps, generate
from mso.sim import sweep as sw

APP = """\
name: pipe4
vertices:
  src: {code: mso.sim.vertices:Source, params: {name: src}, rate: 5, pinned: N1,
        output: mso.sim.vertices:Ev}
  p1: {code: mso.sim.vertices:Pass, cost: 1, output: mso.sim.vertices:Ev}
  p2: {code: mso.sim.vertices:Pass, cost: 1, output: mso.sim.vertices:Ev}
  sink: {code: mso.sim.vertices:Sink, params: {run: sweep, name: sink}, pinned: N9}
edges: [[src, p1], [p1, p2], [p2, sink]]
"""


def run(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args))
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture
def study(tmp_path: Path) -> list[str]:
    spec = Spec("grid", 12, seed=1, degree=4, mobility="random_waypoint", speed=(20.0, 40.0))
    (tmp_path / "g12.yaml").write_text(dumps(generate(spec), spec))
    (tmp_path / "app.yaml").write_text(APP)
    return [
        "sweep", "--scenario", str(tmp_path / "g12.yaml"), "--app", str(tmp_path / "app.yaml"),
        "--policy", "lifetime", "--policy", "energy", "--seeds", "2", "--duration", "4",
    ]  # fmt: skip


def _check_outputs(out: Path) -> list[dict[str, str]]:
    with (out / "runs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["policy"], r["seed"]) for r in rows] == [
        ("lifetime", "0"),
        ("lifetime", "1"),
        ("energy", "0"),
        ("energy", "1"),
    ]
    assert all(r["deploy_ok"] == "True" and int(r["delivered"]) > 0 for r in rows)
    runs = json.loads((out / "runs.json").read_text())["runs"]
    assert len(runs) == 4 and all(len(r["series"]["t"]) == 5 for r in runs)  # t = 0 .. 4
    assert all(r["series"]["energy_j"][-1] > r["series"]["energy_j"][0] for r in runs)
    summary = (out / "summary.md").read_text().splitlines()
    assert len(summary) == 4 and "| grid-12-s1 | 12 | lifetime | 2 | 2 |" in summary[2]
    return rows


def test_a_tiny_study_on_local_processes(study: list[str], tmp_path: Path) -> None:
    out = tmp_path / "study"
    code, stdout, err = run(*study, "--backend", "processes", "--workers", "2", "--out", str(out))
    assert code == 0, err
    rows = _check_outputs(out)
    assert "[4/4]" in err and "4 runs on processes" in stdout
    for name in ("energy", "reconfigurations", "delay_cdf", "control_vs_n"):
        assert (out / f"{name}.png").stat().st_size > 1000
    # a seed is a seed: the same run again (one process) gives the same figures; its summary
    # in JSON on stdout
    again = tmp_path / "again"
    code, said, err = run(*study, "--backend", "processes", "--workers", "1", "--no-plots",
                          "--json", "--out", str(again))  # fmt: skip
    assert code == 0, err
    same = _check_outputs(again)
    keys = ("delivered", "messages", "energy_j", "moves")
    assert [[r[k] for k in keys] for r in rows] == [[r[k] for k in keys] for r in same]
    assert not (again / "energy.png").exists()
    summary = json.loads(said)
    assert summary["runs"] == 4 and summary["plots"] == []
    assert [(s["policy"], s["runs"], s["deployed"]) for s in summary["summary"]] == [
        ("lifetime", 2, 2),
        ("energy", 2, 2),
    ]


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is not installed")
def test_the_same_study_on_ray_local_workers(study: list[str], tmp_path: Path) -> None:
    out = tmp_path / "ray"
    code, stdout, err = run(*study, "--backend", "ray", "--workers", "2", "--no-plots",
                            "--out", str(out))  # fmt: skip
    assert code == 0, err
    _check_outputs(out)
    assert "4 runs on ray" in stdout


def test_without_ray_auto_falls_back_and_ray_asked_for_says_how_to_install(
    study: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # an import of ray now fails
    assert sw.backend_for("auto", None) == "processes"
    code, _, err = run(*study, "--backend", "ray", "--out", str(tmp_path / "x"))
    assert code == 2 and err.strip() == f"error: Ray is not installed: {sw.INSTALL}"
    code, _, err = run(*study, "--address", "ray://127.0.0.1:10001", "--out", str(tmp_path / "x"))
    assert code == 2 and "Ray is not installed" in err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--seeds", "0"], "error: --seeds: expected at least 1, got 0"),
        (["--workers", "0"], "error: --workers: expected at least 1, got 0"),
        (["--policy", "fastest"], "error: --policy fastest: unknown policy 'fastest'"),
        (["--duration", "-1"], "--duration"),
        (["--backend", "processes", "--address", "auto"], "error: --address names a Ray cluster"),
    ],
)
def test_bad_sweep_arguments(study: list[str], extra: list[str], message: str) -> None:
    code, _, err = run(*study, *extra)
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1


def test_a_bad_scenario_is_reported_before_any_run(study: list[str], tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes: {A: {cpu: 0}}\n")
    code, _, err = run(*study, "--scenario", str(bad))
    assert code == 2 and "bad.yaml:1: nodes.A.cpu: expected a number > 0" in err
