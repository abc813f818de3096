"""Plots are drawn from the JSON the commands and benchmarks write."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from mso import plots
from mso.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"
PNG = b"\x89PNG\r\n\x1a\n"


def test_simulate_draws_its_report(tmp_path: Path) -> None:
    out = tmp_path / "sim.png"
    result = CliRunner().invoke(
        main,
        ["simulate", str(EXAMPLES / "convoy-energy.yaml"), "--app", str(EXAMPLES / "convoy.yaml"),
         "--duration", "20", "--json", "--plot", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.stderr
    report = json.loads(result.stdout)
    assert set(report["energy"]) == {"N1", "N2", "N3", "N4"}  # what the battery plot draws
    assert out.read_bytes().startswith(PNG) and out.stat().st_size > 20_000


def test_benchmark_plots(tmp_path: Path) -> None:
    machine = {"machine": {"load_average": [1.0, 1.0, 1.0], "cpus": 2}}
    cpu = {"with": 1.2, "without": 1.0, "added": 0.2}
    results = {
        "dashboard": {"cost": {"node_cpu_pct": {"N1": cpu, "N2": cpu}}} | machine,
        "cli_startup": {"target_status_ms": 150,
                        "commands": {"mso status": {"p50_ms": 90.0, "p90_ms": 110.0}}} | machine,
        "rates": {"rows": [{"asked": 1.0, "got": 1.0, "error_pct": 0.0},
                           {"asked": 10.0, "got": 9.99, "error_pct": -0.1}]},
        "scale": {"sizes": [
            {"topology": "grid", "nodes": n, "startup_cpu_s": n / 100,
             "cpu_ms_per_node_per_sim_s": 2.0} for n in (25, 100)
        ] + [{"topology": "grid", "nodes": 1000, "error": "over the 10 s limit"}]},
    }  # fmt: skip
    assert set(results) == set(plots.BENCHMARKS)
    for name, draw in plots.BENCHMARKS.items():
        out = draw(results[name], tmp_path / f"{name}.png")
        assert out.read_bytes().startswith(PNG), name
