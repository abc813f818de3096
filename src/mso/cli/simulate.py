"""``mso simulate``: a scenario in virtual time, reported as tables or JSON (and a plot)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from mso.cli.common import console, progress, user_errors
from mso.cliargs import NON_NEGATIVE, POSITIVE
from mso.errors import MsoError


@click.command()
@click.argument("scenario_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--app", "app_file", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of emulated loss.")
@click.option(
    "--duration", type=POSITIVE, default=30.0, show_default=True, help="Virtual seconds to run."
)
@click.option("--via", help="Node to deploy from (default: the first node).")
@click.option(
    "--convergence", type=NON_NEGATIVE, default=0.0, show_default=True,
    help="Seconds routes take to follow a link change.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Also draw the report as a PNG: vertex moves, failures, rejoins, energy per node.",
)
@user_errors
def simulate(
    scenario_file: Path,
    app_file: Path,
    seed: int,
    duration: float,
    via: str | None,
    convergence: float,
    as_json: bool,
    plot: Path | None,
) -> None:
    """Run a scenario in virtual time (the daemon's node code, the scenario's timeline)."""
    from mso.model.appfile import load_app
    from mso.model.yamlfile import read_text_file
    from mso.scenario import load_scenario
    from mso.sim.play import simulate as run

    scenario = load_scenario(scenario_file)
    load_app(app_file)  # a bad app file is reported with its file and line, before anything runs
    if convergence < 0:
        raise MsoError(f"--convergence: expected seconds >= 0, got {convergence:g}")
    doc = read_text_file(app_file)
    with progress(f"simulating {duration:g} s of {scenario.name}…"):
        report = run(
            scenario, doc, str(app_file), seed=seed, duration=duration,
            convergence_s=convergence, via=via,
        )  # fmt: skip
    if as_json:
        click.echo(json.dumps(report, sort_keys=True))
    else:
        from mso.cli.render import render_simulation

        render_simulation(console(), report)
    if plot is not None and report["deploy"]["ok"]:
        from mso.plots import simulation

        simulation(report, plot)
        click.echo(f"plot: {plot}", err=as_json)
    if not report["deploy"]["ok"]:
        raise MsoError(f"deployment failed: {report['deploy']['error']}")
