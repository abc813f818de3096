"""``mso scenario generate``: scenarios at scale from one seed (topology and mobility), written
as ordinary scenario files."""

from __future__ import annotations

import json
from pathlib import Path

import click

from mso.cli.common import user_errors
from mso.cliargs import NON_NEGATIVE, POSITIVE, Number


@click.group()
def scenario() -> None:
    """Scenario files: generate them at scale."""


@scenario.command()
@click.argument("topology", type=click.Choice(["grid", "geometric", "platoon"]))
@click.option("--nodes", "-n", type=int, required=True, help="How many nodes (2 to 10,000).")
@click.option("--seed", type=int, default=0, show_default=True, help="One seed for it all.")
@click.option(
    "--degree", type=Number(1.0, strict=False), default=6.0, show_default=True,
    help="Mean links per node (a grid: 4 square, 6 triangular, 8 with diagonals).",
)  # fmt: skip
@click.option(
    "--spacing", type=POSITIVE, default=100.0, show_default=True,
    help="Metres between grid neighbours (the same density for geometric; platoons: a third).",
)  # fmt: skip
@click.option(
    "--platoon", type=int, default=10, show_default=True,
    help="Vehicles per platoon (platoon topology), nodes per group (group mobility).",
)  # fmt: skip
@click.option(
    "--mobility", type=click.Choice(["none", "random_waypoint", "gauss_markov", "group"]),
    default="none", show_default=True,
)  # fmt: skip
@click.option(
    "--speed", type=(NON_NEGATIVE, NON_NEGATIVE), default=(1.0, 5.0), show_default=True,
    help="MIN MAX speed, m/s.",
)  # fmt: skip
@click.option("--pause", type=NON_NEGATIVE, default=0.0, show_default=True, help="Pause, s.")
@click.option(
    "--step", type=POSITIVE, default=0.5, show_default=True,
    help="Seconds between two recomputations of the links from positions.",
)  # fmt: skip
@click.option("--name", help="The scenario's name (default: TOPOLOGY-N-sSEED).")
@click.option("--json", "as_json", is_flag=True, help="With -o: say what was written as JSON.")
@click.option(
    "--output", "-o", type=click.Path(dir_okay=False, path_type=Path),
    help="Write the file here (default: print it).",
)  # fmt: skip
@user_errors
def generate(
    topology: str,
    nodes: int,
    seed: int,
    degree: float,
    spacing: float,
    platoon: int,
    mobility: str,
    speed: tuple[float, float],
    pause: float,
    step: float,
    name: str | None,
    as_json: bool,
    output: Path | None,
) -> None:
    """Generate a scenario: TOPOLOGY grid, geometric (random geometric) or platoon (a convoy
    column of platoons), with an optional mobility model; the same arguments give the same file.

    \b
      mso scenario generate geometric -n 1000 --seed 7 -o g1000.yaml
      mso scenario generate grid -n 200 --mobility random_waypoint --speed 1 5 -o rwp.yaml
    """
    from mso.errors import MsoError
    from mso.scenario.format import loads_scenario
    from mso.scenario.generate import Spec, dumps
    from mso.scenario.generate import generate as make

    spec = Spec(
        topology, nodes, seed=seed, degree=degree, spacing=spacing, platoon=platoon,
        mobility=mobility, speed=speed, pause_s=pause, step_s=step, name=name,
    )  # fmt: skip
    text = dumps(make(spec), spec)
    sc = loads_scenario(text, file=str(output or "<generated>"))  # it loads as written
    if output is None:
        click.echo(text, nl=False)
        return
    try:
        output.write_text(text)
    except OSError as exc:
        raise MsoError(f"--output: cannot write {output}: {exc.strerror}") from None
    links = len(sc.network.links)
    if as_json:
        click.echo(json.dumps({
            "file": str(output), "name": sc.name, "nodes": nodes, "links": links,
            "mean_degree": round(2 * links / nodes, 2), "radio_range": sc.radio_range,
            "mobility": mobility,
        }))  # fmt: skip
        return
    click.echo(f"wrote {output}: {nodes} nodes, {links} links, mean degree {2 * links / nodes:.2f}")
