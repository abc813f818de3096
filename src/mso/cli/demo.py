"""``mso demo``: the bundled convoy app, planned and then run on an emulated 4-robot line."""

from __future__ import annotations

import click

from mso.cli.common import EXAMPLES, console, user_errors
from mso.cliargs import POSITIVE


@click.command(short_help="Run the bundled convoy app on an emulated 4-robot line.")
@click.option(
    "--duration",
    type=POSITIVE,
    default=56.0,
    show_default=True,
    help="Seconds to run, the nodes' start included, and at least 3 after the deploy (56: N3's "
    "battery empties about 44 s in, and the leader turns the first corner, where the second "
    "survivor lies).",
)
@click.option("--plan-only", is_flag=True, help="Only form chains and plan; start no nodes.")
@click.option(
    "--dashboard",
    is_flag=True,
    help="Serve the live web dashboard while it runs (its address is printed).",
)
def demo(duration: float, plan_only: bool, dashboard: bool) -> None:
    """Run the bundled convoy app (paper Fig. 6) on an emulated 4-robot line."""
    _demo(duration, plan_only, dashboard)


@user_errors
def _demo(duration: float, plan_only: bool, dashboard: bool = False) -> None:
    from mso.cli.render import render_plan
    from mso.model.appfile import load_app
    from mso.planning.placement import plan
    from mso.scenario import load_scenario

    out = console()
    app_file, scenario_file = EXAMPLES / "convoy.yaml", EXAMPLES / "convoy-demo.yaml"
    app = load_app(app_file)
    scenario = load_scenario(scenario_file)
    out.print(
        f"[bold]mso demo[/bold]: the convoy app of the MSO paper (Fig. 6), "
        f"{len(app.vertices)} vertices and {len(app.edges)} edges, on {scenario.name} "
        f"({' - '.join(scenario.network.nodes)})\n"
    )
    result = plan(app, scenario.network)
    render_plan(out, app, scenario, result)
    if not plan_only:
        from mso.examples.convoy.demo import run_demo

        out.print(f"\n[bold]running it[/bold] on 4 emulated robots for {duration:g} s")
        run_demo(out, duration, dashboard)
