"""A million fuzzed frames against a node process: does it live, stay bounded and count?

One ``mso node`` process (N1) runs a small app (``mso.sim.vertices``: src -> mid -> sink, all on
N1, 50 events/s). The benchmark connects twice as a member (the overlay key): as a neighbour
(hello as N2, 90% of the frames) and as a client (10%), and sends ``--frames`` authenticated
frames made by :mod:`mso.protocol.wirefuzz`: every message type with well-typed fields of random
meaning (apps, vertices, edges and nodes that may not exist, absurd numbers), some truncated,
bit-flipped or random payloads, and after every ``--bad-tag-every``-th frame a forged one (a
guessed tag). The hellos are left out (they would change a connection's role). The node is
started with an operator key (``--operator-key``): the fuzzer is a member without operator
authority, so every client command that would change the overlay (deploy, undeploy, shutdown,
LinkState, ...) must be refused, and so must the neighbour's StopApp and DeployFailed (only an
operator's signed undeploy stops a running app).

Reported: frames/s, the node's RSS (VmRSS) before, during and after, its counters (frames
rejected and malformed, messages dropped, handler errors, illegal transitions), and whether the
app still delivers events afterwards.

Usage: .venv/bin/python bench/fuzz.py [--frames 1000000] [--seed 1] [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.api import AsyncOverlay
from mso.benchmarks.common import provenance, write_results
from mso.client import overlay_key
from mso.protocol import messages as m
from mso.protocol import wirefuzz
from mso.protocol.authority import Signer
from mso.protocol.framing import FrameCodec

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
KEY = "fuzz-bench-key"
APP = """\
name: pipe
vertices:
  src: {code: 'mso.sim.vertices:Source', params: {name: s}, pinned: N1, rate: 50,
        output: 'mso.sim.vertices:Ev'}
  mid: {code: 'mso.sim.vertices:Pass', input: 'mso.sim.vertices:Ev',
        output: 'mso.sim.vertices:Ev'}
  sink: {code: 'mso.sim.vertices:Sink', params: {run: fuzz, name: k}, pinned: N1,
         input: 'mso.sim.vertices:Ev'}
edges: [[src, mid], [mid, sink]]
"""
OPERATOR = Signer()
HELLOS = (m.ClientHello, m.PeerHello)
TYPES = tuple(t for t in wirefuzz.MESSAGE_TYPES if t not in HELLOS)


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


async def status(port: int) -> dict[str, Any]:
    nodes = await AsyncOverlay(f"127.0.0.1:{port}", key=KEY).status(everywhere=False, timeout=30)
    return dict(nodes["N1"])


def sink_events(st: dict[str, Any]) -> int:
    app = st.get("apps", {}).get("pipe")
    return int(app["vertices"]["sink"]["processed"]) if app else -1


def counters(st: dict[str, Any]) -> dict[str, int]:
    t = st["traffic"]
    return {
        "frames_rejected": t["frames_rejected"],
        "frames_malformed": t["frames_malformed"],
        "dropped_messages": st.get("dropped_messages", 0),
        "handler_errors": st.get("handler_errors", 0),
        "illegal_transitions": st.get("illegal_transitions", 0),
        "frames_failed": t.get("frames_failed", 0),
        "refused_for_authority": st["authority"]["refused"],
    }


class Member:
    """One authenticated connection of the fuzzer; frames go out in batches."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        codec: FrameCodec,
        src: str,
        types: tuple[type[Any], ...],
    ) -> None:
        self.writer, self.codec, self.src, self.types = writer, codec, src, types
        self.batch: list[bytes] = []
        self.sent = 0
        self.replies = asyncio.create_task(reader.read())  # read and ignore what comes back

    @classmethod
    async def open(
        cls, port: int, hello: m.Message, src: str, types: tuple[type[Any], ...]
    ) -> Member:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        codec = FrameCodec(overlay_key(KEY))
        writer.write(codec.hello())
        while not codec.confirmed:
            _, flush = codec.feed(await reader.read(1 << 16))
            writer.write(flush)
        writer.write(codec.seal(m.wrap(src, "N1", hello)))
        return cls(reader, writer, codec, src, types)

    async def send(self, rng: random.Random, forge: bool) -> None:
        if rng.random() < 0.94:
            body = m.wrap(self.src, "N1", wirefuzz.message(rng, self.types))
        else:
            body = wirefuzz.payload(rng, self.src, "N1")
        self.batch.append(self.codec.seal(body))
        if forge:  # a forged frame slipped in: a guessed tag, rejected, the stream goes on
            forged = rng.randbytes(16) + body
            self.batch.append(len(forged).to_bytes(4, "big") + forged)
        if len(self.batch) >= 500:
            await self.flush()

    async def flush(self) -> None:
        chunk = b"".join(self.batch)
        self.batch.clear()
        self.sent += len(chunk)
        self.writer.write(chunk)
        await self.writer.drain()

    def close(self) -> None:
        self.replies.cancel()
        self.writer.close()


async def fuzz(pid: int, port: int, frames: int, seed: int, bad_every: int) -> dict[str, Any]:
    for _ in range(200):  # until the node listens
        try:
            await status(port)
            break
        except Exception:
            await asyncio.sleep(0.05)
    operator = AsyncOverlay(f"127.0.0.1:{port}", key=KEY, signer=OPERATOR)
    await operator.deploy_request(m.DeployRequest(APP, "pipe.yaml"))  # a refusal raises
    await asyncio.sleep(2.0)
    before = await status(port)
    rss: dict[str, Any] = {"before_kb": rss_kb(pid), "samples_kb": []}

    rng = random.Random(seed)
    conns = [
        await Member.open(port, m.PeerHello("N2"), "N2", TYPES),
        await Member.open(port, m.ClientHello("fuzz"), "client", TYPES),
    ]
    t0 = time.monotonic()
    for i in range(frames):
        conn = conns[0] if rng.random() < 0.9 else conns[1]
        await conn.send(rng, bad_every > 0 and i % bad_every == bad_every - 1)
        if i % (frames // 10 or 1) == 0 and i:
            rss["samples_kb"].append(rss_kb(pid))
            st = await status(port)  # what the node holds at this point
            held = {"procedures": len(st["procedures"]), "timers": st.get("timers", 0)}
            rss.setdefault("held", []).append(held)
            print(f"{i:,} frames, node RSS {rss['samples_kb'][-1] / 1024:.1f} MB, {held}",
                  file=sys.stderr)  # fmt: skip
    for conn in conns:
        await conn.flush()
    sent = sum(c.sent for c in conns)
    # until the node has read every byte sent (its bytes_in counts them), bounded
    after = await status(port)
    for _ in range(600):
        if after["traffic"]["bytes_in"] - before["traffic"]["bytes_in"] >= sent:
            break
        await asyncio.sleep(0.2)
        after = await status(port)
    sent_s = time.monotonic() - t0
    for conn in conns:
        conn.close()
    await asyncio.sleep(2.0)
    later = await status(port)
    rss["after_kb"] = rss_kb(pid)
    c0, c1 = counters(before), counters(after)
    return {
        "frames": frames,
        "bytes": sent,
        "send_s": sent_s,
        "frames_per_s": frames / sent_s,
        "rss": rss,
        "counters": {k: c1[k] - c0[k] for k in c1},
        "sink_events": {
            "before": sink_events(before),
            "after": sink_events(after),
            "2 s later": sink_events(later),
        },
        "node_alive": True,
        "last_handler_error": after.get("last_handler_error", ""),
        "refusals": after.get("refusals", {}),  # messages of a wrong meaning, by reason
    }


def render(r: dict[str, Any]) -> str:
    rss = r["rss"]
    growth = (rss["after_kb"] - rss["before_kb"]) / rss["before_kb"] * 100
    # after the first 30% of the frames the allocator has warmed up: growth from there is a leak
    warm = rss["samples_kb"][2] if len(rss["samples_kb"]) > 2 else rss["before_kb"]
    steady = (rss["after_kb"] - warm) / warm * 100
    load = r["machine"]["load_average"]
    c = r["counters"]
    return (
        f"### Fuzz: {r['frames']:,} frames into one node process\n\n"
        f"Machine: {r['machine']['cpus']} vCPUs, load average "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared, loaded).\n\n"
        "| frames | frames/s | RSS before MB | RSS max MB | RSS after MB | growth "
        "| growth after 30% "
        "| rejected (tag) | malformed | dropped | handler errors | illegal transitions "
        "| refused (authority) | sink events before / after / 2 s later |\n"
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n"
        f"| {r['frames']:,} | {r['frames_per_s']:,.0f} | {rss['before_kb'] / 1024:.1f} "
        f"| {max([rss['after_kb'], *rss['samples_kb']]) / 1024:.1f} "
        f"| {rss['after_kb'] / 1024:.1f} | {growth:+.1f}% | {steady:+.1f}% "
        f"| {c['frames_rejected']:,} "
        f"| {c['frames_malformed']:,} | {c['dropped_messages']:,} | {c['handler_errors']:,} "
        f"| {c['illegal_transitions']:,} | {c['refused_for_authority']:,} | "
        + " / ".join(str(v) for v in r["sink_events"].values())
        + " |\n"
        + _refusals(r.get("refusals", {}))
    )


def _refusals(by_reason: dict[str, int]) -> str:
    top = sorted(by_reason.items(), key=lambda kv: -kv[1])[:12]
    if not top:
        return ""
    rows = "".join(f"| {reason} | {n:,} |\n" for reason, n in top)
    return (
        "\nRefused by the core, the most frequent reasons:\n\n| reason | messages |\n|---|---:|\n"
        + rows
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--bad-tag-every", type=int, default=1000)
    ap.add_argument("--quick", action="store_true", help="20,000 frames")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    frames = 20_000 if args.quick else args.frames
    if not 1 <= frames <= 10_000_000:
        ap.error("--frames: 1..10,000,000")
    out: Path = args.json or RESULTS / ("fuzz-quick.json" if args.quick else "fuzz.json")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "MSO_KEY": KEY}
    log_path = Path(tempfile.gettempdir()) / f"mso-fuzz-node-{os.getpid()}.log"
    log = log_path.open("wb")  # the node's warnings and errors, kept for a look
    node = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mso",
            "node",
            "--id",
            "N1",
            "--listen",
            f"127.0.0.1:{port}",
            "--operator-key",
            OPERATOR.public_text(),
        ],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    t0 = time.monotonic()
    try:
        result = asyncio.run(fuzz(node.pid, port, frames, args.seed, args.bad_tag_every))
        result["node_alive"] = node.poll() is None
    finally:
        node.terminate()
        node.wait(10)
        log.close()
    result |= {"benchmark": "fuzz", "seed": args.seed, "seconds": time.monotonic() - t0}
    result["node_log_errors"] = sum(" ERROR " in line for line in log_path.open(errors="replace"))
    print(f"node log: {log_path}", file=sys.stderr)
    result |= provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
