"""Locality of reconfiguration: control messages and nodes involved per relocation, chain remap and
global remap, against the size of the network (issue 24, item 4).

On k x k grids, one measured app of three chains near the centre plus N/20 background apps of
four vertices (``mso.benchmarks.locality``: the study and why), management rules off. Each
reconfiguration runs to quiescence and its episode is read from the simulator's census
(control messages: anything but data, acks, heartbeats and the periodic ChainDelay; nodes
involved: those that sent or were sent one; relays: those that only forwarded one). ``outside``
counts the nodes involved or relaying that are neither the app's nor on a route between two of
its nodes (target 0). Flat means within 20% of the smallest size's figure.

Usage: .venv/bin/python bench/locality.py [--sizes 5,7,10,14] [--seed 0]
Writes bench/results/locality.json and locality.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.benchmarks.locality import measure

RESULTS = Path(__file__).resolve().parent / "results"
KINDS = ("relocation", "chain remap", "global remap")


def table(rows: list[dict[str, Any]]) -> str:
    head = "| N | " + " | ".join(f"{k}: msgs / nodes / relays" for k in KINDS) + " | outside |"
    lines = [head, "|---:|" + "---:|" * len(KINDS) + "---:|"]
    for r in rows:
        steps = {s["kind"]: s for s in r["steps"]}
        cells = [
            f"{s['control_messages']} / {s['nodes_involved']} / {s['relays']}"
            + ("" if s["ok"] else " (failed)")
            for s in (steps[k] for k in KINDS)
        ]
        outside = sum(len(s["outside"]) for s in r["steps"])
        lines.append(f"| {r['nodes']} | " + " | ".join(cells) + f" | {outside} |")
    return "\n".join(lines) + "\n"


def flat(rows: list[dict[str, Any]]) -> dict[str, bool]:
    """Per kind: every size within 20% of the smallest size's control messages."""
    out = {}
    for kind in KINDS:
        steps = [next(s for s in r["steps"] if s["kind"] == kind) for r in rows]
        counts = [s["control_messages"] for s in steps]
        out[kind] = all(0.8 * counts[0] <= c <= 1.2 * counts[0] for c in counts)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", default="5,7,10,14", help="grid sides k (N = k*k), comma-separated")
    p.add_argument("--seed", type=int, default=0, help="seed of the background apps' ends")
    p.add_argument("--out", type=Path, default=RESULTS / "locality.json")
    args = p.parse_args(argv)
    try:
        sides = [int(s) for s in args.sizes.split(",") if s]
    except ValueError:
        p.error(f"--sizes: expected comma-separated integers, got {args.sizes!r}")
    if not sides or any(k < 5 or k > 40 for k in sides):
        p.error("--sizes: each grid side must be 5..40")
    started = time.perf_counter()
    rows = []
    for k in sides:
        t = time.perf_counter()
        steps = measure(k, seed=args.seed)
        took = time.perf_counter() - t
        rows.append({"nodes": k * k, "side": k, "seconds": round(took, 1),
                     "steps": [s.to_json() for s in steps]})  # fmt: skip
        print(f"  N={k * k}: {took:.1f} s", file=sys.stderr)
    result = {
        "benchmark": "locality",
        "argv": sys.argv[1:],
        "rows": rows,
        "flat_within_20pct": flat(rows),
        "seconds": time.perf_counter() - started,
        **provenance(),
    }
    write_results(args.out, result, table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
