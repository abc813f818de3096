"""The ``mso`` command line. Thin: it parses, calls the library, and renders.

Every user error (bad app or scenario file, impossible request) prints one line on stderr and
exits with code 2; a traceback means a bug in mso.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from mso.cliargs import NON_NEGATIVE, POSITIVE, OneLineGroup, power_model
from mso.errors import MsoError

if TYPE_CHECKING:  # imported where used: `mso status` needs neither numpy nor the planner
    from rich.console import Console

    from mso.model.app import App
    from mso.planning.placement import Plan
    from mso.scenario import Scenario

F = TypeVar("F", bound=Callable[..., Any])

EXAMPLES = Path(__file__).parent / "examples"
DASHBOARD_LISTEN = "127.0.0.1:8765"  # mso.dashboard.server.DEFAULT_LISTEN, not imported early
PLANNERS = ["algorithm1", "source", "random", "greedy", "optimal"]


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
    from rich.console import Console

    return Console(highlight=False)


def _progress(what: str) -> contextlib.AbstractContextManager[Any]:
    """A spinner on stderr while long work runs (a terminal only: pipes and --json stay clean)."""
    if not sys.stderr.isatty():
        return contextlib.nullcontext()
    from rich.console import Console

    return Console(stderr=True).status(what)


@click.group(cls=OneLineGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mso")
def main() -> None:
    """mso: run a dataflow app across a mobile ad hoc network and keep re-placing it.

    \b
    An app is a graph of vertices (sources, operators, sinks) joined by edges; mso cuts it into
    chains (mso chains) and places each chain along the route to its sink (mso plan). Every
    device runs the same daemon (mso node); together they form an overlay, reached through any
    of its nodes (--via). A running app is moved without losing an event: one vertex
    (mso relocate), a chain or the whole app (mso remap), by hand or by the nodes' management
    rules as batteries drain, links change and nodes fail.

    \b
    Try it on one machine:  mso demo --dashboard
      mso emulate SCENARIO --app APP --dashboard   # one process per node, live web view
      mso status --watch                           # from another terminal
    Shell completion:  eval "$(mso completion bash)"   (or zsh, fish)
    """


no_import = click.option(
    "--no-import",
    is_flag=True,
    help="Do not import vertex code and formats (plan on a machine without the app's modules).",
)


@main.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@no_import
@click.option("--json", "as_json", is_flag=True, help='Print {"app", "vertices", "edges"}.')
@_user_errors
def validate(app_file: Path, no_import: bool, as_json: bool) -> None:
    """Check an app file and report the first problem."""
    from mso.model.appfile import load_app

    app = load_app(app_file, resolve_code=not no_import)
    if as_json:
        doc = {"app": app.name, "vertices": len(app.vertices), "edges": len(app.edges)}
        click.echo(json.dumps(doc))
        return
    click.echo(f"{app_file}: ok ({len(app.vertices)} vertices, {len(app.edges)} edges)")


@main.command()
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
@_user_errors
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
        _console().print(table)
    if write:
        for why in write_back(app_file, costs, sizes):
            click.echo(f"not written: {why}", err=True)
        if not as_json:
            click.echo(f"wrote costs and edge sizes into {app_file}")


@main.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help='Print {"chains": [[head, ..., tail], ...]}.')
@no_import
@_user_errors
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
@click.option(
    "--planner",
    type=click.Choice(PLANNERS),
    default="algorithm1",
    show_default=True,
    help="Algorithm 1 or a baseline to compare it with.",
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
@_user_errors
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
    from mso.planning.placement import Plan, plan
    from mso.scenario import load_scenario

    app = load_app(app_file, resolve_code=not no_import)
    scenario = load_scenario(scenario_file)
    result = plan(app, scenario.network, origin=origin)
    if planner != "algorithm1":
        placement = BASELINES[planner](app, scenario.network, seed=seed, objective=objective)
        result = Plan(placement, result.chains, result.order, {})
    if as_json:
        doc = result.to_json()
        doc["planner"] = planner
        doc["objectives"] = evaluate(app, scenario.network, result.placement)
        click.echo(json.dumps(doc))
        return
    render_plan(_console(), app, scenario, result)


@main.command()
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
@_user_errors
def compare(app_file: Path, scenario_file: Path, as_json: bool, no_import: bool) -> None:
    """Algorithm 1 beside the baselines on energy per event, max node load and hops."""
    from rich.table import Table

    from mso.errors import PlanningError
    from mso.model.appfile import load_app
    from mso.planning.baselines import BASELINES
    from mso.planning.objectives import evaluate
    from mso.planning.placement import plan
    from mso.scenario import load_scenario

    app = load_app(app_file, resolve_code=not no_import)
    net = load_scenario(scenario_file).network
    rows: dict[str, Any] = {"algorithm1": evaluate(app, net, plan(app, net).placement)}
    for name in ("source", "random", "greedy"):
        rows[name] = evaluate(app, net, BASELINES[name](app, net, seed=0, objective="energy"))
    for objective in ("energy", "max_load", "hops"):
        try:
            placement = BASELINES["optimal"](app, net, seed=0, objective=objective)
            rows[f"optimal:{objective}"] = evaluate(app, net, placement)
        except PlanningError as exc:
            rows[f"optimal:{objective}"] = {"error": str(exc)}
    if as_json:
        click.echo(json.dumps(rows))
        return
    table = Table(title=f"{app.name}: Algorithm 1 beside the baselines")
    for col in ("planner", "energy per event (mJ)", "max node load (ms)", "end-to-end hops"):
        table.add_column(col, justify="left" if col == "planner" else "right")
    for name, r in rows.items():
        if "error" in r:
            table.add_row(name, r["error"], "", "")
        else:
            table.add_row(
                name, f"{r['energy'] * 1e3:.3f}", f"{r['max_load']:.2f}", f"{r['hops']:g}"
            )
    _console().print(table)


def render_plan(console: Console, app: App, scenario: Scenario, result: Plan) -> None:
    """Chains with their placement, then the load each node carries."""
    from rich.table import Table

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


@main.command(short_help="Run the bundled convoy app on an emulated 4-robot line.")
@click.option(
    "--duration",
    type=POSITIVE,
    default=56.0,
    show_default=True,
    help="Seconds to run (56: the leader turns the first corner, where the second survivor lies).",
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


@_user_errors
def _demo(duration: float, plan_only: bool, dashboard: bool = False) -> None:
    from mso.model.appfile import load_app
    from mso.planning.placement import plan
    from mso.scenario import load_scenario

    console = _console()
    app_file, scenario_file = EXAMPLES / "convoy.yaml", EXAMPLES / "convoy-demo.yaml"
    app = load_app(app_file)
    scenario = load_scenario(scenario_file)
    console.print(
        f"[bold]mso demo[/bold]: the convoy app of the MSO paper (Fig. 6), "
        f"{len(app.vertices)} vertices and {len(app.edges)} edges, on {scenario.name} "
        f"({' - '.join(scenario.network.nodes)})\n"
    )
    result = plan(app, scenario.network)
    render_plan(console, app, scenario, result)
    if not plan_only:
        from mso.examples.convoy.demo import run_demo

        console.print(f"\n[bold]running it[/bold] on 4 emulated robots for {duration:g} s")
        run_demo(console, duration, dashboard)


# -- the running system ----------------------------------------------------------------------
sign_option = click.option(
    "--sign",
    envvar="MSO_SIGN",
    metavar="KEYFILE",
    help="Sign the command with this operator key (made by `mso keygen`; default: $MSO_SIGN); "
    "needed by nodes started with --operator-key.",
)
operator_key_option = click.option(
    "--operator-key",
    "operator_keys",
    multiple=True,
    metavar="PUB",
    help="An operator's public key (text or .pub file, repeat): commands that change an overlay "
    "must be signed with one. Without any, the overlay key is all there is.",
)


@main.command()
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help='Print {"private", "public", "key"}.')
@_user_errors
def keygen(out: Path, as_json: bool) -> None:
    """Make an operator key: OUT (private, mode 0600) and OUT.pub (give it to every node)."""
    import os

    from mso.protocol.authority import Signer

    signer = Signer()
    pub = out.with_name(out.name + ".pub")
    try:
        fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(signer.private_text() + "\n")
        pub.write_text(signer.public_text() + "\n")
    except OSError as exc:
        raise MsoError(f"{exc.filename}: {exc.strerror}") from None
    if as_json:
        doc = {"private": str(out), "public": str(pub), "key": signer.public_text()}
        click.echo(json.dumps(doc))
        return
    click.echo(f"wrote {out} (keep it secret) and {pub}: mso node --operator-key {pub}")
    click.echo(signer.public_text())


allow_code_option = click.option(
    "--allow-code",
    "allow_code",
    multiple=True,
    metavar="MODULE",
    help="A module (and its submodules) whose vertex, format and policy code this node may "
    "import (repeat; default: $MSO_ALLOW_CODE, comma-separated; mso's bundled examples always).",
)


DEV_KEY_WARNING = (
    "warning: using the built-in development key: anyone who has mso can join this overlay; "
    "give --key or set $MSO_KEY"
)


def check_key(key: str | None, listen: str, insecure: bool) -> bool:
    """Protected mode: an empty key is an error; the built-in development key is announced,
    and refused on an address beyond loopback unless ``--insecure``."""
    import ipaddress

    from mso.client import DEFAULT_KEY, parse_address

    if key == "":
        raise MsoError("--key: an empty overlay key is refused (give one, or leave --key out)")
    if key is not None and key != DEFAULT_KEY:
        return False
    host, _ = parse_address(listen)
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not insecure:
        raise MsoError(
            f"--listen {listen}: refusing to listen beyond loopback with the built-in "
            "development key; give --key or $MSO_KEY (or --insecure for a lab network)"
        )
    return True


def set_code_allowlist(modules: tuple[str, ...]) -> tuple[str, ...]:
    """Restrict this process's imports to ``modules`` (else $MSO_ALLOW_CODE) plus the bundled
    examples, before anything of an app is loaded."""
    import os

    from mso.model.imports import DEFAULT_ALLOWED, ImportPathError, allow_code

    if not modules:
        modules = tuple(m for m in os.environ.get("MSO_ALLOW_CODE", "").split(",") if m)
    allowed = (*DEFAULT_ALLOWED, *modules)
    try:
        allow_code(allowed)
    except ImportPathError as exc:
        raise MsoError(f"--allow-code: {exc}") from None
    return allowed


key_option = click.option(
    "--key", envvar="MSO_KEY", help="Overlay pre-shared key (default: $MSO_KEY, else a dev key)."
)


overlay_option = click.option(
    "--overlay",
    envvar="MSO_OVERLAY",
    help="Which running emulator (`mso overlays`) when several run (default: $MSO_OVERLAY).",
)


def _resolve_via(via: str | None, overlay: str | None = None) -> str:
    """A node id of a running emulator, or HOST:PORT."""
    from mso.emu.overlays import emulator_address, find_overlay

    if via is None:
        _, state = find_overlay(overlay)
        return str(next(iter(state["nodes"].values())))
    if ":" in via:
        return via
    addr = emulator_address(via, overlay)
    if addr is None:
        raise MsoError(f"unknown node {via!r}: no running emulator knows it; use HOST:PORT")
    return addr


NODE_CONFIG_KEYS = {
    "id",
    "listen",
    "cpu",
    "key",
    "peers",
    "battery_wh",
    "power",
    "policy",
    "manage",
    "allow_code",
    "operator_keys",
    "key_file",
    "encrypt",
    "routes",
    "energy",
}


def _node_config(path: Path) -> dict[str, Any]:
    """A node configuration file: id, listen, cpu, key, peers (node id -> HOST:PORT)."""
    from mso.errors import SpecError
    from mso.model.yamlfile import load_yaml_file

    doc = load_yaml_file(path)
    data = doc.data
    if not isinstance(data, dict):
        raise SpecError("expected a mapping with 'id' and 'listen'", file=doc.file, line=1)
    for k, v in data.items():
        line = doc.line((k,))
        if k not in NODE_CONFIG_KEYS:
            allowed = ", ".join(sorted(NODE_CONFIG_KEYS))
            raise SpecError(
                f"unknown attribute {k!r} (expected one of: {allowed})",
                file=doc.file,
                line=line,
                field=str(k),
            )
        if k == "peers" and not (
            isinstance(v, dict) and all(isinstance(a, str) for a in v.values())
        ):
            raise SpecError(
                "expected a mapping of node id to HOST:PORT", file=doc.file, line=line, field=k
            )
        if k == "power" and not (
            isinstance(v, dict)
            and set(v) <= {"idle_w", "cpu_w", "tx_uj_per_byte", "rx_uj_per_byte"}
            and all(
                isinstance(x, int | float) and not isinstance(x, bool) and 0 <= x < 1e12
                for x in v.values()
            )
        ):
            raise SpecError(
                "expected {idle_w, cpu_w, tx_uj_per_byte, rx_uj_per_byte} as numbers >= 0",
                file=doc.file,
                line=line,
                field=k,
            )
        if k in ("cpu", "battery_wh") and not (
            isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < 1e12
        ):
            raise SpecError(f"expected a number > 0, got {v!r}", file=doc.file, line=line, field=k)
        if k == "manage" and not isinstance(v, bool):
            raise SpecError(f"expected true or false, got {v!r}", file=doc.file, line=line, field=k)
        if k in ("allow_code", "operator_keys") and not (
            isinstance(v, list) and all(isinstance(x, str) and x for x in v)
        ):
            raise SpecError("expected a list of strings", file=doc.file, line=line, field=k)
        if k == "encrypt" and not isinstance(v, bool):
            raise SpecError(f"expected true or false, got {v!r}", file=doc.file, line=line, field=k)
        if k in ("id", "listen", "key", "key_file") and not isinstance(v, str):
            raise SpecError(f"expected a string, got {v!r}", file=doc.file, line=line, field=k)
    return data


@main.command()
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="YAML with id, listen, cpu, key, peers; flags given override it.",
)
@click.option("--id", "node_id", help="This node's id, e.g. N1.")
@click.option("--listen", help="HOST:PORT to serve (default 127.0.0.1:7000).")
@click.option("--cpu", type=POSITIVE, help="Relative CPU speed (default 1.0).")
@click.option("--battery-wh", type=POSITIVE, help="Battery capacity in Wh (default: wall power).")
@click.option(
    "--power",
    help="Power model IDLE_W,CPU_W,TX_UJ_PER_BYTE,RX_UJ_PER_BYTE[,modelled|measured] (the last:"
    " charge CPU energy for the vertices' declared costs or their measured CPU time).",
)
@click.option(
    "--peer",
    "peers",
    multiple=True,
    help="A static neighbour NODE=HOST:PORT (repeat); without it the emulator sets neighbours.",
)
@click.option(
    "--energy",
    type=click.Choice(["auto", "model", "interfaces"]),
    default=None,
    help="auto (default): battery, CPU time and interface bytes from the OS where it reports "
    "them, the power model for the rest; model: the power model and CPU time only (the "
    "user-space emulator passes this); interfaces: also the interface bytes (netns testbed).",
)
@click.option(
    "--routes",
    "routes_from",
    type=click.Choice(["auto", "kernel", "emulator"]),
    default=None,
    help="Where routes come from: kernel (read the routing daemon's kernel routes over "
    "netlink, learn node ids from announcements; listen on a routable address), emulator, or "
    "auto (default: the --peer list if given, else the emulator).",
)
@click.option(
    "--policy",
    help="Management policy for apps that name none: lifetime (default), energy, balance, "
    "delay, or pkg.module:Attr.",
)
@click.option(
    "--manage/--no-manage",
    default=None,
    help="Run the management rules (default on); off keeps every placement as deployed.",
)
@click.option(
    "--heartbeat", "heartbeat_s", type=POSITIVE, default=None,
    help="Seconds between heartbeats to each neighbour (default 0.1).",
)  # fmt: skip
@click.option(
    "--dead-after", "dead_after_s", type=POSITIVE, default=None,
    help="Seconds of silence after which a neighbour is declared failed (default 0.5).",
)  # fmt: skip
@click.option(
    "--metrics",
    help="HOST:PORT to serve Prometheus metrics on at /metrics (default: off).",
)
@allow_code_option
@operator_key_option
@click.option(
    "--key-file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Overlay keys, one a line: the first seals, the others are still accepted. Re-read on "
    "SIGHUP, to rotate the key without stopping anything.",
)
@click.option(
    "--encrypt/--no-encrypt",
    envvar="MSO_ENCRYPT",
    default=None,
    help="Encrypt frames with ChaCha20-Poly1305 (default: $MSO_ENCRYPT; every member and client "
    "must agree).",
)
@click.option(
    "--insecure",
    is_flag=True,
    help="Allow listening beyond loopback with the built-in development key (never on robots).",
)
@key_option
@click.option("-v", "--verbose", is_flag=True)
@_user_errors
def node(
    config_file: Path | None,
    node_id: str | None,
    listen: str | None,
    cpu: float | None,
    battery_wh: float | None,
    power: str | None,
    peers: tuple[str, ...],
    energy: str | None,
    routes_from: str | None,
    policy: str | None,
    manage: bool | None,
    heartbeat_s: float | None,
    dead_after_s: float | None,
    metrics: str | None,
    allow_code: tuple[str, ...],
    operator_keys: tuple[str, ...],
    key_file: Path | None,
    encrypt: bool | None,
    insecure: bool,
    key: str | None,
    verbose: bool,
) -> None:
    """Run the identical mso daemon of one device."""
    from mso.model.network import PowerModel
    from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, check_timing

    heartbeat_s = HEARTBEAT_S if heartbeat_s is None else heartbeat_s
    dead_after_s = DEAD_AFTER_S if dead_after_s is None else dead_after_s
    if why := check_timing(heartbeat_s, dead_after_s):
        raise MsoError(why)

    cfg = _node_config(config_file) if config_file is not None else {}
    node_id = node_id or cfg.get("id")
    if not node_id:
        raise MsoError("a node needs an id: --id N1, or 'id:' in its --config file")
    all_peers = tuple(f"{n}={a}" for n, a in cfg.get("peers", {}).items()) + peers
    model = PowerModel(**cfg.get("power", {}))
    if power is not None:
        head, _, last = power.rpartition(",")
        how = last if last in ("modelled", "measured") else "modelled"
        model = PowerModel(*power_model(head if last == how else power), how)
    set_code_allowlist(allow_code or tuple(cfg.get("allow_code", ())))
    key = key if key is not None else cfg.get("key")
    key_file = key_file or (Path(cfg["key_file"]) if "key_file" in cfg else None)
    if key_file is not None:
        key = read_keys(key_file)[0]  # checked now; re-read on SIGHUP
    encrypt = bool(cfg.get("encrypt", False)) if encrypt is None else encrypt
    authority = node_authority(operator_keys or tuple(cfg.get("operator_keys", ())))
    dev_key = check_key(key, listen or cfg.get("listen", "127.0.0.1:7000"), insecure)
    battery = battery_wh if battery_wh is not None else cfg.get("battery_wh")
    if battery is not None and battery <= 0:
        raise MsoError(f"--battery-wh: expected a number > 0, got {battery:g}")
    _node(
        node_id,
        listen or cfg.get("listen", "127.0.0.1:7000"),
        float(cpu if cpu is not None else cfg.get("cpu", 1.0)),
        all_peers,
        key,
        verbose,
        model,
        battery,
        policy if policy is not None else cfg.get("policy"),
        manage if manage is not None else cfg.get("manage", True),
        heartbeat_s,
        dead_after_s,
        dev_key,
        authority,
        key_file,
        encrypt,
        metrics,
        routes_from or cfg.get("routes", "auto"),
        energy or cfg.get("energy", "auto"),
    )


def read_keys(path: Path) -> list[str]:
    """A key file: overlay keys one a line (the first seals), '#' comments."""
    from mso.errors import SpecError
    from mso.model.yamlfile import read_text_file

    keys = [
        line.strip()
        for line in read_text_file(path).splitlines()
        if line.strip() and not line.strip().startswith("#")
    ]
    if not keys:
        raise SpecError("no overlay key in the key file", file=str(path))
    return keys


def node_authority(keys: tuple[str, ...]) -> Any:
    """The operator keys (and the emulator's, from $MSO_EMULATOR_KEY) this node obeys."""
    from mso.protocol.authority import Authority, KeyError_

    try:
        return Authority.from_env(list(keys))
    except KeyError_ as exc:
        raise MsoError(f"--operator-key: {exc}") from None


def _node(
    node_id: str,
    listen: str,
    cpu: float,
    peers: tuple[str, ...],
    key: str | None,
    verbose: bool,
    power: Any = None,
    battery_wh: float | None = None,
    policy: Any = None,
    manage: bool = True,
    heartbeat_s: float | None = None,
    dead_after_s: float | None = None,
    dev_key: bool = False,
    authority: Any = None,
    key_file: Path | None = None,
    encrypt: bool = False,
    metrics: str | None = None,
    routes_from: str = "auto",
    energy: str = "auto",
) -> None:
    import asyncio
    import logging

    from mso.client import overlay_key, parse_address
    from mso.net.base import Neighbour
    from mso.net.routes_static import StaticRoutes
    from mso.node.core import NodeCore
    from mso.node.driver import PARENT_ENV, NodeDriver, stop_with_parent
    from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format=f"%(asctime)s {node_id} %(levelname)s %(message)s",
    )
    host, port = parse_address(listen)
    metrics_at = None
    if metrics is not None:
        metrics_at = parse_address(metrics, default_port=-1)
        if not 0 <= metrics_at[1] < 65536:
            raise MsoError(f"--metrics: expected HOST:PORT, got {metrics!r}")
    if cpu <= 0:
        raise MsoError(f"--cpu: expected a number > 0, got {cpu:g}")
    static: dict[str, Neighbour] = {}
    for p in peers:
        name, _, addr = p.partition("=")
        if not name or not addr:
            raise MsoError(f"--peer: expected NODE=HOST:PORT, got {p!r}")
        phost, pport = parse_address(addr)
        static[name] = Neighbour(phost, pport)

    core = NodeCore(  # checks the policy before anything listens
        node_id,
        capacity=cpu,
        power=power,
        battery_wh=battery_wh,
        policy=policy,
        manage=manage,
        heartbeat_s=HEARTBEAT_S if heartbeat_s is None else heartbeat_s,
        dead_after_s=DEAD_AFTER_S if dead_after_s is None else dead_after_s,
        # a restarted daemon is a new incarnation: the others restore what it hosted before
        incarnation=time.time_ns() // 1_000_000,
    )

    if energy not in ("auto", "model", "interfaces"):
        raise MsoError(f"energy: expected auto, model or interfaces, got {energy!r}")
    if routes_from not in ("auto", "kernel", "emulator"):
        raise MsoError(f"routes: expected auto, kernel or emulator, got {routes_from!r}")
    if routes_from == "kernel" and static:
        raise MsoError("give either --peer (a fixed set-up) or --routes kernel, not both")
    if routes_from == "kernel" and (port == 0 or host.startswith("127.") or host == "localhost"):
        raise MsoError(
            f"--routes kernel: listen on a routable address and a fixed port "
            f"(e.g. --listen 0.0.0.0:7000), got {listen}"
        )

    async def serve() -> None:
        from mso.net.base import RoutingView
        from mso.net.routes_kernel import KernelRoutes

        keys = [overlay_key(k) for k in read_keys(key_file)] if key_file else [overlay_key(key)]
        psk = keys[0]  # what kernel route announcements are authenticated with
        view: RoutingView | None = None
        kernel: KernelRoutes | None = None
        if routes_from == "kernel":
            view = kernel = KernelRoutes(node_id, port, psk, host=host)
            try:
                await kernel.start()
            except OSError as exc:
                raise MsoError(f"--routes kernel: cannot read routes or bind: {exc}") from None
        elif routes_from == "auto" and static:
            view = StaticRoutes(node_id, static)
        from mso.node.device import DeviceProbe

        device = DeviceProbe(battery=energy == "auto", interfaces=energy != "model")
        driver = NodeDriver(  # no view: the emulator's
            core, host, port, keys, view, device=device, authority=authority, encrypt=encrypt
        )

        def rotate() -> None:  # SIGHUP: take the key file again; open connections keep theirs
            assert key_file is not None
            try:
                driver.transport.set_keys([overlay_key(k) for k in read_keys(key_file)])
                logging.getLogger("mso.node").warning("overlay keys re-read from %s", key_file)
            except MsoError as exc:
                logging.getLogger("mso.node").error("keeping the old keys: %s", exc)

        if key_file is not None:
            import signal

            asyncio.get_running_loop().add_signal_handler(signal.SIGHUP, rotate)
        try:
            await driver.start()
        except OSError as exc:
            raise MsoError(f"cannot listen on {listen}: {exc.strerror}") from None
        exporter = None
        if metrics_at is not None:
            from mso.node.metrics import MetricsServer

            loop = asyncio.get_running_loop()
            exporter = MetricsServer(lambda: core.status(loop.time()), *metrics_at)
            await exporter.start()
        watch = None
        if parent := os.environ.get(PARENT_ENV):  # started by an emulator: end with it
            watch = asyncio.create_task(stop_with_parent(driver, int(parent)))
        try:
            await driver.stopped.wait()
        finally:
            if watch is not None:
                watch.cancel()
            if exporter is not None:
                await exporter.stop()
            if kernel is not None:
                await kernel.close()

    if dev_key:
        click.echo(DEV_KEY_WARNING, err=True)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())


@main.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--via", help="Node to deploy from: a node id of the running emulator or HOST:PORT.")
@sign_option
@overlay_option
@key_option
@click.option("--json", "as_json", is_flag=True)
@_user_errors
def deploy(
    app_file: Path,
    via: str | None,
    overlay: str | None,
    sign: str | None,
    key: str | None,
    as_json: bool,
) -> None:
    """Deploy an app from any node (distributed Algorithm 1)."""
    import asyncio

    from mso.client import load_signer, request
    from mso.model.appfile import load_app
    from mso.model.yamlfile import read_text_file
    from mso.protocol import messages as m

    signer = load_signer(sign)  # a bad key file is reported before anything is sent

    load_app(app_file)  # report file errors here, with their lines, before sending anything
    document = read_text_file(app_file)
    address = _resolve_via(via, overlay)
    reply = asyncio.run(
        request(
            address,
            m.DeployRequest(document, str(app_file)),
            key=key,
            timeout=30,
            signer=signer,
        )
    )
    if not isinstance(reply, m.DeployReply) or not reply.ok:
        raise MsoError(f"deployment failed: {getattr(reply, 'error', reply)}")
    if as_json:
        click.echo(
            json.dumps(
                {"app": reply.app, "placement": reply.placement, "mapping_ms": reply.elapsed_ms}
            )
        )
        return
    click.echo(f"deployed {reply.app} in {reply.elapsed_ms:.1f} ms")
    for v, n in reply.placement.items():
        click.echo(f"  {v:<20} {n}")


async def _only_app(address: str, key: str | None) -> str:
    """The name of the one app running, for commands given no --app."""
    from mso.client import request
    from mso.protocol import messages as m

    st = await request(address, m.StatusRequest(), key=key)
    apps = sorted(next(iter(st.nodes.values()))["apps"]) if isinstance(st, m.StatusReply) else []
    if len(apps) != 1:
        raise MsoError(f"give --app NAME (running: {', '.join(apps) or 'none'})")
    return str(apps[0])


@main.command()
@click.argument("vertex")
@click.option("--app", "app_name", help="The app (default: the only one running).")
@click.option("--upstream", "direction", flag_value="upstream", help="Onto its predecessor's node.")
@click.option(
    "--downstream", "direction", flag_value="downstream", help="To the next node downstream."
)
@click.option("--to", "target", help="Onto this node.")
@click.option("--via", help="Node to ask: a node id of the running emulator or HOST:PORT.")
@sign_option
@overlay_option
@key_option
@click.option("--json", "as_json", is_flag=True)
@_user_errors
def relocate(
    vertex: str,
    app_name: str | None,
    direction: str | None,
    target: str | None,
    via: str | None,
    sign: str | None,
    overlay: str | None,
    key: str | None,
    as_json: bool,
) -> None:
    """Move one vertex of a running app, with its state, losing no event (§3.4.1)."""
    import asyncio

    from mso.client import load_signer, request
    from mso.protocol import messages as m

    signer = load_signer(sign)  # a bad key file is reported before anything is sent

    if bool(direction) == bool(target):
        raise MsoError("give exactly one of --upstream, --downstream or --to NODE")
    address = _resolve_via(via, overlay)
    app = app_name or asyncio.run(_only_app(address, key))
    req = m.RelocateRequest(app, vertex, direction or "", target or "")
    reply = asyncio.run(request(address, req, key=key, signer=signer))
    if not isinstance(reply, m.RelocateReply) or not reply.ok:
        raise MsoError(f"relocation refused: {getattr(reply, 'error', reply)}")
    if as_json:
        click.echo(
            json.dumps({"vertex": vertex, "node": reply.node, "elapsed_ms": reply.elapsed_ms})
        )
        return
    click.echo(f"{vertex} now runs on {reply.node} (relocated in {reply.elapsed_ms:.2f} ms)")


@main.command()
@click.argument("chain", nargs=-1)
@click.option("--app", "app_name", help="The app (default: the only one running).")
@click.option("--chains", help="Several chains, comma-separated (global remap, §3.4.3).")
@click.option("--all", "everything", is_flag=True, help="Every chain of the app.")
@click.option("--via", help="Node to ask: a node id of the running emulator or HOST:PORT.")
@sign_option
@overlay_option
@key_option
@click.option("--json", "as_json", is_flag=True)
@_user_errors
def remap(
    chain: tuple[str, ...],
    app_name: str | None,
    chains: str | None,
    everything: bool,
    via: str | None,
    sign: str | None,
    overlay: str | None,
    key: str | None,
    as_json: bool,
) -> None:
    """Re-place one chain (§3.4.2), several or all (§3.4.3) along freshly probed routes.

    `mso remap chain CHAIN`, `mso remap --chains C1,C2`, `mso remap --all`; a chain is named by
    its index (`mso chains`) or as head-...-tail."""
    import asyncio

    from mso.client import load_signer, request
    from mso.protocol import messages as m

    signer = load_signer(sign)  # a bad key file is reported before anything is sent

    words = list(chain[1:] if chain[:1] == ("chain",) else chain)
    names = [c for c in words + (chains.split(",") if chains else []) if c]
    if bool(names) == everything:
        raise MsoError("name a chain (mso remap chain CHAIN), or give --chains C1,C2, or --all")
    address = _resolve_via(via, overlay)

    async def run() -> Any:
        indices: list[int] = []
        app_name_ = app_name or await _only_app(address, key)
        if names:
            st = await request(address, m.StatusRequest(), key=key)
            assert isinstance(st, m.StatusReply)
            app = next(iter(st.nodes.values()))["apps"].get(app_name_)
            if app is None:
                raise MsoError(f"no running app named {app_name_!r}")
            known = ["-".join(c) for c in app["chains"]]
            for n in names:
                if n.isdigit():
                    indices.append(int(n))
                elif n in known:
                    indices.append(known.index(n))
                else:
                    raise MsoError(f"unknown chain {n!r} (chains: {', '.join(known)})")
        req = m.RemapRequest(app_name_, indices, everything)
        return await request(address, req, key=key, signer=signer)

    reply = asyncio.run(run())
    if not isinstance(reply, m.RemapReply) or not reply.ok:
        raise MsoError(f"remap refused: {getattr(reply, 'error', reply)}")
    if as_json:
        click.echo(json.dumps({"moved": reply.moved, "elapsed_ms": reply.elapsed_ms}))
        return
    click.echo(
        f"remapped in {reply.elapsed_ms:.1f} ms; moved: "
        + (", ".join(f"{v}->{n}" for v, n in reply.moved.items()) or "nothing")
    )


@main.command()
@click.argument("app_name")
@click.option("--via", help="Node to ask: a node id of the running emulator or HOST:PORT.")
@sign_option
@overlay_option
@key_option
@click.option("--json", "as_json", is_flag=True, help='Print {"stopped": NAME}.')
@_user_errors
def undeploy(
    app_name: str,
    via: str | None,
    overlay: str | None,
    sign: str | None,
    key: str | None,
    as_json: bool,
) -> None:
    """Stop an app on every node."""
    import asyncio

    from mso.client import load_signer, request
    from mso.protocol import messages as m

    signer = load_signer(sign)  # a bad key file is reported before anything is sent

    address = _resolve_via(via, overlay)

    async def run() -> None:
        st = await request(address, m.StatusRequest(), key=key)
        apps = (
            sorted(next(iter(st.nodes.values()))["apps"]) if isinstance(st, m.StatusReply) else []
        )
        if app_name not in apps:
            raise MsoError(
                f"no running app named {app_name!r} (running: {', '.join(apps) or 'none'})"
            )
        await request(address, m.StopApp(app_name), key=key, signer=signer)

    asyncio.run(run())
    click.echo(json.dumps({"stopped": app_name}) if as_json else f"stopped {app_name}")


@main.command()
@click.option("--via", help="Node to ask: a node id of the running emulator or HOST:PORT.")
@overlay_option
@key_option
@click.option("--json", "as_json", is_flag=True, help="Print every node's status as JSON.")
@click.option(
    "--watch",
    type=float,
    default=None,
    is_flag=False,
    flag_value=2.0,
    help="Refresh every S seconds (--watch alone: 2) until Ctrl-C; with --json, a line each.",
)
@click.option("--count", type=click.IntRange(1), default=None, help="With --watch: stop after N.")
@_user_errors
def status(
    via: str | None,
    overlay: str | None,
    key: str | None,
    as_json: bool,
    watch: float | None,
    count: int | None,
) -> None:
    """Nodes, neighbours, chains, placement, events per edge, traffic, CPU per vertex."""
    # a blocking socket and plain-text tables, no asyncio nor rich: typed to answer in 150 ms
    from mso.client import request_blocking
    from mso.protocol import messages as m
    from mso.statusview import status_text

    if watch is not None and not watch > 0:
        raise MsoError(f"--watch: expected seconds > 0, got {watch:g}")
    address = _resolve_via(via, overlay)

    def once() -> dict[str, Any]:
        reply = request_blocking(address, m.StatusRequest(everywhere=True), key=key)
        if not isinstance(reply, m.StatusReply):
            raise MsoError(f"unexpected reply {reply!r}")
        return reply.nodes

    if watch is None:
        nodes = once()
        click.echo(json.dumps(nodes, sort_keys=True) if as_json else status_text(nodes))
        return
    shown = 0
    clear = sys.stdout.isatty() and not as_json
    with contextlib.suppress(KeyboardInterrupt):
        while count is None or shown < count:
            started = time.monotonic()
            nodes = once()
            if as_json:  # one document a line
                click.echo(json.dumps(nodes, sort_keys=True))
            else:
                if clear:
                    click.clear()
                click.echo(f"{time.strftime('%H:%M:%S')} via {address}, every {watch:g} s "
                           "(Ctrl-C stops)")  # fmt: skip
                click.echo(status_text(nodes))
            shown += 1
            if count is None or shown < count:
                time.sleep(max(0.0, watch - (time.monotonic() - started)))


@main.command()
@click.argument("scenario_file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--app", "app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--duration", type=POSITIVE, default=None, help="Seconds to run (default: until Ctrl-C)."
)
@click.option(
    "--backend",
    type=click.Choice(["user", "netns"]),
    default="user",
    show_default=True,
    help="user: one process per node on loopback, routes computed by the emulator; netns: one "
    "network namespace per node on a filtered bridge, babeld routing, the kernel forwarding.",
)
@click.option(
    "--cleanup",
    is_flag=True,
    help="Remove what a crashed netns emulation left (namespaces, processes inside) and exit.",
)
@click.option("--via", help="Node to deploy from (default: the first node).")
@click.option(
    "--convergence", type=NON_NEGATIVE, default=0.0, show_default=True,
    help="Seconds routes take to follow a link change.",
)  # fmt: skip
@click.option(
    "--heartbeat", "heartbeat_s", type=POSITIVE, default=None,
    help="Every node's heartbeat period in seconds (default 0.1).",
)  # fmt: skip
@click.option(
    "--dead-after", "dead_after_s", type=POSITIVE, default=None,
    help="Every node's failure timeout in seconds of silence (default 0.5).",
)  # fmt: skip
@click.option(
    "--name",
    help="The overlay's name, for --overlay in other commands "
    "(default: the scenario's, with -2, -3... if taken).",
)
@click.option(
    "--manage/--no-manage",
    default=True,
    help="Run the management rules on the nodes (default on); off keeps placements as deployed.",
)
@click.option("--dashboard", "with_dashboard", is_flag=True, help="Serve the live web dashboard.")
@click.option(
    "--metrics-port",
    type=click.IntRange(0, 65535),
    default=None,
    help="Every node serves Prometheus metrics on its own address at this port (0: a free one).",
)
@click.option(
    "--dashboard-listen",
    default=None,
    help=f"HOST:PORT of the dashboard (default {DASHBOARD_LISTEN}, or a free port if taken).",
)
@click.option(
    "--encrypt",
    is_flag=True,
    help="Every node and the emulator encrypt their frames (ChaCha20-Poly1305).",
)
@allow_code_option
@key_option
@click.option("--json", "as_json", is_flag=True, help="Print the final summary as JSON.")
def emulate(
    scenario_file: Path | None,
    app_file: Path | None,
    duration: float | None,
    backend: str,
    cleanup: bool,
    via: str | None,
    convergence: float,
    heartbeat_s: float | None,
    dead_after_s: float | None,
    name: str | None,
    manage: bool,
    with_dashboard: bool,
    dashboard_listen: str | None,
    metrics_port: int | None,
    encrypt: bool,
    allow_code: tuple[str, ...],
    key: str | None,
    as_json: bool,
) -> None:
    """Run a scenario as one local process per node (user-space MANET emulator), or on a
    network-namespace testbed with babeld (--backend netns)."""
    if cleanup:
        _netns_cleanup()
        return
    if scenario_file is None:
        _console().print("[red]error:[/red] give a SCENARIO_FILE (or --cleanup)")
        sys.exit(2)
    if backend == "netns" and _rootless_reexec():
        return
    _emulate(
        scenario_file, app_file, duration, via, convergence, key, as_json, heartbeat_s,
        dead_after_s, allow_code, name=name, manage=manage,
        dashboard=(dashboard_listen or "") if with_dashboard or dashboard_listen else None,
        metrics_port=metrics_port, encrypt=encrypt, backend=backend,
    )  # fmt: skip


ROOTLESS_ENV = "MSO_NETNS_USERNS"


def _rootless_reexec() -> bool:
    """Not root: run this very command again inside a new user, network and mount namespace
    (``unshare -Urnm``, root there, a private /run for the namespace files) when the kernel
    allows it; True if it ran there. Otherwise the netns backend explains and falls back."""
    import os
    import shutil
    import subprocess

    if os.geteuid() == 0 or os.environ.get(ROOTLESS_ENV) or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-Urnm", "true"], capture_output=True)
    if probe.returncode != 0:
        return False  # the backend's own check says why and falls back
    env = {**os.environ, ROOTLESS_ENV: "1"}
    script = 'mount -t tmpfs tmpfs /run && exec "$@"'
    cmd = ["unshare", "-Urnm", "sh", "-c", script, "sh", sys.executable, "-m", "mso", *sys.argv[1:]]
    sys.exit(subprocess.run(cmd, env=env).returncode)


def _netns_cleanup() -> None:
    from mso.emu.netns.testbed import cleanup, unavailable

    console = _console()
    why = unavailable()
    if why is not None:
        console.print(f"nothing to clean: {why}")
        return
    removed = cleanup()
    console.print(
        f"removed {len(removed)} namespace(s) left by stopped emulations"
        + (f": {', '.join(removed)}" if removed else "")
    )


@_user_errors
def _emulate(
    scenario_file: Path,
    app_file: Path | None,
    duration: float | None,
    via: str | None,
    convergence: float,
    key: str | None,
    as_json: bool,
    heartbeat_s: float | None = None,
    dead_after_s: float | None = None,
    allow_code: tuple[str, ...] = (),
    *,
    name: str | None = None,
    manage: bool = True,
    dashboard: str | None = None,
    metrics_port: int | None = None,
    encrypt: bool = False,
    backend: str = "user",
) -> None:
    import asyncio
    import signal

    from rich.table import Table

    from mso.emu.controller import Emulator
    from mso.emu.netns.emulator import NamespacesUnavailable, NetnsEmulator, check_available
    from mso.model.appfile import load_app
    from mso.model.yamlfile import read_text_file
    from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, check_timing
    from mso.scenario import load_scenario

    if heartbeat_s is not None or dead_after_s is not None:
        why = check_timing(
            HEARTBEAT_S if heartbeat_s is None else heartbeat_s,
            DEAD_AFTER_S if dead_after_s is None else dead_after_s,
        )
        if why:
            raise MsoError(why)
    scenario = load_scenario(scenario_file)
    app = load_app(app_file) if app_file is not None else None
    if duration is not None and duration <= 0:
        raise MsoError(f"--duration: expected a number of seconds > 0, got {duration:g}")
    console = _console()

    kind: type[Emulator] = Emulator
    if backend == "netns" and metrics_port is not None:
        raise MsoError("--metrics is not available with --backend netns yet")
    if backend == "netns":
        try:
            check_available()
            kind = NetnsEmulator
        except NamespacesUnavailable as exc:
            console.print(f"[yellow]{exc}[/yellow]; using the user-space backend instead")

    async def run() -> dict[str, Any]:
        emu = kind(
            scenario,
            key=key,
            convergence_s=convergence,
            heartbeat_s=heartbeat_s,
            dead_after_s=dead_after_s,
            name=name,
            manage=manage,
            metrics_port=metrics_port,
            allow_code=allow_code or None,
            encrypt=encrypt,
        )
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        if task is not None:  # SIGTERM stops like Ctrl-C: the finally below tears down
            loop.add_signal_handler(signal.SIGTERM, task.cancel)
        with _progress(f"starting {len(scenario.network.nodes)} node processes…"):
            await emu.start()
        board = None
        try:
            where = "namespaces (babeld)" if isinstance(emu, NetnsEmulator) else "processes"
            console.print(
                f"emulating {scenario.name} as overlay {emu.name}: {len(emu.nodes)} node {where} "
                + ", ".join(f"{n}={emu.address(n)}" for n in emu.nodes)
            )
            if dashboard is not None:
                from mso.dashboard.server import start_dashboard

                board = await start_dashboard(
                    [emu.address(n) for n in emu.nodes], emu.key, str(emu.name), dashboard,
                    1.0, emu.node_positions, list(emu.nodes),
                )  # fmt: skip
                emu.dashboard = board.url
                emu.write_state()
                console.print(f"dashboard: {board.url}")
            if emu.metrics_port is not None:
                console.print(
                    "metrics: "
                    + ", ".join(
                        f"http://{n.host}:{emu.metrics_port}/metrics" for n in emu.nodes.values()
                    )
                )
            t0 = loop.time()
            changes = asyncio.create_task(emu.play_changes(t0))
            moving = asyncio.create_task(emu.play_mobility(t0))
            if app is not None and app_file is not None:
                origin = via or next(iter(emu.nodes))
                reply = await emu.deploy(read_text_file(app_file), str(app_file), origin)
                if not reply.ok:
                    raise MsoError(f"deployment failed: {reply.error}")
                console.print(f"deployed {reply.app} from {origin} in {reply.elapsed_ms:.1f} ms")
                mapping = Table(title="vertex → node")
                mapping.add_column("vertex")
                mapping.add_column("node")
                for v, n in reply.placement.items():
                    mapping.add_row(v, n)
                console.print(mapping)
            end = None if duration is None else t0 + duration
            while end is None or loop.time() < end:
                await asyncio.sleep(min(2.0, max(0.0, (end or 1e18) - loop.time())))
                if app is not None:
                    nodes = await emu.status()
                    console.print(f"t={loop.time() - t0:5.1f}s  " + _sink_line(nodes, app.name))
            changes.cancel()
            moving.cancel()
            return await emu.status()
        finally:
            if board is not None:
                await board.stop()
            await emu.stop()

    try:
        final = asyncio.run(run())
    except (KeyboardInterrupt, asyncio.CancelledError):
        console.print("interrupted: every node process was stopped")
        return
    if as_json:
        click.echo(json.dumps(final, sort_keys=True))
        return
    from mso.statusview import status_text

    console.print("\n[bold]summary[/bold]")
    click.echo(status_text(final))


@main.command()
@click.option("--via", help="Node to ask: a node id of a running emulator or HOST:PORT.")
@overlay_option
@click.option(
    "--listen",
    default=None,
    help=f"HOST:PORT to serve the page on (default {DASHBOARD_LISTEN}, or a free port if "
    "taken); another host than 127.0.0.1 makes the overlay's controls reachable from there.",
)
@click.option(
    "--interval", type=float, default=1.0, show_default=True, help="Seconds between updates."
)
@key_option
@_user_errors
def dashboard(
    via: str | None, overlay: str | None, listen: str | None, interval: float, key: str | None
) -> None:
    """Serve a live web dashboard of a running overlay: topology, batteries, chains, events/s,
    a timeline of reconfigurations, and controls to relocate and remap. Ctrl-C stops it."""
    import asyncio

    from mso.emu.overlays import find_overlay, state_file

    address = _resolve_via(via, overlay)
    addresses, name, positions = [address], "", None
    if via is None or ":" not in via:  # an emulator's node: every node is a way in
        name, state = find_overlay(overlay) if via is None else _overlay_of(address)
        addresses += [a for a in state.get("nodes", {}).values() if a != address]
        path = state_file(name) if name else None

        def positions() -> dict[str, tuple[float, float]]:
            try:
                raw = json.loads(path.read_text()).get("positions", {}) if path else {}
                return {n: (float(p[0]), float(p[1])) for n, p in raw.items()}
            except (OSError, ValueError, TypeError, IndexError):
                return {}

    async def serve() -> None:
        from mso.dashboard.server import start_dashboard

        board = await start_dashboard(addresses, key, name, listen or "", interval, positions)
        click.echo(f"dashboard of {name or address}: {board.url}  (Ctrl-C stops it)")
        try:
            await asyncio.Event().wait()
        finally:
            await board.stop()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())


def _overlay_of(address: str) -> tuple[str, dict[str, Any]]:
    from mso.emu.overlays import running_overlays

    for name, state in running_overlays().items():
        if address in state["nodes"].values():
            return name, state
    return "", {}


@main.command()
@click.option("--json", "as_json", is_flag=True, help='Print {name: {"pid", "nodes", ...}}.')
def overlays(as_json: bool) -> None:
    """The emulators running on this machine for this user, by name (for --overlay)."""
    from mso.emu.overlays import running_overlays

    found = running_overlays()
    if as_json:
        click.echo(json.dumps(found, sort_keys=True))
        return
    if not found:
        click.echo("no emulator running")
    for name, st in found.items():
        where = f", dashboard {st['dashboard']}" if st.get("dashboard") else ""
        click.echo(
            f"{name}: {st.get('scenario', '?')}, pid {st['pid']}, "
            f"{len(st['nodes'])} nodes ({', '.join(st['nodes'])}){where}"
        )


def _sink_line(nodes: dict[str, Any], app: str) -> str:
    parts = []
    for st in nodes.values():
        a = st.get("apps", {}).get(app)
        if a is None:
            continue
        for v, s in a["vertices"].items():
            if s["kind"] == "sink":
                parts.append(f"{v}@{st['node']}: {s['processed']} events")
    return ", ".join(parts) or "no sink yet"


@main.command()
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
@_user_errors
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
    with _progress(f"simulating {duration:g} s of {scenario.name}…"):
        report = run(
            scenario, doc, str(app_file), seed=seed, duration=duration,
            convergence_s=convergence, via=via,
        )  # fmt: skip
    if as_json:
        click.echo(json.dumps(report, sort_keys=True))
    else:
        render_simulation(_console(), report)
    if plot is not None and report["deploy"]["ok"]:
        from mso.plots import simulation

        simulation(report, plot)
        click.echo(f"plot: {plot}", err=as_json)
    if not report["deploy"]["ok"]:
        raise MsoError(f"deployment failed: {report['deploy']['error']}")


def render_simulation(console: Console, r: dict[str, Any]) -> None:
    """The report of ``mso simulate``: events, reconfigurations, failures, energy."""
    from rich.table import Table

    dep = r["deploy"]
    console.print(
        f"simulated {r['app']} on {r['scenario']} for {r['duration_s']:g} s (seed {r['seed']}): "
        + (
            f"deployed in {dep['elapsed_ms']:.1f} ms"
            if dep["ok"]
            else f"deploy failed: {dep['error']}"
        )
    )
    for t, what in r["timeline"]:
        console.print(f"  t={t:7.3f}s  {what}")
    ev = r["events"]
    et = Table(title="events")
    for col in ("vertex", "kind", "events"):
        et.add_column(col, justify="right" if col == "events" else "left")
    for v, n in ev["emitted"].items():
        et.add_row(v, "emitted", str(n))
    for v, n in ev["delivered"].items():
        et.add_row(v, "delivered", str(n))
    console.print(et)
    console.print(
        f"dropped on parked chains: {ev['dropped_parked']}, "
        f"frames lost on lossy links (resent): {ev['frames_lost_on_links']}"
    )
    rc = r["reconfigurations"]
    console.print(
        f"reconfigurations: {len(rc['moves'])} vertex moves, {len(rc['recoveries'])} recoveries, "
        f"{len(rc['rejoins'])} rejoins, {len(rc['management'])} rule actions"
    )
    for mv in rc["moves"]:
        console.print(f"  t={mv['at']:7.3f}s  {mv['vertex']}: {mv['from']} -> {mv['to']}")
    for rec in rc["recoveries"]:
        state = "ok" if rec.get("ok") else (rec.get("error") or "in progress")
        console.print(
            f"  recovery from {', '.join(rec['failed']) or '-'}: {rec['remap']} remap of "
            f"{', '.join(rec['chains'])}: {state}"
        )
    for rj in rc["rejoins"]:
        console.print(
            f"  t={rj['at']:7.3f}s  {rj['node']} rejoined as incarnation {rj['incarnation']}"
        )
    for d in rc["management"]:
        console.print(f"  rule: {d}")
    ft = Table(title="failures detected")
    for col in ("node", "detector", "at s"):
        ft.add_column(col, justify="right" if col == "at s" else "left")
    for f in r["failures"]:
        ft.add_row(f["node"], f["detector"], f"{f['at']:.3f}")
    if r["failures"]:
        console.print(ft)
    nt = Table(title="energy per node")
    for col in (
        "node",
        "alive",
        "incarnation",
        "energy J",
        "W",
        "battery",
        "bytes out",
        "bytes in",
    ):
        nt.add_column(col, justify="left" if col in ("node", "alive") else "right")
    for n, e in r["energy"].items():
        frac = e["battery_fraction"]
        nt.add_row(
            n, "yes" if e["alive"] else "no", str(e["incarnation"]), f"{e['energy_j']:.2f}",
            f"{e['drain_w']:.2f}", "wall" if frac is None else f"{frac * 100:.1f}%",
            str(e["bytes_sent"]), str(e["bytes_received"]),
        )  # fmt: skip
    console.print(nt)
    console.print(
        "final placement: " + ", ".join(f"{v}@{n}" for v, n in r["placement"].items()) or "-"
    )


@main.command()
@click.argument("shell", type=click.Choice(["bash", "zsh", "fish"]))
def completion(shell: str) -> None:
    """Print the shell completion script: eval "$(mso completion bash)" in ~/.bashrc
    (zsh: ~/.zshrc; fish: mso completion fish > ~/.config/fish/completions/mso.fish)."""
    from click.shell_completion import get_completion_class

    cls = get_completion_class(shell)
    assert cls is not None
    click.echo(cls(main, {}, "mso", "_MSO_COMPLETE").source())


@main.group()
def bench() -> None:
    """Benchmarks (see docs/benchmarks.md)."""


@bench.command(name="lifetime", context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def bench_lifetime(args: tuple[str, ...]) -> None:
    """The energy study: the convoy under four placements, battery-limited robots."""
    from mso.benchmarks.lifetime import main as lifetime

    sys.exit(lifetime(list(args)))


@bench.command(name="table1")
@click.option("--json", "json_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--runs", type=click.IntRange(1, 100_000), default=30, show_default=True)
@click.option("--quick", is_flag=True, help="A few runs, to check it works.")
@click.option("--quiet", is_flag=True, help="No progress lines on stderr.")
def bench_table1(json_file: Path | None, runs: int, quick: bool, quiet: bool) -> None:
    """Table 1 of the paper: mapping, relocations, chain and global remaps, on 4 node processes."""
    from mso.benchmarks.table1 import main as table1

    args = ["--runs", str(runs)] + (["--json", str(json_file)] if json_file else [])
    args += ["--quick"] if quick else []
    sys.exit(table1(args + (["--quiet"] if quiet else [])))
