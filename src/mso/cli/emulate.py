"""``mso emulate``: a scenario as one process per node on loopback, or on the network-namespace
testbed with babeld; prints what it does and a summary at the end."""

from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path
from typing import Any

import click

from mso.cli.common import (
    DASHBOARD_LISTEN,
    allow_code_option,
    console,
    key_option,
    progress,
    user_errors,
)
from mso.cliargs import NON_NEGATIVE, POSITIVE
from mso.errors import MsoError


@click.command()
@click.argument("scenario_file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--app",
    "app_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="An app file to deploy once the nodes are up (default: none, an empty overlay).",
)
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
    "--routing",
    type=click.Choice(["babeld", "batmand"]),  # mso.emu.netns.daemons.DAEMONS (startup)
    default="babeld",
    show_default=True,
    help="The routing daemon in every namespace (--backend netns).",
)
@click.option(
    "--cleanup",
    is_flag=True,
    help="Remove what a crashed netns emulation left (namespaces, processes inside) and exit.",
)
@click.option("--via", help="Node to deploy from (default: the first node).")
@click.option(
    "--planner",
    type=click.Choice(["paper", "bytes"]),  # mso.model.app.PLANNERS (not imported: startup)
    help="How chains are split along their routes: bytes (default) or paper (overrides the "
    "app's planner:).",
)
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
@click.option(
    "--identities",
    is_flag=True,
    help="Run the secure configuration: an operator key made for the run, each node's own "
    "certified key, clients with certified keys only (left for you beside the overlay).",
)
@allow_code_option
@key_option
@click.option("--json", "as_json", is_flag=True, help="Print the final summary as JSON.")
def emulate(
    scenario_file: Path | None,
    app_file: Path | None,
    duration: float | None,
    backend: str,
    routing: str,
    cleanup: bool,
    via: str | None,
    planner: str | None,
    convergence: float,
    heartbeat_s: float | None,
    dead_after_s: float | None,
    name: str | None,
    manage: bool,
    with_dashboard: bool,
    dashboard_listen: str | None,
    metrics_port: int | None,
    encrypt: bool,
    identities: bool,
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
        console().print("[red]error:[/red] give a SCENARIO_FILE (or --cleanup)")
        sys.exit(2)
    if backend == "netns" and _rootless_reexec():
        return
    _emulate(
        scenario_file, app_file, duration, via, convergence, key, as_json, heartbeat_s,
        dead_after_s, allow_code, name=name, manage=manage,
        dashboard=(dashboard_listen or "") if with_dashboard or dashboard_listen else None,
        metrics_port=metrics_port, encrypt=encrypt, backend=backend, planner=planner,
        routing=routing, identities=identities,
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

    out = console()
    why = unavailable()
    if why is not None:
        out.print(f"nothing to clean: {why}")
        return
    removed = cleanup()
    out.print(
        f"removed {len(removed)} namespace(s) left by stopped emulations"
        + (f": {', '.join(removed)}" if removed else "")
    )


@user_errors
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
    planner: str | None = None,
    routing: str = "babeld",
    identities: bool = False,
) -> None:
    import asyncio
    import signal

    from rich.table import Table

    from mso.cli.render import sink_line
    from mso.emu.controller import Emulator
    from mso.emu.netns.emulator import NamespacesUnavailable, NetnsEmulator, check_available
    from mso.model.appfile import load_app
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
    out = console()

    kind: type[Emulator] = Emulator
    if backend == "netns" and metrics_port is not None:
        raise MsoError("--metrics is not available with --backend netns yet")
    if backend == "netns":
        try:
            check_available(routing)
            kind = NetnsEmulator
        except NamespacesUnavailable as exc:
            out.print(f"[yellow]{exc}[/yellow]; using the user-space backend instead")

    from rich.markup import escape

    from mso.cli.story import MoveWatch, console_input, read_commands
    from mso.emu.commands import HELP, Commands, ControlSocket
    from mso.statusview import error_alarms

    def tell(at: float, text: str) -> None:
        out.print(f"t={at:5.1f}s  {escape(text)}")

    async def run() -> tuple[dict[str, Any] | None, Emulator, bool]:
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
            identities=identities,
        )
        if isinstance(emu, NetnsEmulator):
            emu.routing = routing
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        if task is not None:  # SIGTERM stops like Ctrl-C: the summary, then the teardown
            loop.add_signal_handler(signal.SIGTERM, task.cancel)
        with progress(f"starting {len(scenario.network.nodes)} node processes…"):
            await emu.start()
        emu.tell = tell
        commands = Commands(emu)
        control = ControlSocket(commands, str(emu.name))
        board = None
        interrupted = False
        tasks: list[asyncio.Task[Any]] = []
        final: dict[str, Any] | None = None
        try:
            try:
                await control.start()
                where = f"namespaces ({routing})" if isinstance(emu, NetnsEmulator) else "processes"
                out.print(
                    f"emulating {scenario.name} as overlay {emu.name}: {len(emu.nodes)} node "
                    f"{where} " + ", ".join(f"{n}={emu.address(n)}" for n in emu.nodes)
                )
                if emu.user_keys is not None:
                    op, you = emu.user_keys
                    out.print(
                        f"identities: each node proves its own key; clients need a certified "
                        f"one (yours: {you}, found by mso status --overlay {emu.name}); the "
                        f"run's operator key: --sign {op}"
                    )
                if dashboard is not None:
                    from mso.dashboard.server import start_dashboard

                    board = await start_dashboard(
                        [emu.address(n) for n in emu.nodes], emu.key, str(emu.name), dashboard,
                        1.0, emu.node_positions, list(emu.nodes),
                    )  # fmt: skip
                    emu.dashboard = board.url
                    emu.write_state()
                    out.print(f"dashboard: {board.url}")
                if emu.metrics_port is not None:
                    out.print(
                        "metrics: "
                        + ", ".join(
                            f"http://{n.host}:{emu.metrics_port}/metrics"
                            for n in emu.nodes.values()
                        )
                    )
                tasks.append(asyncio.create_task(emu.play()))
                lines = console_input(loop)
                if lines is not None:
                    tasks.append(asyncio.create_task(read_commands(lines, commands, tell)))
                    out.print(f"{HELP} (or mso emulator ... --overlay {emu.name})")
                watch = MoveWatch()
                if app is not None and app_file is not None:
                    origin = via or next(iter(emu.nodes))
                    reply = await emu.overlay(origin).deploy(app_file, planner=planner)
                    out.print(f"deployed {reply.app} from {origin} in {reply.elapsed_ms:.1f} ms")
                    mapping = Table(title="vertex → node")
                    mapping.add_column("vertex")
                    mapping.add_column("node")
                    for v, n in reply.placement.items():
                        mapping.add_row(v, n)
                    out.print(mapping)
                    watch.placed(app.name, reply.placement)
                end = None if duration is None else emu.t0 + duration
                errors: dict[str, int] = {}
                while end is None or loop.time() < end:
                    wait = min(2.0, max(0.0, (end or 1e18) - loop.time()))
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(commands.done.wait(), wait)
                    if commands.done.is_set():
                        break
                    if app is None:
                        continue
                    try:
                        nodes = await emu.status()
                    except MsoError as exc:
                        emu.say(f"status: {exc}")
                        continue
                    for at, line in watch.moves(nodes, app.name, emu.now()):
                        tell(at, line)
                    out.print(f"t={emu.now():5.1f}s  " + sink_line(nodes, app.name))
                    for alarm in error_alarms(errors, nodes, app.name):
                        out.print(f"[red]errors:[/red] {escape(alarm)}")
            except asyncio.CancelledError:  # Ctrl-C or SIGTERM: the summary all the same
                if task is not None:
                    task.uncancel()
                interrupted = True
            for t in tasks:
                t.cancel()
            try:
                final = await emu.status()
            except MsoError as exc:
                emu.say(f"summary: {exc}")
            return final, emu, interrupted
        finally:
            for t in tasks:
                t.cancel()
            await control.stop()
            if board is not None:
                await board.stop()
            await emu.stop()

    try:
        final, emu, interrupted = asyncio.run(run())
    except (KeyboardInterrupt, asyncio.CancelledError):
        out.print("interrupted: every node process was stopped")
        return
    if as_json:
        click.echo(json.dumps(final or {}, sort_keys=True))
        return
    from mso.statusview import status_text

    out.print(
        "\n[bold]summary[/bold]" + (" (stopped early: Ctrl-C or SIGTERM)" if interrupted else "")
    )
    told = [(at, text) for at, text in emu.story if not text.startswith("status: ")]
    if told:
        out.print("what happened (seconds after the start):")
        for at, text in told:
            out.print(f"  t={at:6.1f}s  {escape(text)}")
    down = [n for n in emu.nodes if n in emu.dead]
    if down:
        out.print(f"nodes down at the end: {', '.join(down)}")
    if emu.emptied:
        out.print(f"stopped by an empty battery (fail-stop): {', '.join(sorted(emu.emptied))}")
    if final is None:
        out.print("[red]no node answered the last status request: no figures to show[/red]")
        return
    click.echo(status_text(final))
