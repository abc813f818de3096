"""Chain replication's added latency on the convoy, measured so that the machine's noise cancels.

Runs of the convoy one after the other (``bench/replication.py --emulate-s``) differ by the
load of their moment far more than by replication: ten alternated pairs of 30 s left the added
p50 between -15.6 % and +32 %. Here both settings run **at the same time in the same
processes**: two copies of the convoy on the user-space emulator's 4-robot line, one with
``replicas: 0`` on every vertex and one with the default (1 for each vertex with state), each
logging into its own database. The same events (the same generated world and rates), the same
node processes, loops and links, the same moments: what differs is replication (its snapshots,
their alignment at a merge, the replica's acks and the producer's retention). Which copy is
deployed first alternates between runs (its sources start a few ms earlier).

What replication costs the shared loops (its snapshot frames, ~8.6 KB/s) delays both copies
alike, so it is not in the difference; the CPU time the node processes spend is read per run
too (the same copies with replication off on both: ``--control``, a run of two copies with
replicas 0 each, gives that figure's baseline).

Per run: each copy's rows after a warm-up (the storage log's ``stored_at - stamp``: sources to
the trailing robot's log), the p50/p99 of each. Pooled over runs, the ratio of the p50s and a
95 % interval by resampling time blocks of ``BLOCK_S`` (each block holds both copies' rows of
the same seconds, so a block's load is shared; resampled within each deploy order): the
<= 10 % target is met if the interval's upper end is at most +10 %, not met if its lower end
is above.

Usage: .venv/bin/python bench/replication_pairs.py [--runs 6] [--seconds 40] [--control]
                                                  [--json FILE]
Writes bench/results/replication_pairs.json and replication_pairs.md.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import re
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.emu.controller import Emulator
from mso.scenario.format import load_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
EXAMPLES = HERE.parent / "src" / "mso" / "examples"
WARM_S = 8.0  # imports, first snapshots, placement settled (a first run at 5 s: +67 %)
BLOCK_S = 5.0  # resampled unit: both copies' rows of the same seconds
BOOT = 4000


def copy_doc(name: str, replicas_zero: bool, db: Path) -> str:
    """The convoy as app ``name``, logging into ``db``; ``replicas_zero``: no replicas."""
    doc = (EXAMPLES / "convoy.yaml").read_text(encoding="utf-8")
    doc = doc.replace("\nname: convoy\n", f"\nname: {name}\n", 1)
    if replicas_zero:  # every vertex with state: no replica (as bench/replication.py)
        doc = re.sub(r"(\n  \w+: +\{code: mso\.examples\.convoy:\w+,)", r"\1 replicas: 0,", doc)
        doc = doc.replace("replicas: 0, pinned: N1, rate", "pinned: N1, rate")  # (sources)
    storage = "code: mso.examples.convoy:Storage,"
    if storage not in doc or f"name: {name}" not in doc:
        raise RuntimeError("examples/convoy.yaml changed: the benchmark cannot make its copies")
    return doc.replace(storage, f"{storage} params: {{db: '{db}'}},", 1)


def rows(db: Path, since: float) -> list[tuple[float, float]]:
    """``(stamp, delay ms)`` of each row stamped from ``since`` on."""
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [
            (r[1], (r[0] - r[1]) * 1e3)
            for table in ("trajectory", "targets")
            for r in conn.execute(
                f"SELECT stored_at, stamp FROM {table} WHERE stamp >= ?", (since,)
            )
        ]
    finally:
        conn.close()


def pct(xs: list[float], p: float) -> float:
    if not xs:
        return float("nan")
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, round(p / 100 * (len(s) - 1))))]


def cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds of the node processes so far (/proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])
    return total / tick


def one_run(k: int, seconds: float, tmp: Path, control: bool) -> dict[str, Any]:
    """Both copies side by side for ``seconds`` after the warm-up; run ``k`` deploys the
    replicated copy first when odd."""
    copies = {"r0": True, "rep": control}  # name -> replicas_zero
    dbs = {name: tmp / f"run{k}-{name}.sqlite" for name in copies}
    order = list(copies) if k % 2 == 0 else list(reversed(copies))

    async def run() -> dict[str, Any]:
        emu = Emulator(load_scenario(EXAMPLES / "convoy-line.yaml"))
        await emu.start()
        try:
            for name in order:
                app = f"convoy_{name}"
                reply = await emu.deploy(copy_doc(app, copies[name], dbs[name]), "c.yaml", "N1")
                if not reply.ok:
                    raise RuntimeError(f"{app}: deployment failed: {reply.error}")
            await asyncio.sleep(WARM_S)
            pids = [n.process.pid for n in emu.nodes.values() if n.process is not None]
            t0, c0 = time.monotonic(), cpu_s(pids)
            await asyncio.sleep(seconds)
            st = await emu.status()
            c1 = cpu_s(pids)
            placement = {
                name: {
                    v: n
                    for n, s in sorted(st.items())
                    for v in s["apps"].get(f"convoy_{name}", {}).get("vertices", {})
                }
                for name in copies
            }
            cost = {
                name: sum(
                    r["bytes_per_s"]
                    for s in st.values()
                    for r in s["apps"].get(f"convoy_{name}", {}).get("replication", {}).values()
                )
                for name in copies
            }
            return {"t0": t0, "cpu_s_per_s": (c1 - c0) / seconds, "placement": placement,
                    "snapshot_bytes_per_s": cost}  # fmt: skip
        finally:
            await emu.stop()

    out = asyncio.run(run())
    got = {name: rows(dbs[name], out["t0"]) for name in copies}
    same = out["placement"]["r0"] == out["placement"]["rep"]
    delays = {n: [(round(t - out["t0"], 4), round(d, 3)) for t, d in r] for n, r in got.items()}
    return {
        "first": order[0],
        "same_placement": same,
        "placement": out["placement"],
        "cpu_s_per_s": round(out["cpu_s_per_s"], 4),
        "snapshot_bytes_per_s": {n: round(b, 1) for n, b in out["snapshot_bytes_per_s"].items()},
        "t0": out["t0"],
        "rows": {n: len(r) for n, r in got.items()},
        "p50_ms": {n: round(pct([d for _, d in r], 50), 3) for n, r in got.items()},
        "p99_ms": {n: round(pct([d for _, d in r], 99), 3) for n, r in got.items()},
        "delays": delays,
    }


def pooled(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The pooled p50/p99 of each copy and the 95 % interval of the p50 ratio, resampling
    time blocks (both copies' rows of the same BLOCK_S seconds of one run) with replacement."""
    blocks: dict[tuple[int, int], dict[str, list[float]]] = {}
    for i, r in enumerate(runs):
        for name, ds in r["delays"].items():
            for t, d in ds:
                blocks.setdefault((i, int(t // BLOCK_S)), {"r0": [], "rep": []})[name].append(d)
    keys = [k for k, b in blocks.items() if b["r0"] and b["rep"]]
    if not keys:
        return {}
    # resampled within each deploy order (the copy deployed first may differ by its few ms
    # ahead; the orders alternate, and each keeps its share of the blocks)
    strata = [[k for k in keys if runs[k[0]]["first"] == first] for first in ("r0", "rep")]

    def p(ks: list[tuple[int, int]], name: str, q: float) -> float:
        return pct([d for k in ks for d in blocks[k][name]], q)

    rng = random.Random(1)
    ratios = sorted(
        p(s, "rep", 50) / p(s, "r0", 50)
        for s in ([rng.choice(st) for st in strata for _ in st] for _ in range(BOOT))
    )
    p50 = (p(keys, "r0", 50), p(keys, "rep", 50))
    p99 = (p(keys, "r0", 99), p(keys, "rep", 99))
    lo, hi = ratios[int(0.025 * BOOT)], ratios[int(0.975 * BOOT) - 1]
    return {
        "blocks": len(keys),
        "p50_ms": [round(x, 3) for x in p50],
        "p99_ms": [round(x, 3) for x in p99],
        "added_p50_pct": round((p50[1] / p50[0] - 1) * 100, 2),
        "added_p99_pct": round((p99[1] / p99[0] - 1) * 100, 2),
        "added_p50_ci95_pct": [round((lo - 1) * 100, 2), round((hi - 1) * 100, 2)],
        "runs_rep_no_slower": sum(r["p50_ms"]["rep"] <= r["p50_ms"]["r0"] for r in runs),
    }


def verdict(lo: float, hi: float) -> str:
    return "met" if hi <= 10 else "not met" if lo > 10 else "neither met nor contradicted"


def render(result: dict[str, Any]) -> str:
    second = "replicas 0 as well (control)" if result["control"] else "the default replicas"
    lines = [
        f"### Replication's added latency, both settings side by side (the convoy twice on "
        f"the emulator's 4-robot line, {result['seconds']:g} s a run after {WARM_S:g} s)",
        "",
        f"One copy with replicas 0 (`r0`), one with {second} (`rep`), in the same node "
        "processes at the same time.",
        "",
        "| run | first deployed | same placement | rows r0 / rep | p50 ms r0 / rep | "
        "p99 ms r0 / rep | CPU s/s (4 nodes) | snapshot B/s rep |",
        "|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    for i, r in enumerate(result["runs"]):
        lines.append(
            f"| {i} | {r['first']} | {'yes' if r['same_placement'] else 'no'} | "
            f"{r['rows']['r0']} / {r['rows']['rep']} | {r['p50_ms']['r0']} / "
            f"{r['p50_ms']['rep']} | {r['p99_ms']['r0']} / {r['p99_ms']['rep']} | "
            f"{r['cpu_s_per_s']} | {r['snapshot_bytes_per_s']['rep']} |"
        )
    p = result["pooled"]
    if p:
        lo, hi = p["added_p50_ci95_pct"]
        lines += [
            "",
            f"Pooled ({p['blocks']} blocks of {BLOCK_S:g} s): p50 {p['p50_ms'][0]} -> "
            f"{p['p50_ms'][1]} ms ({p['added_p50_pct']:+.1f} %, 95 % interval {lo:+.1f} .. "
            f"{hi:+.1f} % over the blocks resampled), p99 {p['p99_ms'][0]} -> {p['p99_ms'][1]} "
            f"ms ({p['added_p99_pct']:+.1f} %); `rep` no slower in {p['runs_rep_no_slower']} "
            f"of {len(result['runs'])} runs. The <= 10 % p50 target: {verdict(lo, hi)}.",
        ]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--control", action="store_true", help="both copies with replicas 0")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not (1 <= args.runs <= 40 and 10 <= args.seconds <= 600):
        ap.error("--runs 1..40, --seconds 10..600")
    out: Path = args.json or RESULTS / "replication_pairs.json"
    started = time.monotonic()
    runs = []
    with tempfile.TemporaryDirectory(prefix="mso-bench-pairs-") as tmp:
        for k in range(args.runs):
            runs.append(one_run(k, args.seconds, Path(tmp), args.control))
            r = runs[-1]
            print(f"run {k}: p50 {r['p50_ms']} p99 {r['p99_ms']} rows {r['rows']}", file=sys.stderr)
    result: dict[str, Any] = {
        "benchmark": "replication_pairs",
        "seconds": args.seconds,
        "control": args.control,
        "runs": runs,
        "pooled": pooled(runs),
        "elapsed_s": round(time.monotonic() - started, 1),
    } | provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
