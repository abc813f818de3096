"""``mso dashboard``: the live web view of a running overlay, served from this machine."""

from __future__ import annotations

import contextlib
import json
from typing import Any

import click

from mso.cli.common import DASHBOARD_LISTEN, key_option, overlay_option, user_errors


@click.command()
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
@user_errors
def dashboard(
    via: str | None, overlay: str | None, listen: str | None, interval: float, key: str | None
) -> None:
    """Serve a live web dashboard of a running overlay: topology, batteries, chains, events/s,
    a timeline of reconfigurations, and controls to relocate and remap. Ctrl-C stops it."""
    import asyncio

    from mso.api import resolve_address
    from mso.emu.overlays import find_overlay, state_file

    address = resolve_address(via, overlay)
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

    for name, state in running_overlays(everyone=True).items():
        if address in state["nodes"].values():
            return name, state
    return "", {}
