"""Looking at a running edge: ``mso echo`` (its events, decoded), ``mso hz`` (its rate and
delay) and ``mso record`` (to a ROS 2 bag that ``mso.ros2:BagSource`` replays).

Each opens a tap (:meth:`mso.api.AsyncOverlay.tap`): the node hosting the edge's consumer
sends copies, rate-limited and bounded on its side, so looking never slows or loses the
edge's own events; what the tap had to leave out is counted and said.
"""

from __future__ import annotations

import contextlib
import json
import re
import sys
import time
from collections import deque
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from mso.cli.common import (
    client_key_option,
    json_option,
    key_option,
    overlay_option,
    user_errors,
    via_option,
)
from mso.errors import MsoError

if TYPE_CHECKING:
    import asyncio

    from mso.protocol import messages as m

RECORD_RATE = 10_000.0  # mso.protocol.taps.MAX_RATE: a recording asks for every event
SHOWN_ITEMS = 16  # a list longer than this is cut in text output (--full shows it all)


def _run(main: Coroutine[Any, Any, None]) -> None:
    """Run until done or Ctrl-C (the tap ends on the nodes with its lease)."""
    import asyncio

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main)


def _overlay(via: str | None, overlay: str | None, key: str | None, client_key: str | None) -> Any:
    from mso.api import AsyncOverlay

    return AsyncOverlay(via, overlay=overlay, key=key, client_key=client_key)


def brief(value: Any, full: bool = False) -> Any:
    """An event made readable: bytes as their size, long lists cut (unless ``full``)."""
    if isinstance(value, bytes | bytearray):
        return f"<{len(value)} bytes>"
    if isinstance(value, dict):
        return {k: brief(v, full) for k, v in value.items()}
    if isinstance(value, list):
        shown = value if full or len(value) <= SHOWN_ITEMS else value[:SHOWN_ITEMS]
        items = [brief(v, full) for v in shown]
        if len(shown) < len(value):
            items.append(f"... ({len(value)} items)")
        return items
    return value


def _jsonable(value: Any) -> Any:
    import base64

    if isinstance(value, bytes | bytearray):
        return base64.b64encode(value).decode()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    return value


def _seconds(
    name: str, low: float, high: float, default: float, help: str
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    return click.option(name, type=click.FloatRange(low, high), default=default,
                        show_default=True, help=help)  # fmt: skip


@click.command()
@click.argument("app")
@click.argument("edge")
@click.option(
    "--rate",
    type=click.FloatRange(0.1, 10_000),
    default=10.0,
    show_default=True,
    help="Events shown a second at most (the node leaves out the rest, counted).",
)
@click.option("--count", type=click.IntRange(1), default=None, help="Stop after N events.")
@click.option("--full", is_flag=True, help="Show whole lists and byte strings' sizes uncut.")
@via_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def echo(
    app: str,
    edge: str,
    rate: float,
    count: int | None,
    full: bool,
    via: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Print the events of a running edge as they reach its consumer (EDGE: SRC:DST, 'SRC->DST'
    or a vertex with one output edge), decoded; --json: one object a line, bytes in base64."""
    from mso.api import decode_event

    shown = 0
    last: list[Any] = [None]

    async def main() -> None:
        nonlocal shown
        ov = _overlay(via, overlay, key, client_key)
        async for msg in ov.tap(app, edge, rate=rate):
            last[0] = msg
            for seq, payload in zip(msg.seqs, msg.events, strict=True):
                event = decode_event(payload, msg.fields)
                if as_json:
                    line = {"edge": msg.edge, "node": msg.node, "seq": seq, "event": event}
                    click.echo(json.dumps(_jsonable(line)))
                else:
                    click.echo(f"#{seq} {json.dumps(brief(event, full), default=str)}")
                shown += 1
                if count is not None and shown >= count:
                    return

    _run(main())
    if last[0] is not None and not as_json:
        msg = last[0]
        click.echo(
            f"{app} {msg.edge} at {msg.node}: {msg.seen} events while looking, {shown} shown, "
            f"{msg.dropped} left out by the tap (rate limit)",
            err=True,
        )


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


@click.command()
@click.argument("app")
@click.argument("edge")
@_seconds("--window", 0.5, 600, 5.0, "Seconds the rate and delays are taken over.")
@_seconds("--every", 0.2, 60, 1.0, "Seconds between two reports.")
@click.option("--count", type=click.IntRange(1), default=None, help="Stop after N reports.")
@via_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def hz(
    app: str,
    edge: str,
    window: float,
    every: float,
    count: int | None,
    via: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Report a running edge's rate (events a second reaching its consumer) and delay (how long
    events had been in their chain when they arrived: p50, p99, max)."""
    reports = 0

    async def main() -> None:
        nonlocal reports
        seen: deque[tuple[float, int]] = deque()  # (node clock, events seen)
        delays: deque[tuple[float, float]] = deque()
        due = time.monotonic() + every
        node = ""
        ov = _overlay(via, overlay, key, client_key)
        async for msg in ov.tap(app, edge, rate=0.0):
            if msg.host:  # the old host's last word (its clock), as the relay follows a move
                node = ""
                continue
            if msg.node != node:  # the consumer moved: another node's clock, a fresh window
                node = msg.node
                seen.clear()
                delays.clear()
            seen.append((msg.at, msg.seen))
            delays.extend((msg.at, d) for d in msg.delays_ms)
            while seen and seen[0][0] < msg.at - window:
                seen.popleft()
            while delays and delays[0][0] < msg.at - window:
                delays.popleft()
            if time.monotonic() < due:
                continue
            due += every
            span = seen[-1][0] - seen[0][0]
            rate = (seen[-1][1] - seen[0][1]) / span if span > 0 else 0.0
            ds = [d for _, d in delays]
            report: dict[str, Any] = {"edge": msg.edge, "node": msg.node, "rate": round(rate, 3),
                                      "window_s": round(span, 3), "events": msg.seen}  # fmt: skip
            if ds:
                report |= {"delay_ms": {"p50": _percentile(ds, 0.5), "p99": _percentile(ds, 0.99),
                                        "max": max(ds), "batches": len(ds)}}  # fmt: skip
            if as_json:
                click.echo(json.dumps(report))
            else:
                delay = report.get("delay_ms")
                said = (
                    f"delay p50 {delay['p50']:.2f} ms  p99 {delay['p99']:.2f} ms  "
                    f"max {delay['max']:.2f} ms"
                    if delay
                    else "delay -"
                )
                click.echo(
                    f"{msg.edge} at {msg.node}: {rate:.2f} events/s  {said}  "
                    f"(over {span:.1f} s, {msg.seen} seen)"
                )
            reports += 1
            if count is not None and reports >= count:
                return

    _run(main())


def _topic(app: str, edge: str) -> str:
    """The bag topic an edge is recorded on: ``/APP/SRC/DST`` (ROS name rules applied)."""
    src, _, dst = edge.partition("->")
    parts = [re.sub(r"[^A-Za-z0-9_]", "_", p) or "_" for p in (app, src, dst or "out")]
    return "/" + "/".join(p if p[0].isalpha() else "x" + p for p in parts)


def _bag_path(out: Path, storage: str | None) -> tuple[Path, str]:
    """``-o run.mcap`` -> the bag directory ``run`` with MCAP storage (rosbag2 bags are
    directories, as ``ros2 bag record -o`` makes them)."""
    suffix = {".mcap": "mcap", ".db3": "sqlite3"}.get(out.suffix)
    if suffix is not None:
        if storage is not None and storage != suffix:
            raise MsoError(f"-o {out}: the name says {suffix}, --storage says {storage}")
        return out.with_suffix(""), suffix
    return out, storage or "mcap"


class _Recorder:
    """Each edge's copies, written to one bag as they come (typed ROS messages only)."""

    def __init__(self, path: Path, storage: str) -> None:
        try:
            from mso.ros2.bags import BagSink  # noqa: F401  (the extra is there)
        except ImportError:
            raise MsoError("mso record writes ROS 2 bags: pip install 'mso[ros2]'") from None
        self.path, self.storage = path, storage
        self.writer: Any = None
        self.connections: dict[str, tuple[Any, str, Callable[[bytes], bytes]]] = {}
        self.written: dict[str, int] = {}
        self.dropped: dict[str, int] = {}
        self.seen: dict[str, int] = {}

    def _open(self, app: str, msg: m.TapEvents) -> tuple[Any, str, Callable[[bytes], bytes]]:
        import msgspec
        from rosbags.rosbag2 import StoragePlugin, Writer

        from mso.ros2.types import type_map

        module, _, name = msg.format.partition(":")
        parts = name.split("__")
        if module != "mso.ros2.types" or len(parts) != 3:
            raise MsoError(
                f"edge {msg.edge} carries {msg.format or 'untyped events'}, not a ROS message "
                "(a format mso.ros2.types:pkg__msg__Name): mso record writes ROS 2 bags"
            )
        ros_type = "/".join(parts)
        types = type_map()
        decoder = msgspec.msgpack.Decoder(types.struct(ros_type))

        def cdr(payload: bytes) -> bytes:
            msg = types.to_ros(ros_type, decoder.decode(payload))
            return bytes(types.store.serialize_cdr(msg, ros_type))

        if self.writer is None:
            plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[self.storage]
            self.writer = Writer(self.path, version=9, storage_plugin=plugin)
            self.writer.open()
        conn = self.writer.add_connection(_topic(app, msg.edge), ros_type, typestore=types.store)
        return conn, ros_type, cdr

    def take(self, app: str, msg: m.TapEvents, wall: float, limit: int | None = None) -> int:
        """Write the copies in ``msg`` (stamped on the wall clock from the node's arrival
        stamps), at most ``limit``; returns how many."""
        found = self.connections.get(msg.edge)
        if found is None:
            found = self.connections[msg.edge] = self._open(app, msg)
        conn, _, cdr = found
        n = len(msg.events) if limit is None else min(limit, len(msg.events))
        for stamp, payload in zip(msg.stamps[:n], msg.events[:n], strict=True):
            at_ns = int((wall - (msg.at - stamp)) * 1e9)
            self.writer.write(conn, at_ns, cdr(payload))
        self.written[msg.edge] = self.written.get(msg.edge, 0) + n
        self.dropped[msg.edge], self.seen[msg.edge] = msg.dropped, msg.seen
        return n

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


@click.command()
@click.argument("app")
@click.argument("edges", nargs=-1, required=True)
@click.option(
    "-o",
    "--output",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="The bag to write (a new directory; OUT.mcap or OUT.db3 names the storage).",
)
@click.option(
    "--storage",
    type=click.Choice(["mcap", "sqlite3"]),
    default=None,
    help="Bag storage (default: from -o's suffix, else mcap).",
)
@click.option(
    "--count",
    type=click.IntRange(1),
    default=None,
    help="Stop after N messages (all edges together).",
)
@click.option("--duration", type=click.FloatRange(0.1), default=None, help="Stop after S seconds.")
@via_option
@overlay_option
@key_option
@client_key_option
@json_option
@user_errors
def record(
    app: str,
    edges: tuple[str, ...],
    out: Path,
    storage: str | None,
    count: int | None,
    duration: float | None,
    via: str | None,
    overlay: str | None,
    key: str | None,
    client_key: str | None,
    as_json: bool,
) -> None:
    """Record running edges to a ROS 2 bag (one topic each, /APP/SRC/DST), until Ctrl-C,
    --count or --duration; replay it with mso.ros2:BagSource or ros2 bag play. The edges must
    carry ROS messages (mso.ros2.types formats)."""
    path, kind = _bag_path(out, storage)
    if path.exists():
        raise MsoError(f"{path} exists already; a recording never overwrites")
    import asyncio

    rec = _Recorder(path, kind)
    total = 0
    errors: list[BaseException] = []

    async def one(edge: str, stop: asyncio.Event) -> None:
        nonlocal total
        ov = _overlay(via, overlay, key, client_key)
        try:
            async for msg in ov.tap(app, edge, rate=RECORD_RATE):
                left = None if count is None else count - total
                total += rec.take(app, msg, time.time(), left)
                if count is not None and total >= count:
                    stop.set()
        except MsoError as exc:
            errors.append(exc)
            stop.set()

    async def main() -> None:
        stop = asyncio.Event()
        tasks = [asyncio.create_task(one(e, stop)) for e in edges]
        try:
            await asyncio.wait_for(stop.wait(), duration)
        except TimeoutError:
            pass
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    try:
        _run(main())
    finally:
        rec.close()
    topics = {
        _topic(app, edge): {"edge": edge, "messages": n, "seen": rec.seen.get(edge, 0),
                            "left_out": rec.dropped.get(edge, 0)}
        for edge, n in rec.written.items()
    }  # fmt: skip
    if as_json:
        click.echo(json.dumps({"bag": str(path), "storage": kind, "topics": topics}))
    else:
        for topic, t in topics.items():
            left = t["left_out"]
            note = f", {left} left out by the tap (it never holds the edge back)" if left else ""
            click.echo(f"{topic}: {t['messages']} messages of {t['seen']} seen{note}")
        if rec.written:
            click.echo(f"wrote {path} ({kind})")
    if errors:
        raise MsoError(str(errors[0]))
    if not rec.written:
        click.echo("nothing recorded (no events arrived)", err=True)
        sys.exit(1)
