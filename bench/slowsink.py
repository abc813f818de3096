"""A slow sink: is the source held back to its pace, with nothing lost and no node failed?

Two emulated nodes N1-N2 (0.5 ms, 54 Mbit/s, management off): ``src`` (N1, a rated source asking
``--rate`` events/s) -> ``sink`` (N2, ``vertices.executor:Checker`` sleeping ``--delay`` s per
event: 50 ms, so 20 events/s at most) for ``--duration`` s. Every second both nodes' status is
read. Figures:

* pace: events emitted per second by the source and processed per second by the sink over the
  second half of the run (once the window is full, the source can only go as fast as acks
  free room; target: equal within 5%), and over the whole run;
* what is in flight at the end: the edge's unacknowledged events at the source (bounded by the
  4,096-event window), what the sink's node holds queued for its worker;
* accounting: emitted = delivered + still in flight, with no hole, repeat or reordering at the
  sink (target: 0 lost); nodes declared failed (target: none). The in-flight events would take
  window x delay (about 200 s) to drain, so the run does not wait for them (``--drain`` does).

Usage: .venv/bin/python bench/slowsink.py [--quick] [--duration 60] [--rate 1000]
                                          [--delay 0.05] [--drain] [--json FILE]
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
APP = "slow"
DRAIN_MAX_S = 400.0

LINE2 = """\
name: line2
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


def app_yaml(rate: float, delay: float, limit: int) -> str:
    fmt = f"{VERTICES}:Seq"
    return f"""\
name: {APP}
vertices:
  src:  {{code: {VERTICES}:Counting, pinned: N1, rate: {rate:g},
         params: {{limit: {limit}}}, output: {fmt}}}
  sink: {{code: {VERTICES}:Checker, pinned: N2, params: {{delay_s: {delay:g}}},
         input: {fmt}}}
edges:
  - [src, sink]
"""


def v(nodes: dict[str, Any], node: str, name: str) -> dict[str, Any]:
    out: dict[str, Any] = nodes[node]["apps"][APP]["vertices"][name]
    return out


async def run(rate: float, delay: float, duration: float, drain: bool) -> dict[str, Any]:
    emu = Emulator(loads_scenario(LINE2), manage=False)
    loop = asyncio.get_running_loop()
    samples: list[dict[str, Any]] = []
    failures: dict[str, Any] = {}
    out: dict[str, Any] = {}
    try:
        await emu.start()
        # a source that stops at what it could emit at full rate over the run (never reached)
        await emu.deploy(app_yaml(rate, delay, int(rate * duration)), "slow.yaml", "N1", check=True)
        t0 = loop.time()
        nodes: dict[str, Any] = {}
        while loop.time() < t0 + duration:
            await asyncio.sleep(1.0)
            nodes = await emu.status()
            t = loop.time() - t0
            src, sink = v(nodes, "N1", "src"), v(nodes, "N2", "sink")
            edge = nodes["N1"]["apps"][APP]["edges"]["src->sink"]
            samples.append(
                {
                    "t": round(t, 3),
                    "emitted": src["emitted"],
                    "calls": src["calls"],
                    "processed": sink["processed"],
                    "in_flight": edge["in_flight"],
                    "queued": sink["queued"],
                    "sink_state": sink["state"],
                }
            )
            for n, st in nodes.items():
                if st.get("failed_nodes") or st.get("failures"):
                    failures[n] = {"failed": st["failed_nodes"], "failures": st["failures"]}
        out["end"] = samples[-1]
        out["sink_stats"] = v(nodes, "N2", "sink")["stats"]
        if drain:  # stop the source: undeploying would drop what is in flight, so wait
            deadline = loop.time() + DRAIN_MAX_S
            while loop.time() < deadline:
                await asyncio.sleep(2.0)
                nodes = await emu.status()
                stats = v(nodes, "N2", "sink")["stats"]
                if stats["next"] >= out["end"]["emitted"]:
                    break
            out["drained"] = {"after_s": round(loop.time() - t0 - duration, 1), "sink": stats}
        for n, st in nodes.items():
            if st.get("failed_nodes") or st.get("failures"):
                failures[n] = {"failed": st["failed_nodes"], "failures": st["failures"]}
    finally:
        await emu.stop()
    out["samples"] = samples
    out["failures"] = failures
    return out


def pace(samples: list[dict[str, Any]], key: str, since: float) -> float:
    """Events per second of counter ``key`` between the first sample at/after ``since`` and
    the last."""
    part = [s for s in samples if s["t"] >= since]
    if len(part) < 2:
        return 0.0
    a, b = part[0], part[-1]
    return float(b[key] - a[key]) / float(b["t"] - a["t"])


def summarise(r: dict[str, Any], duration: float) -> dict[str, Any]:
    s, end, st = r["samples"], r["end"], r["sink_stats"]
    half = duration / 2
    in_flight_unprocessed = end["emitted"] - st["next"]
    return {
        "emitted_per_s_second_half": pace(s, "emitted", half),
        "processed_per_s_second_half": pace(s, "processed", half),
        "emitted_per_s_whole": pace(s, "emitted", 0.0),
        "processed_per_s_whole": pace(s, "processed", 0.0),
        "source_calls": end["calls"],
        "emitted": end["emitted"],
        "delivered": st["count"],
        "in_flight_at_source": end["in_flight"],
        "queued_at_sink": end["queued"],
        "not_yet_processed": in_flight_unprocessed,
        "holes": st["missing"],
        "repeats": st["repeats"],
        "out_of_order": st["out_of_order"],
        # every emitted event is either delivered or still held in the window (unacked)
        "accounted": st["missing"] == 0
        and st["repeats"] == 0
        and st["next"] == st["count"]
        and 0 <= in_flight_unprocessed <= end["in_flight"],
    }


def render(result: dict[str, Any]) -> str:
    s = result["summary"]
    load = result["machine"]["load_average"]
    ratio = s["emitted_per_s_second_half"] / max(s["processed_per_s_second_half"], 1e-9)
    lines = [
        f"### Slow sink: {result['delay_s'] * 1e3:g} ms per event, source asking "
        f"{result['rate']:,.0f} events/s, {result['duration_s']:g} s",
        "",
        f"Machine: {result['machine']['cpus']} vCPUs, load average at the end "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared; other engineers' tests ran meanwhile).",
        "",
        "| | source emitted /s | sink processed /s |",
        "|---|---:|---:|",
        f"| second half | {s['emitted_per_s_second_half']:.2f} "
        f"| {s['processed_per_s_second_half']:.2f} |",
        f"| whole run | {s['emitted_per_s_whole']:.2f} | {s['processed_per_s_whole']:.2f} |",
        "",
        f"- source held to the sink's pace in the second half: emitted/processed = {ratio:.3f} "
        f"(target within 5%: {'met' if abs(ratio - 1) <= 0.05 else 'NOT met'}); the source "
        f"was asked for {result['rate'] * result['duration_s']:,.0f} events and emitted "
        f"{s['emitted']:,}",
        f"- at the end: emitted {s['emitted']:,}, delivered {s['delivered']:,}, not yet "
        f"processed {s['not_yet_processed']:,} (unacknowledged at the source: "
        f"{s['in_flight_at_source']:,}, queued at the sink's node: {s['queued_at_sink']:,})",
        f"- holes {s['holes']}, repeats {s['repeats']}, out of order {s['out_of_order']}; "
        f"every emitted event delivered once or still in the window: "
        f"{'yes' if s['accounted'] else 'NO'}",
        f"- nodes declared failed: {result['run']['failures'] or 'none'}",
    ]
    if "drained" in result["run"]:
        d = result["run"]["drained"]
        lines.append(
            f"- drained {d['after_s']:g} s after the run: sink next {d['sink']['next']:,}, "
            f"holes {d['sink']['missing']}, repeats {d['sink']['repeats']}"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--quick", action="store_true", help="20 s")
    ap.add_argument("--rate", type=float, default=1000.0, help="events/s asked (1000)")
    ap.add_argument("--delay", type=float, default=0.05, help="sink seconds per event (0.05)")
    ap.add_argument("--drain", action="store_true", help="wait for the window to drain")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    args = ap.parse_args(argv)
    duration = 20.0 if args.quick else args.duration
    if not 5.0 <= duration <= 600.0 or not 1.0 <= args.rate <= 50_000 or not 0 < args.delay <= 1:
        ap.error("--duration 5..600 s, --rate 1..50000, --delay 0..1 s")
    out: Path = args.json or RESULTS / ("slowsink-quick.json" if args.quick else "slowsink.json")
    t0 = time.monotonic()
    r = asyncio.run(run(args.rate, args.delay, duration, args.drain))
    result: dict[str, Any] = {
        "benchmark": "slowsink",
        "rate": args.rate,
        "delay_s": args.delay,
        "duration_s": duration,
        "summary": summarise(r, duration),
        "run": r,
        "seconds": time.monotonic() - t0,
    }
    result |= provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
