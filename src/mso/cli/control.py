"""``mso emulator``: commands to a running emulator from another terminal (what its console
takes), through :class:`mso.api.EmulatorControl`."""

from __future__ import annotations

import click

from mso.cli.common import overlay_option, user_errors
from mso.cliargs import OneLineGroup


@click.group(cls=OneLineGroup)
def emulator() -> None:
    """Command a running emulator (mso emulate): fail or restart a node, cut or heal a link,
    move a node; the emulator says what it did."""


def _send(overlay: str | None, line: str) -> None:
    from mso.api import EmulatorControl

    click.echo(EmulatorControl(overlay).command(line))


@emulator.command()
@click.argument("node")
@overlay_option
@user_errors
def fail(node: str, overlay: str | None) -> None:
    """Fail-stop NODE now (its process is killed; its links go)."""
    _send(overlay, f"fail {node}")


@emulator.command()
@click.argument("node")
@overlay_option
@user_errors
def restart(node: str, overlay: str | None) -> None:
    """Start NODE again (failed, killed by hand or crashed): a new incarnation."""
    _send(overlay, f"restart {node}")


@emulator.command()
@click.argument("a")
@click.argument("b")
@overlay_option
@user_errors
def cut(a: str, b: str, overlay: str | None) -> None:
    """Cut the link A-B until healed (whatever the radio or the script says)."""
    _send(overlay, f"cut {a} {b}")


@emulator.command()
@click.argument("a")
@click.argument("b")
@overlay_option
@user_errors
def heal(a: str, b: str, overlay: str | None) -> None:
    """Undo a cut of A-B (the link is back if the radio gives it)."""
    _send(overlay, f"heal {a} {b}")


@emulator.command()
@click.argument("node")
@click.argument("x", type=float)
@click.argument("y", type=float)
@overlay_option
@user_errors
def move(node: str, x: float, y: float, overlay: str | None) -> None:
    """Put NODE at X Y metres and keep it there (links follow with a radio_range)."""
    _send(overlay, f"move {node} {x!r} {y!r}")


@emulator.command()
@overlay_option
@user_errors
def stop(overlay: str | None) -> None:
    """End the run: the emulator prints its summary and stops every node."""
    _send(overlay, "stop")
