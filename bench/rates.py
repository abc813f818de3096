"""Does a ``rate:`` source hold its rate, from 1 to 50,000 events/s?

Two emulated nodes N1-N2 (0.5 ms, 54 Mbit/s, management off): ``src`` (N1, rated
``vertices.executor:Counting``) -> ``sink`` (N2, ``vertices.executor:Checker``). For each asked
rate the app is deployed, left ``--warmup`` s, then the sink's last arrival (time, seq) is read
twice, a window apart (``max(--window, 10 events)``); the rate got is
``(seq2 - seq1) / (t2 - t1)``: events that arrived at the sink per second, measured on arrival
times, so the polls' own timing does not enter. The source numbers its events itself, so a
skipped or repeated call would show. Target: within 1% of the asked rate at every rate.

Usage: .venv/bin/python bench/rates.py [--quick] [--rates 1,10,100,1000,10000,50000]
                                       [--window 5] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.emu.controller import Emulator
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.executor"  # the vertex code the nodes import
RATES = [1, 10, 100, 1000, 10_000, 50_000]

LINE2 = """\
name: line2
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


def app_yaml(name: str, rate: float) -> str:
    fmt = f"{VERTICES}:Seq"
    return f"""\
name: {name}
vertices:
  src:  {{code: {VERTICES}:Counting, pinned: N1, rate: {rate:g}, output: {fmt}}}
  sink: {{code: {VERTICES}:Checker, pinned: N2, input: {fmt}}}
edges:
  - [src, sink]
"""


async def sink_stats(emu: Emulator, app: str) -> dict[str, Any]:
    nodes = await emu.status("N2")
    stats: dict[str, Any] = nodes["N2"]["apps"][app]["vertices"]["sink"]["stats"] or {}
    return stats


async def one_rate(
    emu: Emulator, k: int, rate: float, warmup: float, window: float
) -> dict[str, Any]:
    app = f"rate{k}"
    loop = asyncio.get_running_loop()
    await emu.deploy(app_yaml(app, rate), f"{app}.yaml", "N1", check=True)
    try:
        span = max(window, 10.0 / rate)
        await asyncio.sleep(max(warmup, 1.5 / rate))  # at least one event before the window
        a = await sink_stats(emu, app)
        t_a = loop.time()
        await asyncio.sleep(span)
        b = await sink_stats(emu, app)
        nodes = await emu.status()
        src = nodes["N1"]["apps"][app]["vertices"]["src"]
        failed = {n: st["failed_nodes"] for n, st in nodes.items() if st["failed_nodes"]}
        dt = b["last_t"] - a["last_t"]
        got = (b["last_seq"] - a["last_seq"]) / dt if dt > 0 else 0.0
        return {
            "asked": rate,
            "got": got,
            "error_pct": (got - rate) / rate * 100.0,
            "window_s": dt,
            "events": b["last_seq"] - a["last_seq"],
            "poll_window_s": loop.time() - t_a,
            "emitted": src["emitted"],
            "calls": src["calls"],
            "sink_count": b["count"],
            "holes": b["missing"],
            "repeats": b["repeats"],
            "out_of_order": b["out_of_order"],
            "latency_max_ms": b["latency_max_s"] * 1e3,
            "failed_nodes": failed,
        }
    finally:
        await emu.undeploy(app, "N1")


async def run(rates: list[float], warmup: float, window: float) -> list[dict[str, Any]]:
    emu = Emulator(loads_scenario(LINE2), manage=False)
    rows = []
    try:
        await emu.start()
        for k, rate in enumerate(rates):
            try:
                row = await one_rate(emu, k, rate, warmup, window)
            except Exception as exc:  # a failed rate is reported, the others still run
                row = {"asked": rate, "error": f"{type(exc).__name__}: {exc}"}
            rows.append(row)
            print(f"asked {rate:g}/s: {row.get('got', row.get('error'))}", file=sys.stderr)
    finally:
        await emu.stop()
    return rows


def render(result: dict[str, Any]) -> str:
    load = result["machine"]["load_average"]
    lines = [
        "### `rate:` sources, asked vs got (sink arrivals, 2 emulated nodes)",
        "",
        f"Machine: {result['machine']['cpus']} vCPUs, load average at the end "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared; other engineers' tests ran meanwhile).",
        "",
        "| asked /s | got /s | error | window s | events | holes / repeats / reordered "
        "| max latency ms | within 1% |",
        "|---:|---:|---:|---:|---:|---|---:|---|",
    ]
    for r in result["rows"]:
        if "error" in r:
            lines.append(f"| {r['asked']:,g} | FAILED: {r['error']} | | | | | | no |")
            continue
        ok = abs(r["error_pct"]) <= 1.0 and not (r["holes"] or r["repeats"] or r["failed_nodes"])
        lines.append(
            f"| {r['asked']:,g} | {r['got']:,.2f} | {r['error_pct']:+.3f}% | {r['window_s']:.2f} "
            f"| {r['events']:,} | {r['holes']} / {r['repeats']} / {r['out_of_order']} "
            f"| {r['latency_max_ms']:.1f} | {'yes' if ok else 'NO'} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--rates", default=",".join(map(str, RATES)))
    ap.add_argument("--quick", action="store_true", help="2 s windows")
    ap.add_argument("--window", type=float, default=5.0, help="seconds (at least 10 events)")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    args = ap.parse_args(argv)
    rates = [float(x) for x in args.rates.split(",") if x]
    window = 2.0 if args.quick else args.window
    if not rates or any(not 0.1 <= r <= 100_000 for r in rates) or not 1 <= window <= 120:
        ap.error("--rates: 0.1..100000 events/s each; --window 1..120 s")
    out: Path = args.json or RESULTS / ("rates-quick.json" if args.quick else "rates.json")
    t0 = time.monotonic()
    rows = asyncio.run(run(rates, args.warmup, window))
    result: dict[str, Any] = {
        "benchmark": "rates",
        "window_s": window,
        "warmup_s": args.warmup,
        "rows": rows,
        "seconds": time.monotonic() - t0,
    }
    result |= provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
