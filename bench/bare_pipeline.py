"""The floor under mso's 2-hop latency: the same pipeline in bare asyncio over TCP.

``source -> relay -> sink``, three Python processes on loopback, each an asyncio loop (as an mso
node is), events of ``bench/peer_dora.py``'s form (``mso.benchmarks.vertices.peer.Probe``,
msgpack by msgspec) in length-prefixed frames over TCP (``TCP_NODELAY``, as asyncio sets it):
the source a timer at the rate, the relay decodes and re-encodes each event, the sink stamps
its latency. Nothing else: no authentication, no acknowledgement, no sequence numbers, no
heartbeats, no data plane. What mso does per event beyond this is what mso adds; what this
costs is what Python, asyncio and the kernel's loopback cost on the machine.

``bench/peer_dora.py --floor`` runs it beside mso and dora-rs (:func:`run_bare`); alone:
``.venv/bin/python bench/bare_pipeline.py [--size 38] [--rate 100] [--window 10]`` prints its
figures. ``--role`` is how it starts its own three processes.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

from mso.benchmarks.common import cpu_seconds, percentile
from mso.benchmarks.vertices.peer import Probe, probe_pad

LEN = struct.Struct("!I")


async def frames(reader: asyncio.StreamReader) -> Any:
    """Each length-prefixed frame's bytes until the connection closes."""
    while True:
        try:
            head = await reader.readexactly(4)
            yield await reader.readexactly(LEN.unpack(head)[0])
        except (asyncio.IncompleteReadError, ConnectionError):
            return


async def serve_once(port: int) -> asyncio.StreamReader:
    """Accept one connection on ``port`` and return its reader."""
    got: asyncio.Future[asyncio.StreamReader] = asyncio.get_running_loop().create_future()

    def accepted(r: asyncio.StreamReader, _: asyncio.StreamWriter) -> None:
        if not got.done():
            got.set_result(r)

    server = await asyncio.start_server(accepted, "127.0.0.1", port)
    reader = await got
    server.close()
    return reader


async def connect(port: int) -> asyncio.StreamWriter:
    for _ in range(200):  # the next process may not listen yet
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            return writer
        except OSError:
            await asyncio.sleep(0.05)
    raise SystemExit(f"nothing listens on {port}")


async def role(args: argparse.Namespace) -> None:
    enc, dec = msgspec.msgpack.Encoder(), msgspec.msgpack.Decoder(Probe)
    loop = asyncio.get_running_loop()
    if args.role == "source":
        writer = await connect(args.port_out)
        pad = bytes(probe_pad(args.size))
        t0, k = loop.time(), 0
        while True:  # event k at t0 + k / rate (call_at: the loop's timer, as mso's)
            fired = loop.create_future()
            loop.call_at(t0 + k / args.rate, fired.set_result, None)
            await fired
            body = enc.encode(Probe(float(k), time.perf_counter(), pad))
            writer.write(LEN.pack(len(body)) + body)
            k += 1
    reader = await serve_once(args.port_in)
    if args.role == "relay":
        writer = await connect(args.port_out)
        async for body in frames(reader):
            out = enc.encode(dec.decode(body))
            writer.write(LEN.pack(len(out)) + out)
        return
    lat: list[float] = []
    opens = closes = float("inf")
    async for body in frames(reader):
        now = time.perf_counter()
        ev = dec.decode(body)
        if opens == float("inf"):
            opens = now + args.warmup
            closes = opens + args.window
            Path(args.out + ".first.tmp").write_text(json.dumps({"at": time.monotonic()}))
            os.replace(args.out + ".first.tmp", args.out + ".first")
        if opens <= now < closes:
            lat.append(now - ev.t)
        elif now >= closes:
            lat.sort()
            doc = {"window_events": len(lat), "p50_us": percentile(lat, 50) * 1e6,
                   "p99_us": percentile(lat, 99) * 1e6, "missing": 0}  # fmt: skip
            Path(args.out + ".tmp").write_text(json.dumps(doc))
            os.replace(args.out + ".tmp", args.out)
            return


def free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


async def wait_file(path: Path, timeout: float) -> dict[str, Any] | None:
    """The JSON document a process writes to ``path`` (written whole: renamed into place)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError, ValueError):
            doc: dict[str, Any] = json.loads(path.read_text())
            return doc
        await asyncio.sleep(0.005)
    return None


async def run_bare(
    size: int, rate: float, warmup: float, window: float, tmp: Path
) -> dict[str, Any]:
    """One run of the three processes: latency p50/p99 and CPU over the window."""
    row: dict[str, Any] = {"system": "bare asyncio TCP", "size": size}
    out = tmp / f"bare-{size}-{time.monotonic_ns()}.json"
    a, b = free_ports(2)
    common = ["--size", str(size), "--rate", str(rate), "--warmup", str(warmup)]
    common += ["--window", str(window), "--out", str(out)]
    me = [sys.executable, str(Path(__file__).resolve())]
    t0 = time.monotonic()
    procs = [
        await asyncio.create_subprocess_exec(*me, "--role", "sink", "--port-in", str(b), *common),
        await asyncio.create_subprocess_exec(
            *me, "--role", "relay", "--port-in", str(a), "--port-out", str(b), *common
        ),
        await asyncio.create_subprocess_exec(
            *me, "--role", "source", "--port-out", str(a), *common
        ),
    ]
    try:
        first = await wait_file(Path(f"{out}.first"), 30.0)
        if first is None:
            row["error"] = "no event reached the sink within 30 s"
            return row
        row["cold_start_s"] = first["at"] - t0
        await asyncio.sleep(max(0.0, first["at"] + warmup - time.monotonic()))
        c0 = {p.pid: cpu_seconds(p.pid) for p in procs}
        await asyncio.sleep(window)
        used = sum(cpu_seconds(p) - c for p, c in c0.items())
        stats = await wait_file(out, 10.0)
        if stats is None:
            row["error"] = "the sink's window did not close in time"
            return row
        row.update(stats)
        row["node_processes"] = 3
        row["cpu_nodes_s"] = used
        row["cpu_us_per_event"] = used / max(1, stats["window_events"]) * 1e6
    finally:
        for p in procs:
            if p.returncode is None:
                p.kill()
            await p.wait()
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--size", type=int, default=38)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--window", type=float, default=10.0)
    ap.add_argument("--role", choices=("source", "relay", "sink"), help=argparse.SUPPRESS)
    ap.add_argument("--port-in", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--port-out", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--out", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.rate <= 0 or args.window <= 0 or args.warmup < 0:
        ap.error("--rate and --window must be positive, --warmup not negative")
    try:
        probe_pad(args.size)
    except ValueError as exc:
        ap.error(str(exc))
    if args.role:
        asyncio.run(role(args))
        return 0
    with tempfile.TemporaryDirectory(prefix="mso-bench-bare-") as tmp:
        row = asyncio.run(run_bare(args.size, args.rate, args.warmup, args.window, Path(tmp)))
    print(json.dumps(row, indent=2))
    return 0 if "error" not in row else 1


if __name__ == "__main__":
    sys.exit(main())
