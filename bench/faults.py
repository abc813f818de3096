"""Seeded fault schedules in virtual time: thousands of random worlds, invariants checked.

Each seed draws a connected topology (line, mesh or random geometric, 3-8 nodes), an app (a
pipeline, a merge of two sources or a fork to two sinks) and a schedule of crashes and restarts,
partitions and heals, link flaps, message loss and requested relocations and remaps
(``mso.sim.faults``); everything heals, a quiet period follows and ``mso.sim.invariants`` checks
every vertex hosted once, no dangling edge, nothing lost / duplicated / reordered that no
failure explains, every node answering status, the flow following the sources. A failing seed
replays exactly: ``.venv/bin/python -c "from mso.sim import faults; print(faults.run(SEED))"``.

Usage: .venv/bin/python bench/faults.py [--seeds 5000] [--first 0] [--jobs N]
                                        [--faults-s 3] [--quiet-s 4] [--json FILE]
                                        [--no-restarts] [--planner paper|bytes]
                                        [--control-loss P]
(daemon restarts are drawn too, alone or while cut off; ``--no-restarts`` draws the schedules of
the runs before the ninth stop, docs/benchmarks.md. ``--planner``: how the apps' chains are
split, the paper's by default as the committed runs were, or the default bytes split.
``--control-loss P``: a study beside the committed runs, each control frame lost with
probability P, as one that waited out its route wait is; the schedules stay the seeds'.)
Writes bench/results/faults.json and faults.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.sim import faults

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
CHUNK = 50


def run_chunk(args: tuple[int, int, float, float, bool, str, float]) -> list[dict[str, Any]]:
    first, count, faults_s, quiet_s, restarts, planner, control_loss = args
    cfg = faults.Settings(
        start_s=1.0,
        faults_s=faults_s,
        quiet_s=quiet_s,
        rate=10.0,
        restarts=restarts,
        planner=planner,
        control_loss=control_loss,
    )
    rows = []
    for seed in range(first, first + count):
        try:
            r = faults.run(seed, cfg)
            rows.append(
                {
                    "seed": seed,
                    "topology": r.topology,
                    "nodes": r.nodes,
                    "faults": dict(r.faults),
                    "violations": [[v.invariant, v.detail] for v in r.violations],
                    "digest": r.digest,
                    "repeats": r.repeats,
                }
            )
        except Exception as exc:  # a crash of the simulation itself is a finding too
            rows.append(
                {
                    "seed": seed,
                    "faults": {},
                    "violations": [["exception", f"{type(exc).__name__}: {exc}"]],
                }
            )
    return rows


def render(result: dict[str, Any]) -> str:
    s = result["summary"]
    lines = [
        f"### Seeded fault schedules: {s['seeds']:,} seeds from {result.get('first', 0):,} in "
        f"{result['seconds']:.0f} s ({result['jobs']} processes; faults over "
        f"{result['faults_s']:g} s, then {result['quiet_s']:g} s quiet, virtual time; daemon "
        f"restarts {'on' if result['restarts'] else 'off'}; the {result['planner']} planner"
        + (
            f"; control frames lost with probability {result['control_loss']:g}"
            if result.get("control_loss")
            else ""
        )
        + ")",
        "",
        "| faults injected | count |",
        "|---|---:|",
        *[f"| {k} | {v:,} |" for k, v in s["faults"].items()],
        "",
        f"Seeds with a violation: {len(s['failing_seeds']):,} of {s['seeds']:,}.",
        "",
        f"Events a sink got again in a new instance (after its own node's crash or reset: "
        f"what it processed but had not acknowledged, allowed): {s['repeats']:,}, in "
        f"{s['seeds_with_repeats']:,} seeds.",
        "",
    ]
    if s["violations"]:
        lines += [
            "| invariant violated | violations | seeds |",
            "|---|---:|---:|",
            *[
                f"| {k} | {v:,} | {s['seeds_by_invariant'][k]:,} |"
                for k, v in s["violations"].items()
            ],
            "",
        ]
    if s["failing_seeds"]:
        lines.append(
            "First failing seeds (replay with `faults.run(seed, Settings(start_s=1, "
            f"faults_s={result['faults_s']:g}, quiet_s={result['quiet_s']:g}, rate=10, "
            f"restarts={result['restarts']}, planner={result['planner']!r}"
            + (f", control_loss={result['control_loss']:g}" if result.get("control_loss") else "")
            + "))`): "
            + ", ".join(f"{seed} ({', '.join(inv)})" for seed, inv in s["failing_seeds"][:15])
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5000)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--faults-s", type=float, default=3.0)
    ap.add_argument("--quiet-s", type=float, default=4.0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--restarts",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="daemon restarts too (kind restart; --no-restarts: the schedules before them)",
    )
    ap.add_argument(
        "--planner", choices=["paper", "bytes"], default="paper", help="the apps' planner:"
    )
    ap.add_argument(
        "--control-loss",
        type=float,
        default=0.0,
        help="each control frame lost with this probability (a study; default 0)",
    )
    args = ap.parse_args()
    if not 0 <= args.control_loss < 1:
        ap.error("--control-loss must be in [0, 1)")
    if args.seeds < 1 or args.jobs < 1 or args.faults_s <= 0 or args.quiet_s <= 0:
        ap.error("--seeds, --jobs, --faults-s and --quiet-s must be positive")
    out: Path = args.json or RESULTS / "faults.json"
    started = time.monotonic()
    chunks = [
        (
            first,
            min(CHUNK, args.first + args.seeds - first),
            args.faults_s,
            args.quiet_s,
            args.restarts,
            args.planner,
            args.control_loss,
        )
        for first in range(args.first, args.first + args.seeds, CHUNK)
    ]
    rows: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for part in pool.map(run_chunk, chunks):
            rows += part
            bad = sum(1 for r in rows if r["violations"])
            new = ", ".join(str(r["seed"]) for r in part if r["violations"])
            print(
                f"{len(rows)} seeds, {bad} with violations" + (f" (new: {new})" if new else ""),
                file=sys.stderr,
            )
    injected: Counter[str] = Counter()
    by_inv: Counter[str] = Counter()
    seeds_by_inv: Counter[str] = Counter()
    failing = []
    for r in rows:
        injected.update(r["faults"])
        kinds = sorted({k for k, _ in r["violations"]})
        by_inv.update(k for k, _ in r["violations"])
        seeds_by_inv.update(kinds)
        if kinds:
            failing.append([r["seed"], kinds])
    result: dict[str, Any] = {
        "benchmark": "faults",
        "jobs": args.jobs,
        "faults_s": args.faults_s,
        "quiet_s": args.quiet_s,
        "first": args.first,
        "restarts": args.restarts,
        "planner": args.planner,
        "control_loss": args.control_loss,
        "summary": {
            "seeds": len(rows),
            "faults": dict(sorted(injected.items())),
            "violations": dict(sorted(by_inv.items())),
            "seeds_by_invariant": dict(sorted(seeds_by_inv.items())),
            "failing_seeds": failing,
            "repeats": sum(r["repeats"] for r in rows),
            "seeds_with_repeats": sum(1 for r in rows if r["repeats"]),
        },
        "failing": [r for r in rows if r["violations"]],
        "seconds": time.monotonic() - started,
    } | provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
