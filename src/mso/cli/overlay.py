"""Commands on a running overlay, reached through any of its nodes: deploy, relocate, remap,
undeploy, status, the running emulators, and the operator key that signs such commands.

Thin on purpose: every request goes through :mod:`mso.api` (which finds the node, signs,
sends and turns a refusal into an error with the node's reason); these parse and print.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import click

from mso.cli.common import (
    client_key_option,
    json_option,
    key_option,
    overlay_option,
    sign_option,
    user_errors,
    via_option,
)
from mso.errors import MsoError

if TYPE_CHECKING:
    from mso.api import Overlay


def _app_or_only(overlay: Overlay, app_name: str | None) -> str:
    """The app named, or the one app running, for commands given no --app."""
    if app_name:
        return app_name
    apps = overlay.apps()
    if len(apps) != 1:
        raise MsoError(f"give --app NAME (running: {', '.join(apps) or 'none'})")
    return apps[0]


@click.command()
@click.argument("app_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--via", help="Node to deploy from: a node id of the running emulator or HOST:PORT.")
@click.option(
    "--planner",
    type=click.Choice(["paper", "bytes"]),  # mso.model.app.PLANNERS (not imported: startup)
    help="How chains are split along their routes: bytes (default) or paper (overrides the "
    "app's planner:).",
)
@sign_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def deploy(
    app_file: Path,
    via: str | None,
    planner: str | None,
    overlay: str | None,
    sign: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Deploy an app from any node (distributed Algorithm 1)."""
    from mso.api import Overlay

    reply = Overlay(via, overlay=overlay, key=key, sign=sign, client_key=client_key).deploy(
        app_file, planner=planner
    )
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


@click.command()
@click.argument("vertex")
@click.option("--app", "app_name", help="The app (default: the only one running).")
@click.option("--upstream", "direction", flag_value="upstream", help="Onto its predecessor's node.")
@click.option(
    "--downstream", "direction", flag_value="downstream", help="To the next node downstream."
)
@click.option("--to", "target", help="Onto this node.")
@via_option
@sign_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def relocate(
    vertex: str,
    app_name: str | None,
    direction: str | None,
    target: str | None,
    via: str | None,
    sign: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Move one vertex of a running app, with its state, losing no event (§3.4.1)."""
    from mso.api import Overlay

    ov = Overlay(
        via, overlay=overlay, key=key, sign=sign, client_key=client_key
    )  # a bad key file is reported first
    if bool(direction) == bool(target):
        raise MsoError("give exactly one of --upstream, --downstream or --to NODE")
    app = _app_or_only(ov, app_name)
    reply = ov.relocate(app, vertex, direction=direction or "", target=target or "")
    if as_json:
        click.echo(
            json.dumps({"vertex": vertex, "node": reply.node, "elapsed_ms": reply.elapsed_ms})
        )
        return
    click.echo(f"{vertex} now runs on {reply.node} (relocated in {reply.elapsed_ms:.2f} ms)")


@click.command()
@click.argument("chain", nargs=-1)
@click.option("--app", "app_name", help="The app (default: the only one running).")
@click.option("--chains", help="Several chains, comma-separated (global remap, §3.4.3).")
@click.option("--all", "everything", is_flag=True, help="Every chain of the app.")
@via_option
@sign_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def remap(
    chain: tuple[str, ...],
    app_name: str | None,
    chains: str | None,
    everything: bool,
    via: str | None,
    sign: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Re-place one chain (§3.4.2), several or all (§3.4.3) along freshly probed routes.

    `mso remap chain CHAIN`, `mso remap --chains C1,C2`, `mso remap --all`; a chain is named by
    its index (`mso chains`) or as head-...-tail."""
    from mso.api import Overlay

    ov = Overlay(
        via, overlay=overlay, key=key, sign=sign, client_key=client_key
    )  # a bad key file is reported first
    words = list(chain[1:] if chain[:1] == ("chain",) else chain)
    names = [c for c in words + (chains.split(",") if chains else []) if c]
    if bool(names) == everything:
        raise MsoError("name a chain (mso remap chain CHAIN), or give --chains C1,C2, or --all")
    reply = ov.remap(_app_or_only(ov, app_name), chains=names, everything=everything)
    if as_json:
        click.echo(json.dumps({"moved": reply.moved, "elapsed_ms": reply.elapsed_ms}))
        return
    click.echo(
        f"remapped in {reply.elapsed_ms:.1f} ms; moved: "
        + (", ".join(f"{v}->{n}" for v, n in reply.moved.items()) or "nothing")
    )


@click.command()
@click.argument("app_name")
@via_option
@sign_option
@overlay_option
@key_option
@client_key_option
@click.option("--json", "as_json", is_flag=True, help='Print {"stopped": NAME}.')
@user_errors
def undeploy(
    app_name: str,
    via: str | None,
    overlay: str | None,
    sign: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Stop an app on every node."""
    from mso.api import Overlay

    Overlay(via, overlay=overlay, key=key, sign=sign, client_key=client_key).undeploy(app_name)
    click.echo(json.dumps({"stopped": app_name}) if as_json else f"stopped {app_name}")


@click.command("revoke-node")
@click.argument("node_key")
@via_option
@sign_option
@overlay_option
@key_option
@client_key_option
@click.option("--json", "as_json", is_flag=True, help='Print {"revoked": KEY_ID}.')
@user_errors
def revoke_node(
    node_key: str,
    via: str | None,
    overlay: str | None,
    sign: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Have every node refuse a node key (its id, as `mso keygen --node` said it): signed
    with the operator key, passed from node to node, told to nodes that come back."""
    from mso.api import Overlay

    Overlay(via, overlay=overlay, key=key, sign=sign, client_key=client_key).revoke_node(node_key)
    click.echo(json.dumps({"revoked": node_key}) if as_json else f"revoked node key {node_key}")


@click.command()
@via_option
@overlay_option
@key_option
@client_key_option
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
@user_errors
def status(
    via: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
    watch: float | None,
    count: int | None,
) -> None:
    """Nodes, neighbours, chains, placement, events per edge, traffic, CPU per vertex."""
    # a blocking socket and plain-text tables, no asyncio nor rich: typed to answer in 150 ms
    from mso.api import Overlay
    from mso.statusview import status_text

    if watch is not None and not watch > 0:
        raise MsoError(f"--watch: expected seconds > 0, got {watch:g}")
    ov = Overlay(via, overlay=overlay, key=key, client_key=client_key)
    address = ov.address
    if watch is None:
        nodes = ov.status()
        click.echo(json.dumps(nodes, sort_keys=True) if as_json else status_text(nodes))
        return
    shown = 0
    clear = sys.stdout.isatty() and not as_json
    with contextlib.suppress(KeyboardInterrupt):
        while count is None or shown < count:
            started = time.monotonic()
            nodes = ov.status()
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


@click.command()
@click.option("--json", "as_json", is_flag=True, help='Print {name: {"pid", "nodes", ...}}.')
def overlays(as_json: bool) -> None:
    """The emulators running on this machine that this user may reach (root: every user's),
    by name (for --overlay)."""
    from mso.emu.overlays import running_overlays

    found = running_overlays(everyone=True)
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


@click.command()
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help='Print {"private", "public", "key"}.')
@click.option(
    "--node",
    "node_id",
    help="Make node NODE's own key instead, and OUT.cert, its certificate signed with --sign "
    "(for `mso node --identity OUT`).",
)
@click.option(
    "--client",
    "client_name",
    help="Make client NAME's own key instead, and OUT.cert, its certificate signed with --sign "
    "(for `--client-key OUT` on client commands, the dashboard and the API).",
)
@click.option(
    "--read-only",
    is_flag=True,
    help="With --client: a client that may only read (status, taps), never command.",
)
@click.option(
    "--sign",
    "sign",
    type=click.Path(dir_okay=False, path_type=Path),
    help="With --node or --client: the operator key that certifies it.",
)
@user_errors
def keygen(
    out: Path,
    as_json: bool,
    node_id: str | None,
    client_name: str | None,
    read_only: bool,
    sign: Path | None,
) -> None:
    """Make an operator key: OUT (private, mode 0600) and OUT.pub (give it to every node); or,
    with --node or --client, a node's or a client's own key and its certificate."""
    import os

    from mso.protocol.authority import Signer

    signer = Signer()
    if node_id is not None and client_name is not None:
        raise MsoError("give one of --node and --client")
    if read_only and client_name is None:
        raise MsoError("--read-only is for a client's key: give --client NAME")
    certified = node_id if node_id is not None else client_name
    key_id = ""
    if certified is not None:
        from mso.client import load_signer

        if sign is None:
            flag = "--node" if node_id is not None else "--client"
            raise MsoError(f"{flag}: give the operator key that certifies it: --sign OP.KEY")
        operator = load_signer(str(sign))
        assert operator is not None
        now_ms = time.time_ns() // 1_000_000
        if node_id is not None:
            from mso.protocol.identity import certify

            cert = certify(operator, node_id, signer.public, now_ms)
            public, key_id = cert.text(), cert.key_id
        else:
            from mso.protocol import clients

            role = "read" if read_only else "command"
            ccert = clients.certify(operator, certified, signer.public, now_ms, role)
            public, key_id = ccert.text(), ccert.key_id
        pub = out.with_name(out.name + ".cert")
    else:
        pub = out.with_name(out.name + ".pub")
        public = signer.public_text()
    try:
        fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(signer.private_text() + "\n")
        pub.write_text(public + "\n")
    except OSError as exc:
        raise MsoError(f"{exc.filename}: {exc.strerror}") from None
    if node_id is not None:
        click.echo(f"wrote {out} (keep it on {node_id}) and {pub}: mso node --identity {out}")
        click.echo(f"node key id {key_id} (to revoke it: mso node --revoke-node {key_id})")
        return
    if client_name is not None:
        role = "read-only" if read_only else "command"
        click.echo(f"wrote {out} and {pub}: a {role} client, --client-key {out}")
        click.echo(f"client key id {key_id} (to revoke it: mso revoke-node {key_id})")
        return
    if as_json:
        doc = {"private": str(out), "public": str(pub), "key": signer.public_text()}
        click.echo(json.dumps(doc))
        return
    click.echo(f"wrote {out} (keep it secret) and {pub}: mso node --operator-key {pub}")
    click.echo(signer.public_text())
