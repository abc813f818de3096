"""Commands on an app file, before anything runs: check it, measure it, cut it into chains,
place it (Algorithm 1 or a baseline), compare placements."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from mso.cli.common import console, no_import, user_errors
from mso.cliargs import POSITIVE

# algorithm1: the app's planner: key (default bytes); paper/bytes: Algorithm 1 with that split
PLANNERS = ["algorithm1", "paper", "bytes", "source", "random", "greedy", "optimal"]


@click.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@no_import
@click.option("--json", "as_json", is_flag=True, help='Print {"app", "vertices", "edges"}.')
@user_errors
def validate(app_file: Path, no_import: bool, as_json: bool) -> None:
    """Check an app file and report the first problem."""
    from mso.model.appfile import load_app

    app = load_app(app_file, resolve_code=not no_import)
    if not no_import:  # as deploy would: a policy that does not load fails here, not there
        from mso.management import load_policy

        line = app.located.line(("policy",)) if app.located is not None else None
        load_policy(
            app.policy, where=f"{app_file}:{line}: policy" if line else f"{app_file}: policy"
        )
    from mso.cli.render import constraint_json, constraint_text

    needs = app.needs()
    if as_json:
        doc: dict[str, Any] = {
            "app": app.name,
            "vertices": len(app.vertices),
            "edges": len(app.edges),
        }
        if needs:
            doc["constraints"] = {n.vertex: constraint_json(n) for n in needs}
        click.echo(json.dumps(doc))
        return
    click.echo(f"{app_file}: ok ({len(app.vertices)} vertices, {len(app.edges)} edges)")
    for n in needs:
        click.echo(f"  {n.vertex}: placed by capability, {constraint_text(n)}")


@click.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--seconds", type=POSITIVE, default=30.0, show_default=True, help="Simulated seconds to run."
)
@click.option(
    "--speed",
    type=POSITIVE,
    default=1.0,
    show_default=True,
    help="This host's speed relative to a node of cpu: 1.0 (costs are scaled by it).",
)
@click.option("--write", is_flag=True, help="Write the costs and edge sizes into APP_FILE.")
@click.option("--json", "as_json", is_flag=True)
@user_errors
def profile(app_file: Path, seconds: float, speed: float, write: bool, as_json: bool) -> None:
    """Measure each vertex's cost (CPU ms per event) and each edge's size on generated inputs."""
    from rich.table import Table

    from mso.model.appfile import load_app
    from mso.runtime.profile import profile as run_profile
    from mso.runtime.profile import write_back

    app = load_app(app_file)
    prof = run_profile(app, seconds, speed)
    costs, sizes = prof.costs(), prof.sizes()
    if as_json:
        click.echo(
            json.dumps(
                {
                    "costs": costs,
                    "sizes": {f"{a}->{b}": n for (a, b), n in sizes.items()},
                    "errors": {v: p.errors for v, p in prof.vertices.items() if p.errors},
                    "scratch": prof.scratch,
                }
            )
        )
    else:
        table = Table(title=f"{app.name}: {seconds:g} simulated s, speed {speed:g}")
        for col in ("vertex", "calls", "cost (ms/event)", "declared", "errors"):
            table.add_column(col, justify="left" if col == "vertex" else "right")
        for v, p in prof.vertices.items():
            c = costs.get(v)
            table.add_row(
                v,
                str(p.calls),
                "-" if c is None else f"{c:.3g}",
                f"{app.vertices[v].cost:g}",
                str(p.errors) + (f" ({p.last_error})" if p.errors else ""),
            )
        console().print(table)
        for what in prof.scratch:
            click.echo(f"kept off the real file: {what}")
    if write:
        for why in write_back(app_file, costs, sizes):
            click.echo(f"not written: {why}", err=True)
        if not as_json:
            click.echo(f"wrote costs and edge sizes into {app_file}")


@click.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help='Print {"chains": [[head, ..., tail], ...]}.')
@no_import
@user_errors
def chains(app_file: Path, as_json: bool, no_import: bool) -> None:
    """Partition an app into chains (paper §3.2)."""
    from rich.table import Table

    from mso.model.appfile import load_app
    from mso.model.chains import form_chains

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
    console().print(table)


@click.command(name="plan")
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--scenario",
    "scenario_file",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="The network: nodes, capacities, links.",
)
@click.option("--origin", help="Node that hosts unpinned sources (default: the first node).")
@click.option(
    "--planner",
    type=click.Choice(PLANNERS),
    default="algorithm1",
    show_default=True,
    help="Algorithm 1 (with the app's planner:, or paper's or bytes' split) or a baseline.",
)
@click.option(
    "--objective",
    type=click.Choice(["energy", "max_load", "hops"]),
    default="energy",
    show_default=True,
    help="What the optimal planner minimises.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random planner.")
@click.option("--json", "as_json", is_flag=True, help="Print the plan as JSON.")
@no_import
@user_errors
def plan_cmd(
    app_file: Path,
    scenario_file: Path,
    origin: str | None,
    planner: str,
    objective: str,
    seed: int,
    as_json: bool,
    no_import: bool,
) -> None:
    """Place an app on a network with Algorithm 1 (paper §3.3) or a baseline."""
    from mso.model.appfile import load_app
    from mso.planning.baselines import BASELINES
    from mso.planning.objectives import evaluate
    from mso.planning.placement import Plan, plan, with_pins
    from mso.scenario import load_scenario

    app = load_app(app_file, resolve_code=not no_import)
    scenario = load_scenario(scenario_file)
    split = planner if planner in ("paper", "bytes") else None
    result = plan(app, scenario.network, origin=origin, planner=split)
    if planner not in ("algorithm1", "paper", "bytes"):
        pinned = with_pins(app, {v: ns[0] for v, ns in result.capable.items()})
        placement = BASELINES[planner](pinned, scenario.network, seed=seed, objective=objective)
        result = Plan(placement, result.chains, result.order, {}, capable=result.capable)
    if as_json:
        doc = result.to_json()
        doc["planner"] = planner
        if planner in ("algorithm1", "paper", "bytes"):
            doc["split"] = result.planner
        doc["objectives"] = evaluate(app, scenario.network, result.placement)
        click.echo(json.dumps(doc))
        return
    from mso.cli.render import render_plan

    if planner in ("algorithm1", "paper", "bytes"):
        console().print(f"planner: {result.planner}")
    render_plan(console(), app, scenario, result)


@click.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--scenario",
    "scenario_file",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="The network.",
)
@click.option("--json", "as_json", is_flag=True)
@no_import
@user_errors
def compare(app_file: Path, scenario_file: Path, as_json: bool, no_import: bool) -> None:
    """Algorithm 1 beside the baselines on energy per event, max node load and hops, and
    whether each can run: its busiest CPU and (with link rates) its busiest link."""
    from rich.table import Table

    from mso.errors import PlanningError
    from mso.model.appfile import load_app
    from mso.planning.baselines import BASELINES
    from mso.planning.objectives import busiest_cpu, busiest_link, evaluate
    from mso.planning.placement import plan, with_pins
    from mso.scenario import load_scenario

    app = load_app(app_file, resolve_code=not no_import)
    net = load_scenario(scenario_file).network
    rated = any(lk.bandwidth_mbps for lk in net.links.values())

    def scored(placement: dict[str, str]) -> dict[str, float]:
        row = evaluate(app, net, placement)
        row["cpu_share"] = busiest_cpu(app, net, placement)
        row["link_share"] = busiest_link(app, net, placement)
        return row

    first = plan(app, net)
    pinned = with_pins(app, {v: ns[0] for v, ns in first.capable.items()})
    rows: dict[str, Any] = {"algorithm1": scored(first.placement)}
    for split in ("paper", "bytes"):
        rows[f"algorithm1:{split}"] = scored(plan(app, net, planner=split).placement)
    for name in ("source", "random", "greedy"):
        rows[name] = scored(BASELINES[name](pinned, net, seed=0, objective="energy"))
    for objective in ("energy", "max_load", "hops"):
        try:
            placement = BASELINES["optimal"](pinned, net, seed=0, objective=objective)
            rows[f"optimal:{objective}"] = scored(placement)
        except PlanningError as exc:
            rows[f"optimal:{objective}"] = {"error": str(exc)}
    if as_json:
        click.echo(json.dumps(rows))
        return
    table = Table(
        title=f"{app.name}: Algorithm 1 (planner: {first.planner}) beside the baselines; "
        "optimal within each node's CPU (energy, hops: and each link's rate); a share over 100% "
        "cannot run at the app's rates"
    )
    cols = ["planner", "energy mJ/event", "max load ms/event", "hops"]
    cols += ["busiest CPU", *(["busiest link"] if rated else [])]
    for col in cols:
        left = col == "planner"
        table.add_column(col, justify="left" if left else "right", no_wrap=left)
    for name, r in rows.items():
        if "error" in r:
            table.add_row(name, r["error"], *[""] * (len(cols) - 2))
            continue
        shares = [r["cpu_share"], *([r["link_share"]] if rated else [])]
        table.add_row(
            name,
            f"{r['energy'] * 1e3:.3f}",
            f"{r['max_load']:.2f}",
            f"{r['hops']:g}",
            *(f"{x:.0%}" + (" over" if x > 1 + 1e-9 else "") for x in shares),
        )
    console().print(table)
