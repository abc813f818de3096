"""End-to-end origin (issue 27, Build 2): what signing every control frame a node originates
costs, and what checking one costs at its destination (``mso.protocol.origin``).

In this process, no network: CPU per signature (``origin.sign``: the envelope decoded, signed
with the node's Ed25519 key, re-encoded), per check at the destination (``Verifier.check``
with the originator's certificate already verified once, and the first time, when the
operator's signature on the certificate is checked too), and the bytes an origin adds to a
frame. The cost per failure: one failure costs ``CLAIMS_PER_FAILURE`` control messages
overlay-wide (``bench/membership.py``: 45 at 25, 100 and 400 nodes), each signed once by its
sender and checked at most once, by its receiver.

Usage: .venv/bin/python bench/origin.py [--n 2000] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.benchmarks.common import per_call_us, provenance, write_results
from mso.protocol import messages as m
from mso.protocol import origin
from mso.protocol.authority import Signer
from mso.protocol.identity import Identity, certify

HERE = Path(__file__).resolve().parent
CLAIMS_PER_FAILURE = 45


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="calls measured per figure")
    ap.add_argument("--json", type=Path, default=HERE / "results" / "origin.json")
    args = ap.parse_args(argv)
    if not 10 <= args.n <= 1_000_000:
        ap.error("--n: 10..1000000")
    t0 = time.monotonic()
    operator = Signer()
    private = Ed25519PrivateKey.generate()
    me = Identity(private, certify(operator, "N17", private.public_key(), 1000))
    ops = {operator.id: operator.public}
    rows = []
    for name, msg in (
        ("NodeDown", m.NodeDown("N42", "N17", 1_764_000_000_000, "")),
        ("Moved", m.Moved("convoy", "scan_matcher", "N17", 1_764_000_000_000, 3)),
        ("HandoverEvents 4 KiB", m.HandoverEvents("convoy", "v", 1, 0, 0, [b"x" * 4096])),
    ):
        bare = m.wrap("N17", "N3", msg)
        now = time.time_ns() // 1_000_000
        signed = origin.sign(me, bare, now)
        env = m.unwrap(signed)
        warm = origin.Verifier()
        assert warm.check(env, now, ops) is None
        sign_us = per_call_us(lambda b=bare, t=now: origin.sign(me, b, t), args.n)
        check_us = per_call_us(lambda e=env, v=warm, t=now: v.check(e, t, ops), args.n)
        first_us = per_call_us(lambda e=env, t=now: origin.Verifier().check(e, t, ops), args.n // 4)
        rows.append(
            {
                "message": name,
                "bytes": len(bare),
                "bytes_signed": len(signed),
                "sign_us": round(sign_us, 1),
                "check_us": round(check_us, 1),
                "check_first_us": round(first_us, 1),
                "signs_per_s": round(1e6 / sign_us),
                "checks_per_s": round(1e6 / check_us),
            }
        )
    claim = rows[0]
    per_failure_ms = CLAIMS_PER_FAILURE * (claim["sign_us"] + claim["check_us"]) / 1000
    lines = [
        "One process, no network: CPU µs (median of 5 batches) to sign a frame this node "
        "originates and to check it at its destination (the originator's certificate known; "
        "first: its operator signature checked too); bytes before and after.",
        "",
        "| message | bytes | signed | sign µs | check µs | first check µs | signs/s | checks/s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['message']} | {r['bytes']} | {r['bytes_signed']} | {r['sign_us']} | "
            f"{r['check_us']} | {r['check_first_us']} | {r['signs_per_s']:,} | "
            f"{r['checks_per_s']:,} |"
        )
    lines += [
        "",
        f"One failure ({CLAIMS_PER_FAILURE} control messages overlay-wide, "
        f"bench/membership.py): {per_failure_ms:.1f} ms of CPU in all, signed and checked.",
    ]
    result = {
        "benchmark": "origin",
        "rows": rows,
        "per_failure_cpu_ms": round(per_failure_ms, 2),
        "seconds": round(time.monotonic() - t0, 1),
        **provenance(),
    }
    write_results(args.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
