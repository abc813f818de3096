"""``mso node``: the options of the daemon every device runs; :mod:`mso.daemon` settles them
(over a --config file) and runs the node."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from mso.cli.common import allow_code_option, key_option, operator_key_option, user_errors
from mso.cliargs import POSITIVE, power_model

if TYPE_CHECKING:
    from mso.model.network import PowerModel


@click.command()
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="YAML holding any of these options (docs/fleet.md), rules: included; flags given "
    "override it.",
)
@click.option("--id", "node_id", help="This node's id, e.g. N1.")
@click.option("--listen", help="HOST:PORT to serve (default 127.0.0.1:7000).")
@click.option("--cpu", type=POSITIVE, help="Relative CPU speed (default 1.0).")
@click.option("--battery-wh", type=POSITIVE, help="Battery capacity in Wh (default: wall power).")
@click.option(
    "--link-mbps",
    multiple=True,
    metavar="RATE|PEER=RATE",
    help="The rate of this node's radio links in Mb/s (PEER=RATE: of one, repeat), as "
    "configured, not measured: probes carry it to the planner where the routing view does not "
    "know a link's rate.",
)
@click.option(
    "--capability",
    "capabilities",
    multiple=True,
    help="What this node offers, NAME or NAME=AMOUNT (repeat): camera, gpu, mem_mb=4096; "
    "vertices that say requires: are placed by it (docs/app-format.md).",
)
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
    "--rule",
    "rules",
    multiple=True,
    metavar="NAME=VALUE",
    help="A management rule setting (repeat), e.g. vertex_interval_s=10, margin=0.05, "
    "warmup_s=5 (docs/policies.md).",
)
@click.option(
    "--metrics",
    help="HOST:PORT to serve Prometheus metrics on at /metrics (default: off).",
)
@click.option(
    "--state-dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Directory for what must outlive this process: events held for unreachable "
    "consumers (spill.sqlite3) and sources' sequence positions (default: none, kept in memory).",
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
@click.option(
    "--identity",
    type=click.Path(dir_okay=False, path_type=Path),
    help="This node's own key (made by `mso keygen --node ID`; its certificate beside it, "
    ".cert): with --operator-key, neighbours must prove their names too.",
)
@click.option(
    "--revoke-node",
    "revoked_nodes",
    multiple=True,
    metavar="KEY_ID",
    help="A node key the operator withdrew (its id, as `mso keygen --node` says): refused.",
)
@click.option(
    "--strict-moves",
    is_flag=True,
    default=None,
    help="With --operator-key: a chain end's remap moves none of the chain's other vertices "
    "here without an operator's order (its own rules remap nothing).",
)
@key_option
@click.option(
    "-v", "--verbose", is_flag=True,
    help="Debug lines too (default: info: start, deploys, moves, failures, stop).",
)  # fmt: skip
@user_errors
def node(
    config_file: Path | None,
    node_id: str | None,
    listen: str | None,
    cpu: float | None,
    battery_wh: float | None,
    link_mbps: tuple[str, ...],
    capabilities: tuple[str, ...],
    power: str | None,
    peers: tuple[str, ...],
    energy: str | None,
    routes_from: str | None,
    policy: str | None,
    manage: bool | None,
    heartbeat_s: float | None,
    dead_after_s: float | None,
    rules: tuple[str, ...],
    metrics: str | None,
    state_dir: Path | None,
    allow_code: tuple[str, ...],
    operator_keys: tuple[str, ...],
    key_file: Path | None,
    encrypt: bool | None,
    insecure: bool,
    identity: Path | None,
    revoked_nodes: tuple[str, ...],
    strict_moves: bool | None,
    key: str | None,
    verbose: bool,
) -> None:
    """Run the identical mso daemon of one device."""
    from mso.daemon.assembly import run_daemon
    from mso.daemon.config import NodeFlags

    flags = NodeFlags(
        config_file=config_file, node_id=node_id, listen=listen, cpu=cpu, battery_wh=battery_wh,
        link_mbps=link_mbps, capabilities=capabilities, power=_power(power), peers=peers,
        energy=energy, routes_from=routes_from, policy=policy, manage=manage,
        heartbeat_s=heartbeat_s, dead_after_s=dead_after_s, metrics=metrics,
        allow_code=allow_code, operator_keys=operator_keys, key_file=key_file, encrypt=encrypt,
        insecure=insecure, key=key, verbose=verbose, rules=rules, state_dir=state_dir,
        identity=identity, revoked_nodes=revoked_nodes, strict_moves=strict_moves,
    )  # fmt: skip
    run_daemon(flags)


def _power(text: str | None) -> PowerModel | None:
    """``--power IDLE_W,CPU_W,TX_UJ,RX_UJ[,modelled|measured]``, if given."""
    if text is None:
        return None
    from mso.model.network import PowerModel

    head, _, last = text.rpartition(",")
    how = last if last in ("modelled", "measured") else "modelled"
    return PowerModel(*power_model(head if last == how else text), how)
