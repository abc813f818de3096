"""``mso sweep``: a study of seeds × policies × scenarios in virtual time, on Ray or local
processes, gathered into one table (CSV, JSON, Markdown) and four plots."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import click

from mso.cli.common import user_errors
from mso.cliargs import POSITIVE
from mso.errors import MsoError


@click.command()
@click.option(
    "--scenario", "scenario_files", multiple=True, required=True,
    type=click.Path(dir_okay=False, path_type=Path), help="A scenario file (repeat for more).",
)  # fmt: skip
@click.option("--app", "app_file", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--policy", "policies", multiple=True, default=("lifetime",), show_default=True,
    help="A node policy (repeat for more): balance, delay, energy, lifetime or pkg.module:attr.",
)  # fmt: skip
@click.option("--seeds", type=int, default=3, show_default=True, help="Seeds 0 .. SEEDS-1.")
@click.option(
    "--duration", type=POSITIVE, default=30.0, show_default=True, help="Virtual seconds a run."
)
@click.option("--workers", type=int, default=2, show_default=True, help="Runs at once.")
@click.option(
    "--backend", type=click.Choice(["auto", "ray", "processes"]), default="auto",
    show_default=True, help="auto: Ray when installed, else local processes.",
)  # fmt: skip
@click.option("--address", help="An existing Ray cluster's address (ray://HOST:PORT or auto).")
@click.option(
    "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("sweep"),
    show_default=True, help="Directory for runs.csv, runs.json, summary.md and the plots.",
)  # fmt: skip
@click.option("--no-plots", is_flag=True, help="Write the tables only.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@user_errors
def sweep(
    scenario_files: tuple[Path, ...],
    app_file: Path,
    policies: tuple[str, ...],
    seeds: int,
    duration: float,
    workers: int,
    backend: str,
    address: str | None,
    out_dir: Path,
    no_plots: bool,
    as_json: bool,
) -> None:
    """Run a study: every scenario × policy × seed simulated (the app deployed at t=0), then one
    table of the runs, a summary (mean ± sd over seeds) and plots.

    \b
      mso sweep --scenario g100.yaml --scenario g400.yaml --app app.yaml \\
                --policy lifetime --policy energy --seeds 10 --workers 2 --out study
    """
    from mso.management.policy import load_policy
    from mso.model.appfile import load_app
    from mso.model.yamlfile import read_text_file
    from mso.scenario import load_scenario
    from mso.sim import sweep as sw

    if seeds < 1:
        raise MsoError(f"--seeds: expected at least 1, got {seeds}")
    if workers < 1:
        raise MsoError(f"--workers: expected at least 1, got {workers}")
    for p in policies:
        load_policy(p, where=f"--policy {p}")
    scenarios = []
    for f in scenario_files:
        load_scenario(f)  # a bad file is reported with its line, before anything runs
        scenarios.append((str(f), read_text_file(f)))
    load_app(app_file)
    chosen = sw.backend_for(backend, address)
    if chosen == "processes" and backend == "auto" and workers > 1:
        click.echo(
            f"note: Ray is not installed ({sw.INSTALL}): {workers} local processes", err=True
        )
    jobs = sw.jobs(scenarios, (str(app_file), read_text_file(app_file)), list(policies),
                   list(range(seeds)), duration)  # fmt: skip
    count = [0]

    def done(row: dict[str, object]) -> None:
        count[0] += 1
        click.echo(
            f"[{count[0]}/{len(jobs)}] {row['scenario']} {row['policy']} seed {row['seed']}: "
            f"{row['delivered']} delivered, {row['moves']} moves, {row['wall_s']} s",
            err=True,
        )

    rows = sw.execute(jobs, workers=workers, backend=chosen, address=address, done=done)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        with (out_dir / "runs.csv").open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=sw.COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        (out_dir / "runs.json").write_text(json.dumps({"backend": chosen, "runs": rows}) + "\n")
        lines = sw.summary(rows)
        table = sw.markdown(lines)
        (out_dir / "summary.md").write_text(table)
    except OSError as exc:
        raise MsoError(f"--out: cannot write {out_dir}: {exc.strerror}") from None
    plots = []
    if not no_plots and rows:
        from mso.plots import sweep as plot

        plots = [str(p) for p in plot(rows, out_dir)]
    if as_json:
        click.echo(json.dumps({"backend": chosen, "runs": len(rows), "summary": lines,
                               "out": str(out_dir), "plots": plots}))  # fmt: skip
        return
    click.echo(table, nl=False)
    for path in plots:
        click.echo(f"plot: {path}")
    click.echo(f"{len(rows)} runs on {chosen}: {out_dir}/runs.csv, runs.json, summary.md")
