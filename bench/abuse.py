"""Each attack class of issue 27 replayed against a running overlay carrying a counted stream.

For each attack a fresh emulator (node processes on loopback, its own random key) runs the line
``N1 - N2 - N3`` with ``src (N1) -> mid (N2) -> sink (N3)`` (``mso.benchmarks.vertices.failure``:
a counting source at 100 events/s, a pass-through, an order-checking sink), so the stream goes
through N2, the node attacked. After ``--steady`` s the attack runs for ``--attack`` s, then
stops; meanwhile a legitimate client asks N2 for its status every 0.2 s, each time on a fresh
connection (what an operator's ``mso status`` does), with a 2 s timeout. Figures per attack:

- RSS of each node before the attack, its peak during it (sampled every 0.25 s), and after
  (``--after`` s after it stopped); the target is < 2x the one before;
- events lost, duplicated and reordered on the stream over the whole run (the sink's holes and
  what lies past its highest number, its repeats, its arrivals ahead of their turn), read once
  the sink has caught up with the source (or ``DRAIN_S`` passed);
- legitimate status requests answered during the attack, of those asked (target >= 95%);
- recovery: from the attack's end until a status request is answered and the sink has got an
  event the source numbered after the end (target <= 2 s);
- what N2 counted (refusals, connection and traffic counters the attack should move).

Attacks (``--only`` picks some): ``guesser`` (an outsider trying keys: it reads what the node
says after its hello), ``slots`` (an outsider reopening 96 connections, 1.5 times the pending
pool, from four addresses the moment each is closed), ``relay-flood`` (a member sending
invented ``NodeDown``s and 8 MiB control frames to N3 through N2), ``invented-failures``
(50,000 ``NodeDown``s about invented nodes to N2), ``slow-clients`` (20 members asking for
status and never reading), ``early-messages`` (messages of never-announced apps, 64 KiB each),
``deep-bodies`` (bodies nested 100,000 deep), ``big-documents`` (4 MiB deploy documents of
tiny scalars); with ``--identities`` also ``forged-words`` (a captured robot that hosts nothing
of the stream: events for N3 written in N2's name handed to N2, events of the stream's first
edge and acks of its second sent to N2 in its own name, numbered around where the stream is —
each would cost the sink events if taken; on an overlay without identities and operator keys
a member is trusted with the data plane, so it runs only when asked for by ``--only``) and
``captured-steps`` (the same robot coordinates moves of mid, unpinned for this attack, in its
own name: a ``Switch`` of src's edge to N3 and a ``Rewire`` of the sink's input to N1, 20 a
second: without the warrants of ``mso.protocol.warrant`` the stream stops) and
``captured-markers`` (the same robot sends mid's host markers of src's edge naming N3, as if
a move of mid to N3 had switched it, 20 a second: taken, N2 handed mid's state to N3, which
prepared nothing, and the stream stopped; now a marker is taken only for a move N2 holds a
warrant for).

``--mix S``: instead, one overlay under every attack (or those ``--only`` names) in turn,
``--attack`` seconds each, for ``S`` seconds (the issue's soak under a mix of them:
``--mix 600``); the attacked node's RSS after each turn is printed as it goes.

``--identities``: the overlay runs with node identities (``mso emulate --identities``); each
member attacker is then a captured robot holding its own certified node key (it proves its
name and signs what it sends beyond N2), the legitimate client is the operator.

Usage: .venv/bin/python bench/abuse.py [--attack 5] [--only slots,guesser] [--mix 600]
                                      [--identities] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
import tempfile
import time
import zlib
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.benchmarks.common import provenance, write_results
from mso.client import Client, overlay_key
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.protocol import messages as m
from mso.protocol import origin
from mso.protocol.clients import ClientIdentity, operator_client
from mso.protocol.framing import HELLO_BYTES, FrameCodec
from mso.protocol.identity import Identity, certify
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.failure"
DRAIN_S = 10.0
SCENARIO = """\
name: abuse3
link_defaults: {delay_ms: 0.5}
nodes:
  N1: {pos: [0, 0]}
  N2: {pos: [100, 0]}
  N3: {pos: [200, 0]}
links:
  - [N1, N2]
  - [N2, N3]
"""
APP = f"""\
name: stream
vertices:
  src:  {{code: {VERTICES}:CountingSource, pinned: N1, rate: 100, output: {VERTICES}:Seq}}
  mid:  {{code: {VERTICES}:PassThrough, pinned: N2, input: {VERTICES}:Seq, output: {VERTICES}:Seq}}
  sink: {{code: {VERTICES}:GapSink, pinned: N3, input: {VERTICES}:Seq}}
edges:
  - [src, mid]
  - [mid, sink]
"""
# ``captured-steps``: mid not pinned (the paper's split puts it on the relay N2), so that a
# move of it is a move at all: a captured robot coordinates its steps
MOVABLE = APP.replace("name: stream\n", "name: stream\nplanner: paper\n").replace(
    " pinned: N2,", ""
)
Attack = Callable[["Target", asyncio.Event], Awaitable[dict[str, Any]]]


class Target:
    """The node attacked: where it listens and the overlay key (for the member attacks); on
    an overlay with identities (``--identities``) each member attacker is a captured robot
    holding its own certified node key (certified by the run's operator key), and the
    legitimate client the operator."""

    def __init__(self, emu: Emulator, node: str) -> None:
        self.host, self.port = emu.nodes[node].host, emu.nodes[node].port
        assert emu.key is not None
        self.psk = overlay_key(emu.key)
        self.node = node
        self.operator = emu.signer if emu.identities else None
        self.ids: dict[str, Identity] = {}  # the captured robots' own keys, by name
        self.next_seq = 0  # where the stream's sink stands when the attack starts

    def frame(self, src: str, dst: str, msg: m.Message) -> bytes:
        """An envelope from ``src``, signed as its origin when it is a captured robot with a
        key and goes beyond the node attacked (a relay would otherwise refuse it)."""
        payload = m.wrap(src, dst, msg)
        ident = self.ids.get(src)
        if ident is None or dst == self.node:
            return payload
        return origin.sign(ident, payload, time.time_ns() // 1_000_000)

    def client_identity(self) -> ClientIdentity | None:
        return operator_client(self.operator) if self.operator is not None else None

    async def member(self, name: str, peer: bool = False) -> tuple[Any, Any, FrameCodec]:
        """A connection proving the key, introduced as a client (or a peer named ``name``)."""
        r, w = await asyncio.open_connection(self.host, self.port)
        codec = FrameCodec(self.psk)
        w.write(codec.hello())
        while not codec.confirmed:
            data = await asyncio.wait_for(r.read(1 << 16), 5.0)
            if not data:
                raise ConnectionError("closed in the handshake")
            w.write(codec.feed(data)[1])
        hello: m.Message = m.PeerHello(name) if peer else m.ClientHello(name)
        if peer and self.operator is not None:  # a captured robot proves its own name
            while not codec.ready:
                w.write(codec.feed(await asyncio.wait_for(r.read(1 << 16), 5.0))[1])
            private = Ed25519PrivateKey.generate()
            ident = self.ids[name] = Identity(
                private, certify(self.operator, name, private.public_key(), 1000)
            )
            cert = msgspec.msgpack.encode(ident.cert)
            hello = m.PeerHello(name, cert, ident.prove(codec.hello(), codec.peer_hello))
        w.write(codec.seal(m.wrap(name, self.node, hello)))
        return r, w, codec


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


async def until(stop: asyncio.Event, seconds: float) -> bool:
    """Wait up to ``seconds`` for ``stop``; True once it is set."""
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), seconds)
    return stop.is_set()


# -- attacks ---------------------------------------------------------------------------------
async def guesser(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    tries = answered = 0
    while not stop.is_set():
        codec = FrameCodec(os.urandom(32))  # a guess (not stretched: the oracle is the point)
        try:
            r, w = await asyncio.open_connection(t.host, t.port)
            w.write(codec.hello())
            _, confirmation = codec.feed(await asyncio.wait_for(r.readexactly(HELLO_BYTES), 5))
            w.write(confirmation)
            rest = await asyncio.wait_for(r.read(), 5.0)
            answered += len(rest) > 0  # anything keyed the node sent back: a guessing oracle
            w.close()
        except (OSError, TimeoutError, asyncio.IncompleteReadError):
            pass
        tries += 1
    return {"tries": tries, "answers_to_guess_against": answered}


async def slots(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    opened = [0]

    async def hold(source: str) -> None:
        while not stop.is_set():
            try:
                r, w = await asyncio.open_connection(t.host, t.port, local_addr=(source, 0))
            except OSError:
                await asyncio.sleep(0.01)
                continue
            opened[0] += 1
            read = asyncio.ensure_future(r.read())
            await asyncio.wait([read, asyncio.ensure_future(stop.wait())], timeout=30,
                               return_when=asyncio.FIRST_COMPLETED)  # fmt: skip
            read.cancel()
            w.close()

    sources = [f"127.0.0.{i}" for i in range(2, 6)]
    await asyncio.gather(*(hold(sources[i % 4]) for i in range(96)))  # 1.5x the pool
    return {"connections_opened": opened[0]}


async def relay_flood(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    _, w, codec = await t.member("X9", peer=True)
    sent = big = 0
    bulk = m.ChainPlaced("ghost", 0, {"k": "x" * (8 << 20)})
    while not stop.is_set():
        batch = [
            codec.seal(t.frame("X9", "N3", m.NodeDown(f"Z{sent + i}", "X9", 1))) for i in range(500)
        ]
        sent += len(batch)
        if big < 20:
            batch.append(codec.seal(t.frame("X9", "N3", bulk)))
            big += 1
        w.write(b"".join(batch))
        await w.drain()
        if await until(stop, 0.05):
            break
    w.close()
    return {"node_downs_sent": sent, "big_frames_sent": big}


async def invented_failures(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    _, w, codec = await t.member("X8", peer=True)
    sent = 0
    while not stop.is_set() and sent < 50_000:
        w.write(b"".join(
            codec.seal(m.wrap("X8", t.node, m.NodeDown(f"Y{sent + i}", "X8", 1)))
            for i in range(1000)
        ))  # fmt: skip
        sent += 1000
        await w.drain()
        await until(stop, 0.05)
    await stop.wait()
    w.close()
    return {"node_downs_sent": sent}


async def slow_clients(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    conns = [await t.member(f"slow{i}") for i in range(20)]
    asked = 0
    while not stop.is_set():
        for _, w, codec in conns:
            if not w.is_closing():
                w.write(codec.seal(m.wrap("c", t.node, m.StatusRequest(everywhere=True))))
                asked += 1
        await until(stop, 0.05)
    closed = sum(w.is_closing() or r.at_eof() for r, w, _ in conns)
    for _, w, _ in conns:
        w.close()
    return {"requests_never_read": asked, "clients_closed_by_node": closed}


async def early_messages(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    _, w, codec = await t.member("X7", peer=True)
    sent = 0
    payload = {"k": "x" * 65536}
    while not stop.is_set() and sent < 2048:  # 128 MiB offered
        w.write(b"".join(
            codec.seal(m.wrap("X7", t.node, m.ChainPlaced(f"never{sent + i}", 0, payload)))
            for i in range(64)
        ))  # fmt: skip
        sent += 64
        await w.drain()
        await until(stop, 0.05)
    await stop.wait()
    w.close()
    return {"messages_sent": sent}


async def deep_bodies(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    _, w, codec = await t.member("X6")
    enc = msgspec.msgpack.Encoder()
    head = enc.encode(["client", t.node, 32, 0, msgspec.Raw(b"\xc0")])  # a bare envelope
    frame = head[:-1] + b"\x91" * 100_000 + b"\xc0"
    sent = 0
    while not stop.is_set():
        w.write(b"".join(codec.seal(frame) for _ in range(10)))
        sent += 10
        await w.drain()
        await until(stop, 0.05)
    w.close()
    return {"frames_sent": sent}


async def big_documents(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    doc = "name: big\nvertices:\n  A: {}\nx: [" + "0," * 2_000_000 + "0]\n"
    sent = 0
    while not stop.is_set():
        client = Client(t.host, t.port, t.psk, "docs")
        try:
            await client.connect()
            await client.call(m.DeployRequest(doc), 10.0)
        except MsoError:
            pass
        finally:
            await client.close()
        sent += 1
    return {"documents_sent": sent}


async def robot_sends(
    t: Target, stop: asyncio.Event, name: str, frames: Callable[[], list[bytes]], every_s: float
) -> int:
    """A captured robot ``name``, a proven peer of the node attacked, sends what ``frames``
    makes every ``every_s`` until ``stop``; how many frames it sent."""
    _, w, codec = await t.member(name, peer=True)
    sent = 0
    while not stop.is_set():
        batch = frames()
        w.write(b"".join(codec.seal(f) for f in batch))
        sent += len(batch)
        await w.drain()
        if await until(stop, every_s):
            break
    w.close()
    return sent


async def forged_words(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    epoch = (zlib.crc32(b"N1") & 0xFFFF) + 1  # the stream's: the first app N1 deployed
    t0, junk = time.monotonic(), [b"\x00"]

    def frames() -> list[bytes]:
        seq = t.next_seq + int((time.monotonic() - t0) * 100)  # the stream's 100 events/s
        out = []
        for s in range(seq - 5, seq + 15):
            out += [
                m.wrap("N2", "N3", m.Data("stream", 1, epoch, s, junk)),  # in N2's name
                m.wrap("X4", t.node, m.Data("stream", 0, epoch, s, junk)),  # its own
                m.wrap("X4", t.node, m.Ack("stream", 1, epoch, s)),
            ]
        return out

    return {"frames_sent": await robot_sends(t, stop, "X4", frames, 0.05)}


async def captured_steps(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    """A captured robot (hosting nothing of the stream, not an end of its chain) coordinates
    moves of mid in its own name: a ``Switch`` of src's edge to N3 (N2 would hand mid's
    state to N3 at the marker, which prepared nothing) and a ``Rewire`` telling the sink
    mid runs on N1 (it would ack there), each with a fresh move id, every 0.1 s."""
    rids = iter(range(1 << 40, 1 << 41, 2))

    def frames() -> list[bytes]:
        rid = next(rids)
        return [
            t.frame("X5", "N1", m.Switch("stream", 0, "N3", rid)),
            t.frame("X5", "N3", m.Rewire("stream", 1, "N1", rid + 1, False)),
        ]

    return {"steps_sent": await robot_sends(t, stop, "X5", frames, 0.1)}


async def captured_markers(t: Target, stop: asyncio.Event) -> dict[str, Any]:
    """A captured robot (hosting nothing of the stream) sends mid's host markers of src's
    edge naming N3, each of a fresh move id and near where the stream stands, every 0.1 s."""
    rids = iter(range(1 << 40, 1 << 41))
    t0 = time.monotonic()

    def frames() -> list[bytes]:
        seq = t.next_seq + int((time.monotonic() - t0) * 100)  # the stream's 100 events/s
        return [t.frame("X5", t.node, m.Marker("stream", 0, seq, next(rids), "N3"))]

    return {"markers_sent": await robot_sends(t, stop, "X5", frames, 0.05)}


ATTACKS: dict[str, Attack] = {
    "guesser": guesser,
    "slots": slots,
    "relay-flood": relay_flood,
    "invented-failures": invented_failures,
    "slow-clients": slow_clients,
    "early-messages": early_messages,
    "deep-bodies": deep_bodies,
    "big-documents": big_documents,
    "forged-words": forged_words,
    "captured-steps": captured_steps,
    "captured-markers": captured_markers,
}
# by default only against an overlay with identities (and operator keys)
IDENTITIES_ONLY = {"forged-words", "captured-steps", "captured-markers"}
# the app an attack runs against (else APP)
APPS = {"captured-steps": MOVABLE, "captured-markers": MOVABLE}


async def mix(
    t: Target, stop: asyncio.Event, each_s: float, rss: Callable[[], int], only: list[str]
) -> dict[str, Any]:
    """Every attack in turn, ``each_s`` seconds each, over and over until ``stop``; the
    attacked node's RSS (MB) after each turn is kept (``rss_after_turn``)."""
    rounds: dict[str, int] = {}
    after: list[tuple[str, int]] = []
    while not stop.is_set():
        for name in only:
            attack = ATTACKS[name]
            if stop.is_set():
                break
            turn = asyncio.Event()
            task = asyncio.ensure_future(attack(t, turn))
            await until(stop, each_s)
            turn.set()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(task, 30.0)
            rounds[name] = rounds.get(name, 0) + 1
            after.append((name, rss()))
            print(f"turn {name}: N2 at {after[-1][1]} MB ({time.time():.1f})", flush=True)
    return {**rounds, "rss_after_turn": after}


# -- one run ---------------------------------------------------------------------------------
def _vertex(nodes: dict[str, Any], vertex: str) -> dict[str, Any]:
    for st in nodes.values():
        found = st.get("apps", {}).get("stream", {}).get("vertices", {}).get(vertex)
        if found is not None:
            return dict(found.get("stats", {}))
    return {}


async def legit(t: Target, stop: asyncio.Event, tally: dict[str, int]) -> None:
    """An operator's status request to the node every 0.2 s, each on a fresh connection."""
    while not stop.is_set():
        client = Client(t.host, t.port, t.psk, "operator", identity=t.client_identity())
        tally["asked"] += 1
        try:
            await client.connect(2.0)
            if isinstance(await client.call(m.StatusRequest(), 2.0), m.StatusReply):
                tally["answered"] += 1
        except MsoError:
            pass
        finally:
            await client.close()
        await until(stop, 0.2)


async def one(name: str, args: argparse.Namespace) -> dict[str, Any]:
    logs = tempfile.TemporaryDirectory(prefix="mso-emu-abuse-")
    emu = Emulator(
        loads_scenario(SCENARIO),
        manage=False,
        log_dir=Path(logs.name),
        identities=args.identities,
    )
    await emu.start()
    loop = asyncio.get_running_loop()
    row: dict[str, Any] = {"attack": name}
    try:
        reply = await emu.deploy(APPS.get(name, APP), "stream.yaml", "N1")
        assert reply.ok, reply.error
        await asyncio.sleep(args.steady)  # the stream flows
        target = Target(emu, "N2")
        target.next_seq = int(_vertex(await emu.status(timeout=5.0), "sink").get("next", 0))
        pids = {n: node.process.pid for n, node in emu.nodes.items() if node.process}
        row["rss_before_mb"] = {n: rss_kb(p) // 1024 for n, p in pids.items()}
        peak = dict(row["rss_before_mb"])
        stop, tally = asyncio.Event(), {"asked": 0, "answered": 0}
        if name == "mix":
            pid = pids["N2"]
            attack = asyncio.ensure_future(
                mix(target, stop, args.attack, lambda: rss_kb(pid) // 1024, args.turns)
            )
            t_end = loop.time() + args.mix
        else:
            attack = asyncio.ensure_future(ATTACKS[name](target, stop))
            t_end = loop.time() + args.attack
        operator = asyncio.ensure_future(legit(target, stop, tally))
        while loop.time() < t_end and not attack.done():
            for n, p in pids.items():
                peak[n] = max(peak[n], rss_kb(p) // 1024)
            await asyncio.sleep(0.25)  # sampling RSS
        stop.set()
        ended = loop.time()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(operator, 10.0)
        try:
            row["attacker"] = await asyncio.wait_for(attack, 30.0)
        except Exception as exc:  # the attacker's own failure is a figure, not a crash
            row["attacker"] = {"error": f"{type(exc).__name__}: {exc}"}
        row["rss_peak_mb"] = peak
        row["legit"] = dict(tally)
        # recovery: a status answered and an event numbered after the end at the sink
        at_end = None
        recovered = None
        while loop.time() < ended + 30.0:
            try:
                nodes = await emu.status(timeout=2.0)
            except MsoError:
                nodes = {}
            src, sink = _vertex(nodes, "src"), _vertex(nodes, "sink")
            if at_end is None and src:
                at_end = int(src.get("sent", 0))
            if "N2" in nodes and at_end is not None and int(sink.get("next", 0)) > at_end:
                recovered = loop.time() - ended
                break
            await asyncio.sleep(0.05)  # polling: the sink has no event to wait on
        row["recovery_s"] = round(recovered, 2) if recovered is not None else None
        await asyncio.sleep(max(0.0, ended + args.after - loop.time()))
        row["rss_after_mb"] = {n: rss_kb(p) // 1024 for n, p in pids.items()}
        deadline = loop.time() + DRAIN_S
        while True:  # the sink catches up with the source (or the drain bound passes)
            nodes = await emu.status(timeout=5.0)
            src, sink = _vertex(nodes, "src"), _vertex(nodes, "sink")
            sent = int(src.get("sent", 0))
            if int(sink.get("next", 0)) >= sent - 100 or loop.time() > deadline:
                break
            await asyncio.sleep(0.2)
        n2 = nodes.get("N2", {})
        row.update(
            sent=sent,
            received=int(sink.get("count", 0)),
            lost=int(sink.get("missing", 0)) + max(0, sent - int(sink.get("next", 0)) - 100),
            duplicated=int(sink.get("repeats", 0)),
            reordered=int(sink.get("out_of_order", 0)),
            failed_nodes=sorted({f for st in nodes.values() for f in st.get("failed_nodes", [])}),
            n2_connections=n2.get("connections", {}),
            n2_traffic={k: v for k, v in n2.get("traffic", {}).items() if k.startswith("frames")},
            n2_refusals=n2.get("refusals", {}),
        )
        return row
    finally:
        await emu.stop()
        logs.cleanup()


def table(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    lines = [
        (
            f"Every attack in turn, {args.attack:g} s each, for {args.mix:g} s"
            if args.mix
            else f"Attack {args.attack:g} s"
        )
        + " against N2 (the relay of a 100 events/s stream N1 -> N2 -> "
        "N3); RSS in MB (N1/N2/N3); legit = status requests to N2 answered during the attack; "
        "recovery from the attack's end to a status answered and a newer event at the sink; "
        "lost/dup/reord over the whole run (the last second's events in flight not counted)."
        + (
            " With node identities (--identities): each member attacker a captured robot with "
            "its own certified key, the legitimate client the operator."
            if args.identities
            else ""
        ),
        "",
        "| attack | RSS before | RSS peak | RSS after | lost | dup | reord | legit answered "
        "| recovery s | failed nodes | attacker |",
        "|---|---|---|---|---:|---:|---:|---|---:|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['attack']} | error: {r['error']} |")
            continue

        def mb(d: dict[str, int]) -> str:
            return "/".join(str(d[n]) for n in sorted(d))

        legit = r["legit"]
        share = 100 * legit["answered"] / max(1, legit["asked"])
        attacker = ", ".join(f"{k} {v}" for k, v in r["attacker"].items() if k != "rss_after_turn")
        lines.append(
            f"| {r['attack']} | {mb(r['rss_before_mb'])} | {mb(r['rss_peak_mb'])} "
            f"| {mb(r['rss_after_mb'])} | {r['lost']} | {r['duplicated']} | {r['reordered']} "
            f"| {legit['answered']}/{legit['asked']} ({share:.0f}%) | {r['recovery_s']} "
            f"| {', '.join(r['failed_nodes']) or '-'} | {attacker} |"
        )
    return "\n".join(lines) + "\n"


async def main_async(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    for name in args.only:
        t = time.monotonic()
        try:
            row = await asyncio.wait_for(one(name, args), max(args.attack, args.mix) + 120)
        except Exception as exc:  # one attack's failure is reported, the others still run
            row = {"attack": name, "error": f"{type(exc).__name__}: {exc}"}
        row["seconds"] = round(time.monotonic() - t, 1)
        print(row, file=sys.stderr)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--attack", type=float, default=5.0, help="seconds each attack lasts")
    ap.add_argument("--steady", type=float, default=2.0)
    ap.add_argument("--after", type=float, default=3.0)
    ap.add_argument("--only", default="")
    ap.add_argument(
        "--mix",
        type=float,
        default=0.0,
        help="instead: one overlay under every attack in turn (--attack s each) for this long",
    )
    ap.add_argument(
        "--identities",
        action="store_true",
        help="the overlay runs with node identities (mso emulate --identities)",
    )
    ap.add_argument("--json", type=Path, default=None, help="(default: results/abuse.json, "
                    "or results/abuse-identities.json with --identities)")  # fmt: skip
    args = ap.parse_args(argv)
    if args.json is None:
        args.json = RESULTS / ("abuse-identities.json" if args.identities else "abuse.json")
    args.only = [a for a in args.only.split(",") if a] or [
        a for a in ATTACKS if args.identities or a not in IDENTITIES_ONLY
    ]
    unknown = [a for a in args.only if a not in ATTACKS]
    if unknown or not 0.5 <= args.attack <= 600 or not 0 <= args.mix <= 3600:
        ap.error(f"--only: one of {', '.join(ATTACKS)}; --attack: 0.5..600 s; --mix: 0..3600 s")
    if args.mix:  # the attacks --only names, in turn
        args.turns, args.only = args.only, ["mix"]
    t0 = time.monotonic()
    rows = asyncio.run(main_async(args))
    result = {"benchmark": "abuse", "attacks": rows, "seconds": time.monotonic() - t0}
    result |= provenance()
    write_results(args.json, result, table(rows, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
