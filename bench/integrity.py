"""End-to-end integrity of an app's data (issue 27, round three): what it would cost to have
a relay unable to alter or inject the events of an app it carries but takes no part in.

Data frames (``Data``, ``Ack``) are authenticated hop by hop only (the link's keyed tag,
:mod:`mso.protocol.framing`), so a captured relay can alter them. Two ways to close it, each
measured per data frame in this process (no network), against what a frame costs a node
today at each hop (sealed by the sender's link and opened by the receiver's):

- a per-app key held by the nodes that host part of the app: a keyed blake2b tag (16 bytes)
  written by the producer's node and checked by the consumer's — a relay that hosts nothing
  of the app cannot forge it, a host of the app can (it holds the key);
- the producer's node signs each frame with its node key (Ed25519, as control frames'
  origins are): no other node can forge it, whatever it hosts.

Built (round four, :mod:`mso.protocol.dataseal`): a tag by the *pair's* key (X25519 between
the two nodes' certified keys), so neither a relay nor a third host can forge it. Measured
here as built: the source's transport writes it (``Trust.seal``: unwrap, tag, rewrap) and the
destination's checks it (``Trust.origin`` on a frame a relay handed over); and over TCP, the
line N1 - N2 - N3 with node identities in this process, ``--frames`` data frames of 1 KiB
from N1 to N3 through N2, the process's CPU per frame with the tags on and off.

Usage: .venv/bin/python bench/integrity.py [--n 5000] [--frames 3000] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import os
import sys
import time
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.benchmarks.common import per_call_us, provenance, write_results
from mso.client import overlay_key
from mso.net.base import Counters
from mso.net.limits import ConnectionCounters, Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.net.trust import Trust
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer
from mso.protocol.framing import FrameCodec
from mso.protocol.identity import Identity, certify

HERE = Path(__file__).resolve().parent
SHAPES = (  # events per frame x bytes per event: a scan, a pose stream, an image
    ("10 x 64 B", 10, 64),
    ("1 x 1 KiB", 1, 1024),
    ("1 x 16 KiB", 1, 16384),
)


def link_pair() -> tuple[FrameCodec, FrameCodec]:
    """Two ends of a link whose handshake is done (the key from a passphrase: no matter)."""
    key = hashlib.blake2b(b"bench", digest_size=32).digest()
    a, b = FrameCodec(key), FrameCodec(key, responder=True)
    _, flush = b.feed(a.hello())
    _, back = a.feed(b.hello() + flush)
    b.feed(back)
    return a, b


OPERATOR = Signer()


def trusts() -> tuple[Trust, Trust]:
    """N1's and N4's trust, each knowing the other's certificate (as after a link or hello)."""
    out = []
    for n in ("N1", "N4"):
        private = Ed25519PrivateKey.generate()
        ident = Identity(private, certify(OPERATOR, n, private.public_key(), 1000))
        auth = Authority.configure([OPERATOR.public_text()])
        out.append(Trust(ident, auth, Counters(), ConnectionCounters()))
    n1, n4 = out
    assert n1.identity is not None and n4.identity is not None
    n1.origins.learn(n4.identity.cert)
    n4.origins.learn(n1.identity.cert)
    return n1, n4


async def _line(frames: int, tags: bool) -> float:
    """CPU µs per 1 KiB data frame N1 -> N2 -> N3 over TCP, all three in this process."""
    names = ("N1", "N2", "N3")
    ids = {}
    for n in names:
        private = Ed25519PrivateKey.generate()
        ids[n] = Identity(private, certify(OPERATOR, n, private.public_key(), 1000))
    views = {n: EmulatorRoutes(n) for n in names}
    key = overlay_key("bench")
    nets = {
        n: TcpTransport(
            n, "127.0.0.1", 0, key, views[n], Limits(),
            Authority.configure([OPERATOR.public_text()]), identity=ids[n],
        )
        for n in names
    }  # fmt: skip
    got = 0
    done = asyncio.Event()

    def receive(src: str, msg: m.Message) -> None:
        nonlocal got
        if isinstance(msg, m.Data):
            got += 1
            if got == frames:
                done.set()

    nets["N3"].set_receiver(receive)
    for n in names:
        await nets[n].start()
    try:

        def spec(n: str) -> list[object]:
            return ["127.0.0.1", nets[n].port, None, 0.0, 0.0]

        views["N1"].apply(m.LinkState(1, {"N2": spec("N2")}, {"N2": ["N2", 1], "N3": ["N2", 2]}))
        views["N2"].apply(
            m.LinkState(1, {"N1": spec("N1"), "N3": spec("N3")}, {"N1": ["N1", 1], "N3": ["N3", 1]})
        )
        views["N3"].apply(m.LinkState(1, {"N2": spec("N2")}, {"N2": ["N2", 1], "N1": ["N2", 2]}))
        for a, b in (("N1", "N3"), ("N3", "N1")):  # as after their hellos
            nets[a].trust.origins.learn(ids[b].cert)
        if not tags:
            for n in names:
                nets[n].trust.pairs = None
                nets[n].trust._data_refused = lambda peer, env: None  # type: ignore[method-assign]
        event = os.urandom(1024)
        t = time.process_time()
        for seq in range(frames):
            nets["N1"].send("N3", m.wrap("N1", "N3", m.Data("bench", 0, 1, seq, [event])), m.DATA)
            if seq % 100 == 99:
                await asyncio.sleep(0)  # let the loop carry them (its queues are bounded)
        await asyncio.wait_for(done.wait(), 120.0)
        return (time.process_time() - t) / frames * 1e6
    finally:
        for n in names:
            await nets[n].close()


def line(frames: int) -> dict[str, float]:
    """The line's CPU per frame with the tags off and on (best of three each, alternated)."""
    off, on = [], []
    for _ in range(3):
        off.append(asyncio.run(_line(frames, tags=False)))
        on.append(asyncio.run(_line(frames, tags=True)))
    return {"off_us": round(min(off), 1), "on_us": round(min(on), 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5000, help="calls measured per figure")
    ap.add_argument("--frames", type=int, default=3000, help="frames sent along the TCP line")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "integrity.json")
    args = ap.parse_args(argv)
    if not 10 <= args.n <= 1_000_000:
        ap.error("--n: 10..1000000")
    if not 100 <= args.frames <= 100_000:
        ap.error("--frames: 100..100000")
    n1, n4 = trusts()
    t0 = time.monotonic()
    app_key = os.urandom(32)
    node_key = Ed25519PrivateKey.generate()
    public = node_key.public_key()
    a, b = link_pair()
    rows = []
    for name, count, size in SHAPES:
        frame = m.wrap("N1", "N4", m.Data("convoy", 3, 1, 1000, [os.urandom(size)] * count))

        def hop(f: bytes = frame) -> None:
            b.feed(a.seal(f))

        def tag(f: bytes = frame) -> None:
            t = hashlib.blake2b(f, key=app_key, digest_size=16).digest()
            assert hashlib.blake2b(f, key=app_key, digest_size=16).digest() == t

        def sign(f: bytes = frame) -> None:
            public.verify(node_key.sign(f), f)

        def built(f: bytes = frame) -> None:  # the source seals, the destination checks
            env = m.unwrap(n1.seal("N4", f))
            assert n4._data_refused("N2", env) is None

        hop_us, tag_us, sign_us, built_us = (
            per_call_us(fn, args.n) for fn in (hop, tag, sign, built)
        )
        rows.append(
            {
                "frame": name,
                "bytes": len(frame),
                "link_hop_us": round(hop_us, 1),
                "app_key_tag_us": round(tag_us, 1),
                "app_key_added_bytes": 16,
                "node_signature_us": round(sign_us, 1),
                "node_signature_added_bytes": 64,
                "tag_vs_hop": round(tag_us / hop_us, 2),
                "signature_vs_hop": round(sign_us / hop_us, 2),
                "signed_frames_per_s": round(1e6 / sign_us),
                "pair_tag_built_us": round(built_us, 1),
                "pair_tag_vs_hop": round(built_us / hop_us, 2),
            }
        )
    tcp = line(args.frames)
    lines = [
        "One process, no network: CPU µs (median of 5 batches) per data frame — one link hop "
        "today (sealed and opened with the link's tag), and what end-to-end integrity would "
        "add once per frame (written at the producer's node and checked at the consumer's): "
        "a per-app key's blake2b tag, or an Ed25519 signature by the producer's node; and the "
        "pair tag as built (mso.protocol.dataseal: the source's transport unwraps, tags and "
        "rewraps the frame, the destination's checks it).",
        "",
        "| frame | bytes | link hop µs | app-key tag µs (x hop) | node signature µs (x hop) "
        "| signed frames/s per core | pair tag as built µs (x hop) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['frame']} | {r['bytes']} | {r['link_hop_us']} | {r['app_key_tag_us']} "
            f"({r['tag_vs_hop']}x) | {r['node_signature_us']} ({r['signature_vs_hop']}x) | "
            f"{r['signed_frames_per_s']:,} | {r['pair_tag_built_us']} ({r['pair_tag_vs_hop']}x) |"
        )
    lines += [
        "",
        f"Over TCP, N1 - N2 - N3 with node identities in one process, {args.frames} data "
        "frames of 1 KiB N1 -> N3 through N2 (best of 3): CPU per frame, all three nodes, "
        f"tags off {tcp['off_us']} µs, on {tcp['on_us']} µs "
        f"({(tcp['on_us'] / tcp['off_us'] - 1) * 100:+.0f}%).",
    ]
    result = {
        "benchmark": "integrity",
        "rows": rows,
        "tcp_line_cpu_per_frame": tcp,
        "frames": args.frames,
        "seconds": round(time.monotonic() - t0, 1),
        **provenance(),
    }
    write_results(args.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
