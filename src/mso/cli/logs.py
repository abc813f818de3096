"""``mso logs NODE``: a node's log, its last lines or followed as it grows.

Nodes log one logfmt line a record (:mod:`mso.daemon.logs`); an emulator keeps each node's in a
file and names it in its overlay's state file (``logs``), which is where this finds it. A node
on a device logs to its stderr: systemd's journal (``journalctl -u mso-node``).
"""

from __future__ import annotations

import contextlib
import json
import time
from collections import deque
from pathlib import Path
from typing import IO

import click

from mso.cli.common import json_option, overlay_option, user_errors
from mso.errors import MsoError

FOLLOW_S = 0.2  # how often a followed log is looked at
MAX_LINE = 1 << 20  # a longer line (a node never writes one) is cut


def parse_logfmt(line: str) -> dict[str, str]:
    """``key=value key="quoted \\"value\\""`` -> a mapping; a word without ``=`` is kept under
    its own name with an empty value (a line that is not logfmt comes back as ``msg``)."""
    out: dict[str, str] = {}
    i, n = 0, len(line)
    while i < n:
        while i < n and line[i] == " ":
            i += 1
        start = i
        while i < n and line[i] not in "= ":
            i += 1
        key = line[start:i]
        if i >= n or line[i] != "=":
            if key:
                out[key] = ""
            continue
        i += 1
        if i < n and line[i] == '"':
            i += 1
            value: list[str] = []
            while i < n and line[i] != '"':
                if line[i] == "\\" and i + 1 < n:
                    i += 1
                    value.append({"n": "\n", "t": "\t"}.get(line[i], line[i]))
                else:
                    value.append(line[i])
                i += 1
            i += 1
            out[key] = "".join(value)
        else:
            start = i
            while i < n and line[i] != " ":
                i += 1
            out[key] = line[start:i]
    return out if "=" in line else {"msg": line}


def log_path(node: str, overlay: str | None) -> Path:
    """Where the emulator running ``node`` keeps its log (a clear error if none does)."""
    from mso.emu.overlays import find_overlay, running_overlays

    if overlay is not None:
        running = dict([find_overlay(overlay)])
    else:
        running = running_overlays(everyone=True)
    having = {name: st for name, st in running.items() if node in st.get("nodes", {})}
    if not having:
        names = sorted({n for st in running.values() for n in st.get("nodes", {})})
        known = f" (nodes: {', '.join(names)})" if names else " (no emulator is running)"
        raise MsoError(
            f"no running emulator has a node {node!r}{known}; a node on a device logs to "
            "stderr: journalctl -u mso-node"
        )
    if len(having) > 1:
        raise MsoError(
            f"node {node!r} is in {len(having)} overlays ({', '.join(having)}): give --overlay NAME"
        )
    name, state = next(iter(having.items()))
    path = state.get("logs", {}).get(node)
    if not isinstance(path, str) or not path:
        raise MsoError(f"overlay {name!r} does not say where {node}'s log is (an older mso?)")
    return Path(path)


def _show(line: str, as_json: bool) -> None:
    line = line.rstrip("\n")[:MAX_LINE]
    click.echo(json.dumps(parse_logfmt(line)) if as_json else line)


def _tail(f: IO[str], lines: int) -> deque[str]:
    last: deque[str] = deque(maxlen=lines)
    for line in f:
        last.append(line)
    return last


@click.command()
@click.argument("node")
@click.option(
    "-n",
    "--lines",
    type=click.IntRange(0),
    default=20,
    show_default=True,
    help="How many of the last lines to print first.",
)
@click.option(
    "-f",
    "--follow",
    is_flag=True,
    help="Keep printing lines as the node logs them, until Ctrl-C or the emulator stops.",
)
@overlay_option
@json_option
@user_errors
def logs(node: str, lines: int, follow: bool, overlay: str | None, as_json: bool) -> None:
    """Print an emulated node's log (one logfmt line a record; --json: one object a line)."""
    path = log_path(node, overlay)
    try:
        f = path.open(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MsoError(f"cannot read {node}'s log {path}: {exc.strerror}") from None
    with f:
        if lines:
            for line in _tail(f, lines):
                _show(line, as_json)
        else:  # (a follow goes on from what the tail read: nothing written meanwhile is lost)
            f.seek(0, 2)
        if not follow:
            return
        with contextlib.suppress(KeyboardInterrupt):
            _follow(f, path, node, overlay, as_json)


def _follow(f: IO[str], path: Path, node: str, overlay: str | None, as_json: bool) -> None:
    """Print lines as they come; stop when the emulator is gone."""
    partial = ""
    checked = time.monotonic()
    while True:
        chunk = f.readline()
        if chunk:
            partial += chunk
            if partial.endswith("\n") or len(partial) > MAX_LINE:
                _show(partial, as_json)
                partial = ""
            continue
        if time.monotonic() - checked > 1.0:  # the emulator still runs?
            checked = time.monotonic()
            try:
                if log_path(node, overlay) != path:
                    return
            except MsoError:
                return
        time.sleep(FOLLOW_S)
