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

Usage: .venv/bin/python bench/integrity.py [--n 5000] [--json FILE]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.benchmarks.common import per_call_us, provenance, write_results
from mso.protocol import messages as m
from mso.protocol.framing import FrameCodec

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5000, help="calls measured per figure")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "integrity.json")
    args = ap.parse_args(argv)
    if not 10 <= args.n <= 1_000_000:
        ap.error("--n: 10..1000000")
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

        hop_us, tag_us, sign_us = (per_call_us(fn, args.n) for fn in (hop, tag, sign))
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
            }
        )
    lines = [
        "One process, no network: CPU µs (median of 5 batches) per data frame — one link hop "
        "today (sealed and opened with the link's tag), and what end-to-end integrity would "
        "add once per frame (written at the producer's node and checked at the consumer's): "
        "a per-app key's blake2b tag, or an Ed25519 signature by the producer's node.",
        "",
        "| frame | bytes | link hop µs | app-key tag µs (x hop) | node signature µs (x hop) "
        "| signed frames/s per core |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['frame']} | {r['bytes']} | {r['link_hop_us']} | {r['app_key_tag_us']} "
            f"({r['tag_vs_hop']}x) | {r['node_signature_us']} ({r['signature_vs_hop']}x) | "
            f"{r['signed_frames_per_s']:,} |"
        )
    result = {
        "benchmark": "integrity",
        "rows": rows,
        "seconds": round(time.monotonic() - t0, 1),
        **provenance(),
    }
    write_results(args.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
