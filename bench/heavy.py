"""A vertex burning 2 s of pure-Python CPU per event: does its node stay alive and on time?

On an emulated line N1-N2-N3 (0.5 ms, 54 Mbit/s links, management rules off) the app
``src`` (N1, ``--rate`` events/s, a fixed number of events) -> ``heavy`` (unpinned, lands on N2;
``vertices.executor:Burn``, a busy loop until its thread has used ``--cpu`` s of CPU per event)
-> ``sink`` (N3, checks order) runs for ``--duration`` s. A third of the way in ``heavy`` is
relocated downstream (onto the sink's node N3) and two thirds in (or once the first move is
answered) upstream (onto the source's node N1), while it computes; the polls go on meanwhile.
Before it, the same app with a 0 s vertex runs ``--baseline`` s for reference figures.

Figures (each node's status is polled every 0.5 s):

* failures: ``failed_nodes`` and ``failures`` of every node at every poll (target: none);
* heartbeat inter-arrival per (observer, neighbour) from status ``liveness`` (a bounded window
  of the last 2,048 beats: the whole run at 0.1 s), p50 / p99 / max, and lateness = p99 minus
  the heartbeat period (target: p99 lateness <= 50 ms);
* delivery: the source's ``emitted`` vs the sink's count, holes, repeats, order (target: all,
  once, in order) after the source stops and the pipeline drains (at most 30 s; what is still
  on its way then is counted apart from what is lost: on a loaded machine 2 s of CPU per
  event can take 10 s);
* relocations: ok, elapsed ms (a move is answered at its handover: after the call in progress
  and the events queued before the markers), and events lost across them (same target);
* how many polls saw ``heavy`` busy.

``--workers`` measures instead what CPU-bound vertices cost a node's event loop with the
daemon's thread executor and with the process-lane prototype (``mso.runtime.process_lane``), in
this process, without the network: a 50 ms timer on the loop (the heartbeat's place) records
how late it fires while 1 or 2 ``Burn`` vertices (a fixed amount of pure-Python work per
event, about 50 ms alone) each process ``--events`` events queued at once; and a pass-through
vertex's throughput (events in batches of 256), which the process lane pays IPC for. Written to
``heavy-workers.json``/``.md``.

Usage: .venv/bin/python bench/heavy.py [--quick] [--duration 60] [--cpu 2.0] [--rate 0.4]
                                       [--heartbeat 0.1] [--dead-after 0.5] [--json FILE]
       .venv/bin/python bench/heavy.py --workers [--events 40] [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.benchmarks.vertices.executor import Burn, Seq
from mso.emu.controller import Emulator
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.executor"  # the vertex code the nodes import
APP = "heavy"
POLL_S = 0.5
DRAIN_S = 30.0

LINE3 = """\
name: line3
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}}
links: [[N1, N2], [N2, N3]]
"""


def app_yaml(cpu_s: float, rate: float, limit: int) -> str:
    fmt = f"{VERTICES}:Seq"
    return f"""\
name: {APP}
planner: paper  # heavy on N2 (bytes: on the source's node)
vertices:
  src:   {{code: {VERTICES}:Counting, pinned: N1, rate: {rate:g},
          params: {{limit: {limit}}}, output: {fmt}}}
  heavy: {{code: {VERTICES}:Burn, params: {{cpu_s: {cpu_s:g}}}, input: {fmt},
          output: {fmt}}}
  sink:  {{code: {VERTICES}:Checker, pinned: N3, input: {fmt}}}
edges:
  - [src, heavy]
  - [heavy, sink]
"""


def vertex(nodes: dict[str, Any], name: str) -> tuple[str, dict[str, Any]]:
    """(node, status entry) of the one node hosting ``name`` ("", {} if none)."""
    for n, st in nodes.items():
        v = st.get("apps", {}).get(APP, {}).get("vertices", {}).get(name)
        if v:
            return n, v
    return "", {}


async def phase(
    cpu_s: float, rate: float, duration: float, hb: float, dead: float, moves: bool
) -> dict[str, Any]:
    """One fresh emulator: deploy, poll for ``duration`` (relocating), drain, read figures."""
    limit = max(1, int(rate * duration))
    emu = Emulator(loads_scenario(LINE3), manage=False, heartbeat_s=hb, dead_after_s=dead)
    loop = asyncio.get_running_loop()
    out: dict[str, Any] = {"cpu_s": cpu_s, "rate": rate, "duration_s": duration, "limit": limit}
    failures: dict[str, Any] = {}
    states: dict[str, int] = {}
    relocations: list[dict[str, Any]] = []
    try:
        await emu.start()
        reply = await emu.deploy(app_yaml(cpu_s, rate, limit), "heavy.yaml", "N1", check=True)
        out["placement"] = reply.placement
        t0 = loop.time()
        plan = [(duration / 3, "downstream"), (2 * duration / 3, "upstream")] if moves else []
        # a move of a busy vertex is answered at its handover (after the call in progress and
        # the events before the markers: seconds), so it runs beside the polls, on a connection
        # of its own, and the next waits for it
        mover = await emu.open_overlay("N1", name="heavy-mover") if moves else None
        moving: asyncio.Task[dict[str, Any]] | None = None

        async def move(direction: str, before: str) -> dict[str, Any]:
            assert mover is not None
            at = loop.time() - t0
            r = await mover.relocate(APP, "heavy", direction=direction, check=False)
            return {
                "at_s": round(at, 2),
                "direction": direction,
                "from": before,
                "to": r.node,
                "ok": r.ok,
                "elapsed_ms": r.elapsed_ms,
                "error": r.error,
            }

        while loop.time() < t0 + duration or moving is not None:
            await asyncio.sleep(POLL_S)
            nodes = await emu.status()
            for n, st in nodes.items():
                if st.get("failed_nodes") or st.get("failures"):
                    failures[n] = {"failed": st["failed_nodes"], "failures": st["failures"]}
            _, hv = vertex(nodes, "heavy")
            states[hv.get("state", "?")] = states.get(hv.get("state", "?"), 0) + 1
            if moving is not None and moving.done():
                relocations.append(moving.result())
                moving = None
            if moving is None and plan and loop.time() - t0 >= plan[0][0]:
                _, direction = plan.pop(0)
                moving = asyncio.ensure_future(move(direction, vertex(nodes, "heavy")[0]))
        if mover is not None:
            await mover.close()
        # the source stops at ``limit`` events; everything emitted reaches the sink
        deadline = loop.time() + DRAIN_S
        while True:
            nodes = await emu.status()
            _, src = vertex(nodes, "src")
            _, sink = vertex(nodes, "sink")
            stats = sink.get("stats") or {}
            if stats.get("next", 0) >= src.get("emitted", 0) or loop.time() > deadline:
                break
            await asyncio.sleep(POLL_S)
        out["drain_s"] = round(loop.time() - t0 - duration, 2)
        for n, st in nodes.items():
            if st.get("failed_nodes") or st.get("failures"):
                failures[n] = {"failed": st["failed_nodes"], "failures": st["failures"]}
        out["emitted"] = src.get("emitted", 0)
        out["sink"] = stats
        out["lost"] = stats.get("missing", 0)  # holes in the numbering
        out["undelivered"] = max(0, out["emitted"] - stats.get("next", 0))  # in the drain
        out["heavy"] = {k: v for k, v in vertex(nodes, "heavy")[1].items() if k != "last_error"}
        out["heavy_node"] = vertex(nodes, "heavy")[0]
        out["liveness"] = {n: st.get("liveness", {}) for n, st in nodes.items()}
    finally:
        await emu.stop()
    out["failures"] = failures
    out["states"] = states
    out["relocations"] = relocations
    return out


def beats(result: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per (observer, neighbour): heartbeat inter-arrival figures."""
    rows = []
    for obs, lv in sorted(result.get("liveness", {}).items()):
        period = lv.get("heartbeat_s", 0.1) * 1e3
        for nb, g in sorted(lv.get("inter_arrival", {}).items()):
            rows.append({"observer": obs, "neighbour": nb, "period_ms": period, **g})
            rows[-1]["late_p99_ms"] = round(g["p99_ms"] - period, 3)
    return rows


def render(result: dict[str, Any]) -> str:
    h = result["heavy_run"]
    load = result["machine"]["load_average"]
    lines = [
        f"### A {h['cpu_s']:g} s/event pure-Python vertex on a 3-node line "
        f"({h['duration_s']:g} s, {h['rate']:g} events/s, heartbeat {result['heartbeat_s']:g} s, "
        f"dead after {result['dead_after_s']:g} s)",
        "",
        f"Machine: {result['machine']['cpus']} vCPUs, load average at the end "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared; other engineers' tests ran meanwhile).",
        "",
        "| run | observer | neighbour | beats | inter-arrival p50 ms | p99 ms | max ms "
        "| p99 late ms |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for name in ("baseline_run", "heavy_run"):
        r = result.get(name)
        if not r:
            continue
        for b in beats(r):
            lines.append(
                f"| {name.removesuffix('_run')} | {b['observer']} | {b['neighbour']} | {b['n']} "
                f"| {b['p50_ms']:.1f} | {b['p99_ms']:.1f} | {b['max_ms']:.1f} "
                f"| {b['late_p99_ms']:.1f} |"
            )
    worst = max((b["late_p99_ms"] for b in beats(h)), default=0.0)
    lines += [
        "",
        f"- nodes declared failed: {h['failures'] or 'none'}",
        f"- events: emitted {h['emitted']}, at the sink {h['sink'].get('count')}, lost "
        f"{h['lost']}, still on the way after the drain {h.get('undelivered', 0)}, repeated "
        f"{h['sink'].get('repeats')}, out of order "
        f"{h['sink'].get('out_of_order')} (drained {h['drain_s']:g} s after the source stopped)",
        f"- `heavy`: {h['heavy'].get('processed')} events, {h['heavy'].get('cpu_s', 0):.1f} s "
        f"CPU; states seen by the polls: {h['states']}",
        "- relocations while it computed: "
        + (
            "; ".join(
                f"{r['direction']} {r['from']}->{r['to']} "
                + (f"ok in {r['elapsed_ms']:.0f} ms" if r["ok"] else f"FAILED: {r['error']}")
                for r in h["relocations"]
            )
            or "none"
        ),
        f"- worst p99 lateness (inter-arrival p99 minus the period) under the heavy vertex: "
        f"{worst:.1f} ms (target <= 50 ms: {'met' if worst <= 50 else 'NOT met'})",
    ]
    return "\n".join(lines) + "\n"


# -- threads versus processes, in this process ----------------------------------------------
TICK_S = 0.05


def _start(instance: int, code: str, params: dict[str, Any], kind: str = "operator") -> Any:
    from mso.model.app import Vertex
    from mso.protocol import effects as fx

    vertex = Vertex(f"v{instance}", code, params=params, input=Seq, output=Seq)
    return fx.StartVertex(instance, "bench", vertex, kind, {0: Seq})


async def _workload(kind: str, n: int, events: int, work: int, batch: int) -> dict[str, Any]:
    """``n`` instances of Burn(work) each fed ``events`` events in batches of ``batch``; a
    50 ms timer measures the loop's lateness meanwhile."""
    import msgspec

    from mso.protocol import effects as fx
    from mso.runtime.executor import ThreadExecutor
    from mso.runtime.process_lane import ProcessExecutor

    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    got = {"started": 0, "processed": 0}
    total = n * events

    def on_loop(res: Any) -> None:
        if isinstance(res, fx.VertexStarted):
            got["started"] += 1
        elif isinstance(res, fx.VertexProcessed):
            got["processed"] += res.count
        if got["started"] == n and (got["processed"] >= total):
            done.set()

    def deliver(res: Any) -> None:
        loop.call_soon_threadsafe(on_loop, res)

    ex: Any = ThreadExecutor(deliver) if kind == "threads" else ProcessExecutor(deliver)
    late: list[float] = []
    ticking = True

    async def ticker() -> None:
        due = loop.time()
        while ticking:
            due += TICK_S
            await asyncio.sleep(max(0.0, due - loop.time()))
            late.append(loop.time() - due)

    payload = msgspec.msgpack.encode(Seq(1, 0.0))
    try:
        for i in range(n):
            ex.submit(_start(i, f"{VERTICES}:Burn", {"work": work}))
        while got["started"] < n:  # processes start first (not timed)
            await asyncio.sleep(0.01)
        tick = asyncio.create_task(ticker())
        await asyncio.sleep(0.5)  # idle lateness first
        idle = len(late)
        t0 = loop.time()
        for i in range(n):
            for k in range(0, events, batch):
                ex.submit(fx.FeedVertex(i, 0, [payload] * min(batch, events - k), 0.0))
        await asyncio.wait_for(done.wait(), 300)
        elapsed = loop.time() - t0
        ticking = False
        await tick
    finally:
        ex.shutdown(2.0)
    busy = sorted(late[idle:])
    from mso.benchmarks.common import percentile

    return {
        "executor": kind,
        "vertices": n,
        "events_each": events,
        "work": work,
        "batch": batch,
        "elapsed_s": elapsed,
        "events_per_s": total / elapsed,
        "idle_late_p99_ms": percentile(sorted(late[:idle]), 99) * 1e3 if idle else None,
        "late_p50_ms": percentile(busy, 50) * 1e3 if busy else None,
        "late_p99_ms": percentile(busy, 99) * 1e3 if busy else None,
        "late_max_ms": max(busy) * 1e3 if busy else None,
        "ticks": len(busy),
    }


def _calibrate(target_s: float = 0.05) -> int:
    """Burn's ``work`` for about ``target_s`` of CPU per event on this machine."""
    w = 20_000
    t = time.thread_time()
    Burn(work=w)(Seq(0))
    per = (time.thread_time() - t) / w
    return max(1000, int(target_s / per))


def workers(events: int) -> dict[str, Any]:
    work = _calibrate()
    rows = []
    for kind in ("threads", "processes"):
        for n in (1, 2):
            rows.append(asyncio.run(_workload(kind, n, events, work, 1)))
        rows.append(asyncio.run(_workload(kind, 1, 20_000, 0, 256)))  # pass-through: IPC cost
    return {"benchmark": "heavy-workers", "work_per_event": work, "rows": rows}


def render_workers(result: dict[str, Any]) -> str:
    load = result["machine"]["load_average"]
    lines = [
        "### CPU-bound vertices: thread executor vs process lane (one node process, no network)",
        "",
        f"Machine: {result['machine']['cpus']} vCPUs, load average at the end "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared; other engineers' tests ran meanwhile). "
        f"Burn: {result['work_per_event']:,} rounds per event (~50 ms alone).",
        "",
        "| executor | vertices | work | events | events/s | 50 ms timer late p50 / p99 / max ms "
        "| idle p99 ms |",
        "|---|---:|---|---:|---:|---|---:|",
    ]

    def f(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f}"

    for r in result["rows"]:
        work = "pass-through" if not r["work"] else "burn ~50 ms"
        lines.append(
            f"| {r['executor']} | {r['vertices']} | {work} | {r['vertices'] * r['events_each']:,} "
            f"| {r['events_per_s']:,.1f} | {f(r['late_p50_ms'])} / {f(r['late_p99_ms'])} / "
            f"{f(r['late_max_ms'])} | {f(r['idle_late_p99_ms'])} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of flow (60)")
    ap.add_argument("--quick", action="store_true", help="20 s, 5 s baseline")
    ap.add_argument("--cpu", type=float, default=2.0, help="CPU seconds per event (2.0)")
    ap.add_argument("--rate", type=float, default=0.4, help="source events/s (0.4)")
    ap.add_argument("--baseline", type=float, default=10.0, help="seconds of the idle run")
    ap.add_argument("--heartbeat", type=float, default=0.1)
    ap.add_argument("--dead-after", type=float, default=0.5)
    ap.add_argument("--workers", action="store_true", help="threads vs processes, in-process")
    ap.add_argument("--events", type=int, default=40, help="--workers: events per vertex")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    args = ap.parse_args(argv)
    if args.workers:
        if not 1 <= args.events <= 1000:
            ap.error("--events: 1..1000")
        w = workers(10 if args.quick else args.events) | provenance()
        wout: Path = args.json or RESULTS / "heavy-workers.json"
        wout.write_text(json.dumps(w, indent=2) + "\n")
        wout.with_suffix(".md").write_text(render_workers(w))
        print(render_workers(w))
        return 0
    duration = 20.0 if args.quick else args.duration
    baseline = 5.0 if args.quick else args.baseline
    if not 5.0 <= duration <= 600.0 or not 0.0 <= baseline <= 120.0:
        ap.error("--duration: 5..600 s, --baseline: 0..120 s")
    if not 0.0 < args.cpu <= 10.0 or not 0.01 <= args.rate <= 10.0:
        ap.error("--cpu: 0..10 s, --rate: 0.01..10 events/s")
    out: Path = args.json or RESULTS / ("heavy-quick.json" if args.quick else "heavy.json")
    t0 = time.monotonic()
    hb, dead = args.heartbeat, args.dead_after
    result: dict[str, Any] = {"benchmark": "heavy", "heartbeat_s": hb, "dead_after_s": dead}
    if baseline:
        result["baseline_run"] = asyncio.run(phase(0.0, 5.0, baseline, hb, dead, False))
    result["heavy_run"] = asyncio.run(phase(args.cpu, args.rate, duration, hb, dead, True))
    result["seconds"] = time.monotonic() - t0
    result |= provenance()
    table = render(result)
    write_results(out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
