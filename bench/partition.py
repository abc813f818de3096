"""A partition that heals: the sink's node is cut off, declared failed, then comes back.

The app ``src -> mid -> sink`` of ``bench/failure.py`` (a counting source at 200 events/s
pinned to N1, a pass-through ``mid``, a gap-timing sink pinned to N4) runs on an emulated line
N1-N2-N3-N4 (0.5 ms links), one ``mso node`` process per node, management rules off. After
1.5 s of flow the link N3-N4 goes down (``Emulator.set_link``); after ``--outage`` seconds
(default 2.0, longer than the 0.5 s failure deadline) it comes back. Figures per run:

* detection_ms: the earliest survivor's failure record for N4 minus the cut;
* rejoin_ms: the earliest survivor's rejoin record for N4 (it reset and came back as a new
  incarnation) minus the heal;
* resume_ms: the first arrival at the sink's new instance minus the heal;
* dropped: events the survivors dropped on the parked chain's edges while N4 was out
  (``dropped_parked``) -- what a partition costs by design;
* lost_after / duplicated: events emitted after the sink came back that it never got, or got
  twice (target 0), read once the sink has caught up with the source (at most 3 s).

Usage: .venv/bin/python bench/partition.py [--runs 5] [--outage 2.0] [--quick] [--json FILE]
Writes bench/results/partition.json and partition.md (``-quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from failure import app_yaml, log_lines, node_status, summary, vertex
from mso.benchmarks.common import provenance, write_results
from mso.emu.controller import Emulator
from mso.model.network import LinkSpec
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
RATE = 200.0
STEADY_S = 1.5
POLL_S = 0.05
RESUME_S = 8.0  # bound on waiting for the flow to resume after the heal
DRAIN_S = 3.0
LINE = """\
name: line4
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""
SURVIVORS = ("N1", "N2", "N3")


async def one_run(k: int, outage: float, logs: Path) -> dict[str, Any]:
    row: dict[str, Any] = {"run": k, "error": None}
    log_dir = logs / f"run-{k}"
    log_dir.mkdir()
    scenario = loads_scenario(LINE)
    emu = Emulator(scenario, log_dir=log_dir, manage=False)
    loop = asyncio.get_running_loop()
    try:
        await emu.start()
        await emu.deploy(app_yaml("N1", "N4", RATE), "partition.yaml", "N1", check=True)
        await asyncio.sleep(STEADY_S)
        before = {n: await node_status(emu, n) for n in emu.nodes}
        link = scenario.network.link("N3", "N4") or LinkSpec("N3", "N4")
        cut_t = loop.time()
        await emu.set_link("N3", "N4", False)
        await asyncio.sleep(outage)
        heal_t = loop.time()
        await emu.set_link("N3", "N4", True, link)

        stats: dict[str, Any] = {}
        deadline = heal_t + RESUME_S
        while loop.time() < deadline:
            await asyncio.sleep(POLL_S)
            st4 = await node_status(emu, "N4")
            stats = vertex(st4, "sink").get("stats", {})
            if st4["incarnation"] != before["N4"]["incarnation"] and stats.get("count", 0) > 50:
                break
        else:
            row["error"] = f"the flow did not resume within {RESUME_S:g} s of the heal"
        emitted = int(vertex(await node_status(emu, "N1"), "src").get("emitted", 0))
        deadline = loop.time() + DRAIN_S
        while loop.time() < deadline:
            stats = vertex(await node_status(emu, "N4"), "sink").get("stats", {})
            caught_up = stats.get("missing", 0) <= stats.get("first_seq", 0)
            if stats.get("next", 0) >= emitted and caught_up:
                break
            await asyncio.sleep(POLL_S)
        now = {n: await node_status(emu, n) for n in emu.nodes}

        def first_record(kind: str, since: float) -> float | None:
            ats = [
                r["at"]
                for n in SURVIVORS
                for r in now[n].get(kind, [])
                if r["node"] == "N4" and r["at"] >= since
            ]
            return (min(ats) - since) * 1e3 if ats else None

        row["detection_ms"] = first_record("failures", cut_t)
        row["rejoin_ms"] = first_record("rejoins", heal_t)
        first = stats.get("first")
        row["resume_ms"] = (first - heal_t) * 1e3 if first is not None else None
        row["incarnation_step"] = now["N4"]["incarnation"] - before["N4"]["incarnation"]
        row["dropped"] = sum(
            sum(now[n]["apps"]["fail"].get("dropped_parked", {}).values()) for n in SURVIVORS
        )
        row["emitted"] = emitted
        row["sink_count"] = stats.get("count", 0)
        # the new sink's first event opened a hole below it: what the partition cost, not
        # a loss after the resume
        holes = int(stats.get("missing", 0)) - int(stats.get("first_seq", 0))
        row["first_seq"] = stats.get("first_seq")
        row["lost_after"] = holes + max(0, emitted - int(stats.get("next", 0)))
        row["duplicated"] = int(stats.get("repeats", 0))
        row["failed_nodes"] = {n: st.get("failed_nodes") for n, st in now.items()}
        if any(row["failed_nodes"].values()):
            row["error"] = row["error"] or f"still failed: {row['failed_nodes']}"
        if row["detection_ms"] is None or row["rejoin_ms"] is None:
            row["error"] = row["error"] or "no failure or no rejoin recorded"
    except Exception as exc:  # a failed run is reported, the others still run
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if row["error"] or row.get("lost_after") or row.get("duplicated"):
            row["logs"] = log_lines(emu)
        await emu.stop()
    return row


def render(result: dict[str, Any]) -> str:
    s = result["summary"]

    def fig(key: str) -> str:
        x = s[key]
        if x["n"] == 0:
            return "-"
        return f"{x['p50']:,.0f} / {x['max']:,.0f}"

    lines = [
        f"### A healed partition: the sink's node cut off for {result['outage_s']:g} s "
        f"({result['runs']} runs, {RATE:g} events/s)",
        "",
        "| runs ok | detection ms p50 / max | rejoin after heal ms p50 / max "
        "| flow resumes after heal ms p50 / max | dropped while parked | lost after resume "
        "| duplicated |",
        "|---:|---:|---:|---:|---:|---:|---:|",
        f"| {s['ok']}/{result['runs']} | {fig('detection_ms')} | {fig('rejoin_ms')} | "
        f"{fig('resume_ms')} | {s['dropped_total']:,} | {s['lost_after_total']} of "
        f"{s['emitted_total']:,} | {s['duplicated_total']} |",
        "",
        "- detection: survivors' failure record minus the cut; rejoin: survivors' rejoin "
        "record (N4 reset and came back as a new incarnation) minus the heal; resume: the "
        "first event at the sink's new instance minus the heal; dropped: events on the parked "
        "chain's edges while N4 was out (by design); lost after resume and duplicated: target 0",
    ]
    for row in result["rows"]:
        if row["error"]:
            lines.append(f"- run {row['run']}: {row['error']}")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--outage", type=float, default=2.0, help="seconds the link stays down")
    ap.add_argument("--quick", action="store_true", help="2 runs")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    runs = 2 if args.quick else args.runs
    if runs < 1 or args.outage <= 0:
        ap.error("--runs and --outage must be positive")
    out: Path = args.json or RESULTS / ("partition-quick.json" if args.quick else "partition.json")
    started = time.monotonic()

    async def all_runs() -> list[dict[str, Any]]:
        with tempfile.TemporaryDirectory(prefix="mso-partition-") as tmp:
            rows = []
            for k in range(runs):
                row = await one_run(k, args.outage, Path(tmp))
                print(
                    f"run {k}: detection {row.get('detection_ms')}, rejoin {row.get('rejoin_ms')}"
                    f", resume {row.get('resume_ms')}, dropped {row.get('dropped')}, lost after "
                    f"{row.get('lost_after')}, dup {row.get('duplicated')}"
                    + (f" ERROR {row['error']}" if row["error"] else ""),
                    file=sys.stderr,
                )
                rows.append(row)
            return rows

    rows = asyncio.run(all_runs())
    good = [r for r in rows if not r["error"]]

    def col(key: str) -> list[float]:
        return [float(r[key]) for r in good if r.get(key) is not None]

    result: dict[str, Any] = {
        "benchmark": "partition",
        "runs": runs,
        "outage_s": args.outage,
        "rate": RATE,
        "summary": {
            "ok": len(good),
            "detection_ms": summary(col("detection_ms")),
            "rejoin_ms": summary(col("rejoin_ms")),
            "resume_ms": summary(col("resume_ms")),
            "dropped_total": sum(int(r.get("dropped") or 0) for r in rows),
            "lost_after_total": sum(int(r.get("lost_after") or 0) for r in rows),
            "duplicated_total": sum(int(r.get("duplicated") or 0) for r in rows),
            "emitted_total": sum(int(r.get("emitted") or 0) for r in rows),
        },
        "rows": rows,
        "seconds": time.monotonic() - started,
    } | provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
