"""The ``mso`` command line. Thin: it parses, calls the library, and renders.

Every user error (bad app or scenario file, impossible request) prints one line on stderr and
exits with code 2; a traceback means a bug in mso.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import click
from rich.console import Console
from rich.table import Table

from mso.errors import MsoError
from mso.model.app import App
from mso.model.appfile import load_app
from mso.model.chains import form_chains
from mso.planning.placement import Plan, plan
from mso.scenario import Scenario, load_scenario

F = TypeVar("F", bound=Callable[..., Any])

EXAMPLES = Path(__file__).parent / "examples"


def _user_errors(fn: F) -> F:
    """Turn an MsoError into a one-line message and exit code 2."""

    @wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except MsoError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(exc.exit_code)

    return wrapper  # type: ignore[return-value]


def _console() -> Console:
    return Console(highlight=False)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mso")
def main() -> None:
    """mso: run a dataflow app across a mobile ad hoc network and keep re-placing it."""


no_import = click.option(
    "--no-import",
    is_flag=True,
    help="Do not import vertex code and formats (plan on a machine without the app's modules).",
)


@main.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@no_import
def validate(app_file: Path, no_import: bool) -> None:
    """Check an app file and report the first problem."""
    _validate(app_file, no_import)


@_user_errors
def _validate(app_file: Path, no_import: bool) -> None:
    app = load_app(app_file, resolve_code=not no_import)
    click.echo(f"{app_file}: ok ({len(app.vertices)} vertices, {len(app.edges)} edges)")


@main.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help='Print {"chains": [[head, ..., tail], ...]}.')
@no_import
def chains(app_file: Path, as_json: bool, no_import: bool) -> None:
    """Partition an app into chains (paper §3.2)."""
    _chains(app_file, as_json, no_import)


@_user_errors
def _chains(app_file: Path, as_json: bool, no_import: bool) -> None:
    app = load_app(app_file, resolve_code=not no_import)
    found = form_chains(app)
    if as_json:
        click.echo(json.dumps({"chains": [list(c.vertices) for c in found]}))
        return
    table = Table(title=f"chains of {app.name}")
    table.add_column("#", justify="right")
    table.add_column("head")
    table.add_column("tail")
    table.add_column("vertices")
    for c in found:
        table.add_row(str(c.index), c.head, c.tail, " → ".join(c.vertices))
    _console().print(table)


@main.command(name="plan")
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--scenario",
    "scenario_file",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="The network: nodes, capacities, links.",
)
@click.option("--origin", help="Node that hosts unpinned sources (default: the first node).")
@click.option("--json", "as_json", is_flag=True, help="Print the plan as JSON.")
@no_import
def plan_cmd(
    app_file: Path, scenario_file: Path, origin: str | None, as_json: bool, no_import: bool
) -> None:
    """Place an app on a network with Algorithm 1 (paper §3.3)."""
    _plan(app_file, scenario_file, origin, as_json, no_import)


@_user_errors
def _plan(
    app_file: Path, scenario_file: Path, origin: str | None, as_json: bool, no_import: bool
) -> None:
    app = load_app(app_file, resolve_code=not no_import)
    scenario = load_scenario(scenario_file)
    result = plan(app, scenario.network, origin=origin)
    if as_json:
        click.echo(json.dumps(result.to_json()))
        return
    render_plan(_console(), app, scenario, result)


def render_plan(console: Console, app: App, scenario: Scenario, result: Plan) -> None:
    """Chains with their placement, then the load each node carries."""
    net = scenario.network
    table = Table(title=f"{app.name} on {scenario.name}: chains in placement order")
    table.add_column("step", justify="right")
    table.add_column("chain, head first: vertex@node")
    table.add_column("probed route")
    for step, ci in enumerate(result.order, start=1):
        c = result.chains[ci]
        placed = " → ".join(f"{v}@{result.placement[v]}" for v in c.vertices)
        table.add_row(str(step), placed, "-".join(result.routes.get(ci, [])))
    console.print(table)
    nodes = Table(title="nodes")
    nodes.add_column("node")
    nodes.add_column("cpu", justify="right")
    nodes.add_column("load (ms/event)", justify="right")
    nodes.add_column("vertices")
    for nid, spec in net.nodes.items():
        here = [v for v, n in result.placement.items() if n == nid]
        load = sum(app.vertices[v].cost for v in here) / spec.cpu
        nodes.add_row(nid, f"{spec.cpu:g}", f"{load:.2f}", ", ".join(here) or "-")
    console.print(nodes)


@main.command()
def demo() -> None:
    """Form the chains of the bundled convoy app and place them on a 4-robot line."""
    _demo()


@_user_errors
def _demo() -> None:
    console = _console()
    app = load_app(EXAMPLES / "convoy.yaml")
    scenario = load_scenario(EXAMPLES / "convoy-line.yaml")
    console.print(
        f"[bold]mso demo[/bold]: the convoy app of the MSO paper (Fig. 6), "
        f"{len(app.vertices)} vertices and {len(app.edges)} edges, on {scenario.name} "
        f"({' - '.join(scenario.network.nodes)})\n"
    )
    result = plan(app, scenario.network)
    render_plan(console, app, scenario, result)
