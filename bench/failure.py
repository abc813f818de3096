"""Fail-stop failure of a relaying node: detection time, recovery time, events lost.

The app ``src -> mid -> sink`` (``vertices.failure``: a counting source at 200 events/s pinned to
the first node, a stateless pass-through ``mid`` left unpinned, a gap-timing sink pinned to the
last node) runs on two emulated topologies, one ``mso node`` process per node:

* ``line``: a convoy of 5 robots R1..R5 100 m apart with ``radio_range: 250`` (each robot hears
  the robots up to two positions away; 54 Mbit/s, 0.5 ms links). The route R1 -> R5 is
  R1-R3-R5 and Algorithm 1 puts ``mid`` on R3 with no tuning (equal costs); killing R3 leaves
  R1-R2-R4-R5, so the line is never partitioned.
* ``mesh``: the 6-node mesh of tests/test_emulator.py (0.5 ms links); ``mid`` lands on N3, an
  interior node of the route N1-N2-N3-N6; N1-N2-N5-N6 and N1-N4-N5-N6 survive it.

Each run starts a fresh emulator (management rules off, so only the failure moves ``mid``),
deploys the app via the first node, lets it flow for 1.5 s, then SIGKILLs the node hosting
``mid`` (read from the placement just before the kill; it must be an interior node) with
``Emulator.kill``, and polls the sink's node (its own status: an ``everywhere`` status would wait
up to 1 s for the dead node) until the sink has received a good half second of events after the
kill (at most 8 s). It then reads the source's ``emitted`` and waits (at most 3 s) until the sink
has everything up to it. Figures per run:

* detection_ms: the earliest ``failures[*].at`` for the killed node over the survivors minus
  the kill time (node loop times and the controller's are the same CLOCK_MONOTONIC);
* recovery_ms: first arrival at the sink after the outage minus the last arrival before it, the
  outage being the largest inter-arrival gap that ends after the kill (the sink keeps its five
  largest gaps); ``straddles`` says whether it starts before the kill (events already past the
  victim may still arrive just after it);
* resume_ms: first arrival after the outage minus the kill time;
* remap_started_ms: the coordinator's recovery record ``at`` minus the kill time (it starts once
  its routes avoid the victim); remap_ms: that record's ``took_ms`` (probe, place, restore);
* lost: events the source emitted (read after recovery) that the sink never got -- holes the
  sink still has plus what lies beyond its highest seq (target 0); duplicated: events the sink
  got twice (target 0).

``--heartbeat S`` and ``--dead-after S`` set every node's failure detection (default 0.1 s and
0.5 s; ``failure-hb0.05-dead0.15.json`` etc. for other settings); a survivor that declares a
live node failed (a false detection) fails its run.

``--convergence S`` is the emulator's routing convergence delay (routes follow a link change
after S seconds; 0 = at once, 2.0 = babeld-like). Each setting is its own invocation with its
own files: ``bench/results/failure.json``/``.md`` for 0, ``failure-conv2.json``/``.md`` for 2.0
(``-quick`` appended with ``--quick``).

Usage: .venv/bin/python bench/failure.py [--runs 10] [--quick] [--convergence 0.0]
                                         [--topology line,mesh] [--manage] [--json FILE]
                                         [--heartbeat 0.1] [--dead-after 0.5]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import percentile, provenance, write_results
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.failure"  # the vertex code the nodes import
APP = "fail"
RATE = 200.0
STEADY_S = 1.5  # flow before the kill
RECOVER_S = 8.0  # bound on waiting for the flow to resume
DRAIN_S = 3.0  # bound on waiting for in-flight events after it resumed
POLL_S = 0.05
RUN_TIMEOUT_S = 45.0  # a whole run (start, deploy, kill, recover, drain, stop)
RUN_BUDGET_S = 15.0  # per planned run: no run starts once runs x this has passed (~3-5 s used)

TOPOLOGIES: dict[str, tuple[str, str, str]] = {  # name -> (scenario, first node, last node)
    "line": (
        """\
name: convoy5
link_defaults: {bandwidth_mbps: 54, delay_ms: 0.5}
radio_range: 250
nodes:
  R1: {pos: [0, 0]}
  R2: {pos: [100, 0]}
  R3: {pos: [200, 0]}
  R4: {pos: [300, 0]}
  R5: {pos: [400, 0]}
""",
        "R1",
        "R5",
    ),
    "mesh": (
        """\
name: mesh
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}, N6: {}}
links: [[N1, N2], [N2, N3], [N3, N6], [N1, N4], [N4, N5], [N5, N6], [N2, N5], [N3, N5]]
""",
        "N1",
        "N6",
    ),
}


def app_yaml(first: str, last: str, rate: float) -> str:
    """src (pinned to ``first``) -> mid (unpinned) -> sink (pinned to ``last``)."""
    fmt = f"{VERTICES}:Seq"
    return f"""\
name: {APP}
vertices:
  src:  {{code: {VERTICES}:CountingSource, pinned: {first}, rate: {rate:g},
         output: {fmt}}}
  mid:  {{code: {VERTICES}:PassThrough, input: {fmt}, output: {fmt}}}
  sink: {{code: {VERTICES}:GapSink, pinned: {last}, input: {fmt}}}
edges:
  - [src, mid]
  - [mid, sink]
"""


def summary(values: list[float]) -> dict[str, Any]:
    """mean / p50 / p99 / max (and min, n) of a list, None when it is empty."""
    if not values:
        return {"mean": None, "p50": None, "p99": None, "max": None, "min": None, "n": 0}
    return {
        "mean": statistics.fmean(values),
        "p50": percentile(values, 50),
        "p99": percentile(values, 99),
        "max": max(values),
        "min": min(values),
        "n": len(values),
    }


async def node_status(emu: Emulator, node: str) -> dict[str, Any]:
    """One node's own status (not ``everywhere``: that waits up to 1 s for a dead node)."""
    nodes = await emu.overlay(node).status(everywhere=False, timeout=5.0)
    st: dict[str, Any] = nodes[node]
    return st


def vertex(st: dict[str, Any], name: str) -> dict[str, Any]:
    """A vertex's status entry on a node ({} if the node does not host it)."""
    v: dict[str, Any] = st.get("apps", {}).get(APP, {}).get("vertices", {}).get(name, {})
    return v


def outage(stats: dict[str, Any], kill_t: float) -> tuple[float, float] | None:
    """The largest recorded gap that ends after the kill: (last before, first after)."""
    after_kill = [(b, a) for b, a in stats.get("gaps", []) if a > kill_t]
    if not after_kill:
        return None
    return max(after_kill, key=lambda g: g[1] - g[0])


def log_lines(emu: Emulator, limit: int = 12) -> dict[str, list[str]]:
    """The last warning/error lines of each node's log (they go with the emulator)."""
    words = ("Error", "ERROR", "WARNING", "Traceback", "failed", "refused")
    out: dict[str, list[str]] = {}
    for name, node in emu.nodes.items():
        if node.log is None or not node.log.exists():
            continue
        lines = node.log.read_text(errors="replace").splitlines()
        hits = [ln for ln in lines if any(w in ln for w in words)]
        if hits:
            out[name] = hits[-limit:]
    return out


async def one_run(
    topology: str,
    k: int,
    convergence: float,
    rate: float,
    manage: bool,
    logs: Path,
    detection: tuple[float | None, float | None] = (None, None),
    backend: str = "user",
) -> dict[str, Any]:
    """One fresh emulator: deploy, flow, kill the relay hosting ``mid``, measure."""
    scenario_text, first, last = TOPOLOGIES[topology]
    row: dict[str, Any] = {"topology": topology, "run": k, "error": None}
    log_dir = logs / f"{topology}-{k}"
    log_dir.mkdir()
    kind: type[Emulator] = Emulator
    if backend == "netns":  # a namespace per node, babeld, the kernel view
        from mso.emu.netns.emulator import NetnsEmulator

        kind = NetnsEmulator
    emu = kind(
        loads_scenario(scenario_text),
        convergence_s=convergence,
        log_dir=log_dir,
        manage=manage,
        heartbeat_s=detection[0],
        dead_after_s=detection[1],
    )
    loop = asyncio.get_running_loop()
    try:
        await emu.start()
        reply = await emu.deploy(app_yaml(first, last, rate), "failure.yaml", first, check=True)
        row["placed"] = reply.placement["mid"]
        await asyncio.sleep(STEADY_S)
        before = await node_status(emu, first)
        victim = before["apps"][APP]["placement"]["mid"]
        row["victim"] = victim
        if victim in (first, last):
            raise MsoError(f"mid is on an end node ({victim}), not on a relay")
        pre = vertex(await node_status(emu, last), "sink").get("stats", {})
        row["count_before"] = pre.get("count", 0)
        kill_t = emu.kill(victim)

        # the flow resumes: the sink has a good half second of events after the kill
        want = row["count_before"] + int(rate * 0.5) + int(rate * 0.05)
        stats: dict[str, Any] = {}
        deadline = kill_t + RECOVER_S
        while loop.time() < deadline:
            await asyncio.sleep(POLL_S)
            stats = vertex(await node_status(emu, last), "sink").get("stats", {})
            gap = outage(stats, kill_t)
            if stats.get("count", 0) >= want and gap is not None and stats["last"] > gap[1]:
                break
        else:
            row["error"] = f"no recovery within {RECOVER_S:g} s"
        row["resumed_wait_s"] = loop.time() - kill_t

        # everything the source has emitted so far reaches the sink
        emitted = int(vertex(await node_status(emu, first), "src").get("emitted", 0))
        deadline = loop.time() + DRAIN_S
        while loop.time() < deadline:
            stats = vertex(await node_status(emu, last), "sink").get("stats", {})
            if stats.get("next", 0) >= emitted and not stats.get("missing", 0):
                break
            await asyncio.sleep(POLL_S)
        everywhere = await emu.status(first)

        row["emitted"] = emitted
        row["sink_count"] = stats.get("count", 0)  # by now: includes events after ``emitted``
        row["lost"] = int(stats.get("missing", 0)) + max(0, emitted - int(stats.get("next", 0)))
        row["duplicated"] = int(stats.get("repeats", 0))
        row["out_of_order"] = int(stats.get("out_of_order", 0))
        row["late"] = int(stats.get("late", 0))

        ats = [
            (f["at"], f["detector"])
            for n, st in everywhere.items()
            if n != victim
            for f in st.get("failures", [])
            if f["node"] == victim
        ]
        if ats:
            at, detector = min(ats)
            row["detection_ms"] = (at - kill_t) * 1e3
            row["detector"] = detector
        else:
            row["detection_ms"] = None
            row["error"] = row["error"] or "no survivor recorded the failure"
        if victim in emu.dead:
            row["noticed_ms"] = (emu.dead[victim] - kill_t) * 1e3  # by the controller
        gap = outage(stats, kill_t)
        if gap is not None:
            row["recovery_ms"] = (gap[1] - gap[0]) * 1e3
            row["resume_ms"] = (gap[1] - kill_t) * 1e3
            row["straddles"] = gap[0] <= kill_t < gap[1]
            row["outage_starts_ms"] = (gap[0] - kill_t) * 1e3
        else:
            row["recovery_ms"] = row["resume_ms"] = None
            row["straddles"] = False
        records = [
            r
            for n, st in everywhere.items()
            for r in st.get("apps", {}).get(APP, {}).get("recoveries", [])
        ]
        row["recoveries"] = records
        row["remap_ms"] = records[0].get("took_ms") if len(records) == 1 else None
        if records:  # when the coordinator started (it waits for routes around the victim)
            row["remap_started_ms"] = (records[0]["at"] - kill_t) * 1e3
        if len(records) != 1 or not records[0].get("ok"):
            row["error"] = row["error"] or f"recovery records: {records}"
        hosts = [n for n, st in everywhere.items() if vertex(st, "mid")]
        row["mid_after"] = hosts[0] if len(hosts) == 1 else hosts
        row["failed_nodes"] = {n: st.get("failed_nodes") for n, st in everywhere.items()}
        false = sorted({f["node"] for st in everywhere.values() for f in st.get("failures", [])})
        if false != [victim]:  # a live node declared failed: detection too eager
            row["error"] = row["error"] or f"nodes declared failed: {false} (victim {victim})"
        row["unroutable"] = {  # frames a node had no route (or no live next hop) for
            n: st["traffic"]["frames_unroutable"]
            for n, st in everywhere.items()
            if st.get("traffic", {}).get("frames_unroutable")
        }
        row["dropped_messages"] = {
            n: st["dropped_messages"] for n, st in everywhere.items() if st.get("dropped_messages")
        }
    except Exception as exc:  # a failed run is reported, the others still run
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if row["error"] or row.get("lost") or row.get("duplicated"):
            row["logs"] = log_lines(emu)
        await emu.stop()
        shutil.rmtree(log_dir, ignore_errors=True)
    return row


def topology_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary figures of one topology's runs (failed runs count only in ``failed``)."""

    def col(key: str) -> list[float]:
        return [float(r[key]) for r in rows if r.get(key) is not None and not r["error"]]

    good = [r for r in rows if not r["error"]]
    moves: dict[str, int] = {}
    for r in good:
        key = f"{r.get('victim')}->{r.get('mid_after')}"
        moves[key] = moves.get(key, 0) + 1
    return {
        "runs": len(rows),
        "ok": len(good),
        "failed": len(rows) - len(good),
        "detection_ms": summary(col("detection_ms")),
        "recovery_ms": summary(col("recovery_ms")),
        "resume_ms": summary(col("resume_ms")),
        "remap_ms": summary(col("remap_ms")),
        "remap_started_ms": summary(col("remap_started_ms")),
        "retried": sum(any(x.get("retried") for x in r.get("recoveries") or []) for r in good),
        "retried_steps": sorted(
            {s for r in good for x in r.get("recoveries") or [] for s in x.get("retried") or []}
        ),
        "lost_total": sum(int(r.get("lost") or 0) for r in rows),
        "duplicated_total": sum(int(r.get("duplicated") or 0) for r in rows),
        "emitted_total": sum(int(r.get("emitted") or 0) for r in rows),
        "straddling": sum(bool(r.get("straddles")) for r in good),
        "mid_moves": moves,
    }


async def run(
    runs: int,
    convergence: float,
    rate: float,
    topologies: list[str],
    manage: bool,
    detection: tuple[float | None, float | None] = (None, None),
    backend: str = "user",
) -> dict[str, Any]:
    """``runs`` fresh-emulator runs per topology, within the time budget."""
    t0 = time.monotonic()
    budget = RUN_BUDGET_S * runs * len(topologies)
    result: dict[str, Any] = {"topologies": {}, "rows": [], "notes": []}
    with tempfile.TemporaryDirectory(prefix="mso-bench-failure-") as tmp:
        for topology in topologies:
            rows = []
            for k in range(runs):
                if time.monotonic() - t0 > budget:
                    result["notes"].append(f"{topology}: budget spent after {k} runs")
                    break
                try:
                    row = await asyncio.wait_for(
                        one_run(
                            topology,
                            k,
                            convergence,
                            rate,
                            manage,
                            Path(tmp),
                            detection,
                            backend,
                        ),
                        RUN_TIMEOUT_S,
                    )
                except TimeoutError:
                    row = {"topology": topology, "run": k, "error": "run timed out"}
                rows.append(row)
                status = "ok" if not row["error"] else f"FAILED: {row['error']}"
                print(
                    f"{topology} run {k}: victim {row.get('victim')} -> "
                    f"{row.get('mid_after')}, detection {_f(row.get('detection_ms'))} ms, "
                    f"recovery {_f(row.get('recovery_ms'))} ms, "
                    f"lost {row.get('lost')}, dup {row.get('duplicated')} ({status})",
                    file=sys.stderr,
                )
            result["topologies"][topology] = topology_summary(rows)
            result["rows"] += rows
    result["seconds"] = time.monotonic() - t0
    return result


def _f(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:,.{digits}f}"


def render(result: dict[str, Any]) -> str:
    """The Markdown table (and what went wrong, if anything)."""
    conv = result["convergence_s"]
    lines = [
        f"### Fail-stop failure of the relay hosting `mid` (convergence {conv:g} s, "
        f"{result['rate']:g} events/s, {result['runs']} runs per topology, heartbeat "
        f"{result.get('heartbeat_s', 0.1):g} s, failed after {result.get('dead_after_s', 0.5):g} "
        "s of silence)",
        "",
        "| topology | runs ok | detection ms mean / p50 / p99 / max "
        "| recovery ms mean / p50 / p99 / max | remap starts after kill ms p50 "
        "| remap ms p50 / max | lost | duplicated | mid moved |",
        "|---|---:|---|---|---:|---|---:|---:|---|",
    ]
    for name, s in result["topologies"].items():
        d, r = s["detection_ms"], s["recovery_ms"]
        moves = ", ".join(f"{k} ({v})" for k, v in sorted(s["mid_moves"].items()))
        lines.append(
            f"| {name} | {s['ok']}/{s['runs']} "
            f"| {_f(d['mean'])} / {_f(d['p50'])} / {_f(d['p99'])} / {_f(d['max'])} "
            f"| {_f(r['mean'])} / {_f(r['p50'])} / {_f(r['p99'])} / {_f(r['max'])} "
            f"| {_f(s['remap_started_ms']['p50'])} "
            f"| {_f(s['remap_ms']['p50'], 2)} / {_f(s['remap_ms']['max'], 2)} "
            f"| {s['lost_total']} of {s['emitted_total']:,} | {s['duplicated_total']} | {moves} |"
        )
    lines += [
        "",
        "- detection: earliest survivor's failure record minus the kill (SIGKILL) time; "
        "recovery: first sink arrival after the outage minus the last before it (nominal "
        f"inter-arrival {1e3 / result['rate']:g} ms); remap starts: the coordinator's recovery "
        "record minus the kill (it waits for routes around the victim); remap: its `took_ms`; "
        "lost/duplicated: over all runs (target 0)",
    ]
    for name, s in result["topologies"].items():
        if s["ok"] and s["straddling"] < s["ok"]:
            lines.append(
                f"- {name}: in {s['ok'] - s['straddling']} run(s) a few events already past "
                "the victim arrived after the kill; the outage was timed from the last of them"
            )
    for name, s in result["topologies"].items():
        if s["retried"]:
            lines.append(
                f"- {name}: in {s['retried']} run(s) the remap took about 1 s more: a step was "
                f"re-sent after the 1 s step timeout ({', '.join(s['retried_steps'])})"
            )
    for note in result["notes"]:
        lines.append(f"- note: {note}")
    for row in result["rows"]:
        if row["error"]:
            lines.append(f"- FAILED {row['topology']} run {row['run']}: {row['error']}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--runs", type=int, default=10, help="runs per topology (default 10)")
    ap.add_argument("--quick", action="store_true", help="3 runs per topology")
    ap.add_argument("--convergence", type=float, default=0.0, help="routing convergence, s")
    ap.add_argument("--rate", type=float, default=RATE, help="source events/s (default 200)")
    ap.add_argument("--topology", default="line,mesh", help="comma-separated: line,mesh")
    ap.add_argument("--manage", action="store_true", help="run the management rules too")
    ap.add_argument("--heartbeat", type=float, help="every node's heartbeat period, s (0.1)")
    ap.add_argument("--dead-after", type=float, help="every node's failure timeout, s (0.5)")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    ap.add_argument(
        "--backend",
        choices=("user", "netns"),
        default="user",
        help="netns: a namespace per node, babeld routing (heartbeat 0.2 s, dead-after 3 s "
        "unless given), the kernel forwarding",
    )
    args = ap.parse_args(argv)
    runs = 3 if args.quick else args.runs
    topologies = [t for t in args.topology.split(",") if t]
    if not 1 <= runs <= 100:
        ap.error("--runs: 1..100")
    if not 0.0 <= args.convergence <= 10.0:
        ap.error("--convergence: 0..10 s")
    if not 1.0 <= args.rate <= 5000.0:
        ap.error("--rate: 1..5000 events/s")
    if unknown := [t for t in topologies if t not in TOPOLOGIES]:
        ap.error(f"unknown topology {unknown}; known: {', '.join(TOPOLOGIES)}")
    name = "failure" + (f"-conv{args.convergence:g}" if args.convergence else "")
    if args.backend == "netns":
        name += "-netns"
    if args.heartbeat is not None:
        name += f"-hb{args.heartbeat:g}"
    if args.dead_after is not None:
        name += f"-dead{args.dead_after:g}"
    name += "-quick" if args.quick else ""
    out: Path = args.json or RESULTS / f"{name}.json"

    detection = (args.heartbeat, args.dead_after)
    netns = args.backend == "netns"
    if netns and args.heartbeat is None and args.dead_after is None:
        from mso.emu.netns.emulator import DEAD_AFTER_NETNS_S, HEARTBEAT_NETNS_S

        detection = (HEARTBEAT_NETNS_S, DEAD_AFTER_NETNS_S)
    result = asyncio.run(
        run(runs, args.convergence, args.rate, topologies, args.manage, detection, args.backend)
    )
    result = {
        "benchmark": "failure",
        "convergence_s": args.convergence,
        "rate": args.rate,
        "runs": runs,
        "quick": args.quick,
        "manage": args.manage,
        "steady_s": STEADY_S,
        "backend": args.backend,
        "heartbeat_s": detection[0] if detection[0] is not None else 0.1,
        "dead_after_s": detection[1] if detection[1] is not None else 0.5,
    } | result
    result |= provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
