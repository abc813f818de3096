"""The simulator at scale (issue 24): start-up, CPU, memory and traffic against N; a mobile run;
a sweep on 1 and 2 workers.

1. **Sizes.** For N = 25, 50, 100, 200, 400, 1,000 on two generated topologies (``mso scenario
   generate``, seed 1: ``grid`` triangular, mean degree ~6, and ``geometric``, random geometric
   at mean degree 6), N/20 apps of 4 vertices (``pipelines``: a 5 events/s source and a sink
   pinned to two random nodes, two pass-throughs placed by Algorithm 1), each deployed from its
   source's node at t=0 with the wire encoding on and default heartbeats. Each size runs in a
   process of its own (so its peak RSS is its own) with a time limit. Figures: start-up (CPU
   seconds from building the simulation to the last deployment's reply, which comes at the
   virtual time given) and the peak RSS then; over the next ``--duration`` simulated seconds
   the CPU seconds per simulated second (and per node: the target is 1 ms), messages and bytes
   per node per second, and the heartbeats' share.
2. **Mobility.** 200 nodes, random geometric at mean degree 6, random waypoint at 1-5 m/s with
   links recomputed every 0.5 s, 10 apps, for ``--rwp-duration`` simulated seconds (300) or
   until its wall-time limit: CPU per simulated second, nodes declared failed, failed nodes
   still reachable at the end, membership messages per node per second, vertex moves.
3. **Sweep.** 100 runs (a 25-node grid, one app, ``--sweep-run-s`` simulated seconds each, 5 by
   default: ``mso.sim.sweep``) on 1 and then 2 workers (Ray when installed, else local
   processes): wall time of each, and their ratio; with Ray, its start and stop apart (as long
   as the runs themselves when they are short).

``--only sizes|rwp|sweep`` measures one part and puts it into the kept results (the other
parts stay as they were measured).

Usage: .venv/bin/python bench/scale.py [--sizes 25,50,...] [--topologies grid,geometric]
       [--duration 10] [--rwp-duration 300] [--sweep-runs 100] [--sweep-run-s 5]
       [--limit 1200] [--quick]
       [--only sizes|rwp|sweep]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import Progress, provenance, write_results

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
MEMBERSHIP = ("Heartbeat", "Suspect", "Hears", "NodeDown", "Rejoin", "Sync", "Probe")


def _scenario(topology: str, n: int, mobility: str = "none") -> Any:
    from mso.scenario.format import loads_scenario
    from mso.scenario.generate import Spec, dumps, generate

    spec = Spec(topology, n, seed=1, degree=6, mobility=mobility, speed=(1.0, 5.0))
    return loads_scenario(dumps(generate(spec), spec), file=f"{topology}-{n}.yaml")


def _rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _deploy(sim: Any, nodes: list[str], count: int) -> int:
    from mso.protocol import messages as m
    from mso.scenario.generate import pipelines

    apps = pipelines(nodes, count, seed=1, run="scale")
    for src, doc in apps:
        sim.request(src, m.DeployRequest(doc, f"<{src}>"))
    return len(apps)


def _replies(sim: Any) -> tuple[int, int]:
    from mso.protocol import messages as m

    replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    return len(replies), sum(r.ok for r in replies)


def one(topology: str, n: int, duration: float) -> dict[str, Any]:
    """One size, in this process: start-up, then ``duration`` simulated seconds."""
    from mso.sim.runner import Simulation

    t0, c0 = time.perf_counter(), time.process_time()
    sc = _scenario(topology, n)
    sim = Simulation(sc.network)
    apps = _deploy(sim, list(sc.network.nodes), max(1, n // 20))
    while _replies(sim)[0] < apps and sim.now < 30.0:  # bounded: 30 virtual seconds
        sim.run_until(sim.now + 0.1)
    startup_cpu, startup_wall = time.process_time() - c0, time.perf_counter() - t0
    startup_rss = _rss_mb()
    msgs0 = dict(sim.census.by_type)
    bytes0 = sum(b[0] for b in sim.bytes.values())
    t1, c1 = sim.now, time.process_time()
    sim.run_until(t1 + duration)
    cpu = time.process_time() - c1
    by_type = {k: v - msgs0.get(k, 0) for k, v in sim.census.by_type.items()}
    sent = sum(b[0] for b in sim.bytes.values()) - bytes0
    total = sum(by_type.values())
    per = n * duration
    return {
        "topology": topology,
        "nodes": n,
        "links": len(sc.network.links),
        "mean_degree": round(2 * len(sc.network.links) / n, 2),
        "apps": apps,
        "deployed": _replies(sim)[1],
        "startup_cpu_s": round(startup_cpu, 2),
        "startup_wall_s": round(startup_wall, 2),
        "startup_virtual_s": round(t1, 2),
        "startup_rss_mb": startup_rss,
        "duration_s": duration,
        "cpu_per_sim_s": round(cpu / duration, 3),
        "cpu_ms_per_node_per_sim_s": round(cpu / duration / n * 1e3, 3),
        "messages_per_node_s": round(total / per, 1),
        "heartbeats_per_node_s": round(by_type.get("Heartbeat", 0) / per, 1),
        "bytes_per_node_s": round(sent / per, 1),
        "end_rss_mb": _rss_mb(),
        "delivered": sim.delivered,
        "by_type": dict(sorted(by_type.items())),
    }


def rwp(n: int, duration: float, limit_s: float) -> dict[str, Any]:
    """``n`` nodes in random waypoint for ``duration`` simulated seconds (or until
    ``limit_s`` of wall time)."""
    from mso.scenario.timeline import Timeline
    from mso.sim.play import drive
    from mso.sim.runner import Simulation

    sc = _scenario("geometric", n, mobility="random_waypoint")
    sim = Simulation(sc.network)
    timeline = Timeline(sc, network=sim.network)
    apps = _deploy(sim, list(sc.network.nodes), max(1, n // 20))
    t0, c0 = time.perf_counter(), time.process_time()
    reached = 0.0
    while reached < duration and time.perf_counter() - t0 < limit_s:
        reached = min(duration, reached + 10.0)
        drive(sim, timeline, reached)
    cpu = time.process_time() - c0
    live = [x for x in sim.cores if x not in sim.killed]
    held = 0  # (node, peer) where node holds peer failed and reaches it
    for x in live:
        held += sum(1 for p in sim.cores[x].failed if sim.network.route(x, p) is not None)
    failures = {(f["node"], round(f["at"], 3)) for c in sim.cores.values() for f in c.failures}
    member = sum(v for k, v in sim.census.by_type.items() if k in MEMBERSHIP)
    total = sum(sim.census.by_type.values())
    return {
        "nodes": n,
        "apps": apps,
        "deployed": _replies(sim)[1],
        "asked_s": duration,
        "reached_s": reached,
        "wall_s": round(time.perf_counter() - t0, 1),
        "cpu_per_sim_s": round(cpu / max(reached, 1e-9), 3),
        "link_changes": sum(1 for _, w in timeline.played if w == "mobility"),
        "failures_declared": len(failures),
        "failed_but_reachable": held,
        "messages_per_node_s": round(total / n / max(reached, 1e-9), 1),
        "membership_per_node_s": round(member / n / max(reached, 1e-9), 1),
        "delivered": sim.delivered,
        "by_type": dict(sorted(sim.census.by_type.items())),
        "rss_mb": _rss_mb(),
    }


def sweep(runs: int, run_s: float = 5.0) -> dict[str, Any]:
    """``runs`` small runs on 1 worker, then on 2: wall time each. With Ray, its local
    instance is started before the runs and stopped after them, timed apart (``start_s_W``):
    7-8 s on this machine whatever the workers, as long as a 1-worker sweep of 5-s runs, so the
    runs' wall time (``wall_s_W``) is what scales with the workers, and ``total_s_W`` is both."""
    from mso.scenario.generate import Spec, dumps, generate, pipelines
    from mso.sim import sweep as sw

    spec = Spec("grid", 25, seed=1, degree=4)
    scenario = ("grid-25.yaml", dumps(generate(spec), spec))
    ((_, app),) = pipelines([f"N{i}" for i in range(1, 26)], 1, seed=1, run="sweep")
    policies = ["lifetime", "energy"]
    jobs = sw.jobs([scenario], ("app.yaml", app), policies, list(range(runs // 2)), run_s)
    backend = sw.backend_for("auto", None)
    out: dict[str, Any] = {"runs": len(jobs), "backend": backend, "run_s": run_s}
    for workers in (1, 2):
        t0 = time.perf_counter()
        ray = _ray_started(workers) if backend == "ray" else None
        t1 = time.perf_counter()
        try:
            rows = sw.execute(jobs, workers=workers, backend=backend)
        finally:
            t2 = time.perf_counter()
            if ray is not None:
                ray.shutdown()
        t3 = time.perf_counter()
        out[f"wall_s_{workers}"] = round(t2 - t1, 1)
        out[f"start_s_{workers}"] = round((t1 - t0) + (t3 - t2), 1)
        out[f"total_s_{workers}"] = round(t3 - t0, 1)
        out[f"ok_{workers}"] = sum(bool(r["deploy_ok"]) for r in rows)
        out[f"cpu_s_{workers}"] = round(sum(r["cpu_s"] for r in rows), 1)
    out["speedup"] = round(out["wall_s_1"] / out["wall_s_2"], 2)
    out["speedup_total"] = round(out["total_s_1"] / out["total_s_2"], 2)
    return out


def _ray_started(workers: int) -> Any:
    """A local Ray instance of ``workers`` CPUs, as :func:`mso.sim.sweep.execute` starts it
    (which then uses it and leaves it running)."""
    import os

    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    return ray


def _child(args: list[str], limit: float, script: str = __file__) -> dict[str, Any]:
    """Run one measurement in a fresh process (its own RSS), bounded by ``limit`` seconds."""
    try:
        done = subprocess.run(
            [sys.executable, script, *args], capture_output=True, text=True, timeout=limit
        )
    except subprocess.TimeoutExpired:
        return {"error": f"over the {limit:g} s limit"}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr else "failed"}
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def table(result: dict[str, Any]) -> str:
    lines = [
        "### The simulator at scale: start-up, CPU, memory and traffic against N",
        "",
        f"N/20 apps of 4 vertices, wire encoding on, default heartbeats; {result['duration_s']:g}"
        " simulated seconds after start-up. Targets at 1,000 nodes: start-up <= 30 s and"
        " <= 2 GB, <= 1 ms CPU per node per simulated second.",
        "",
        "| topology | N | degree | apps | deployed | start-up CPU s | (virtual s) | RSS MB"
        " | CPU s / sim s | CPU ms / node / sim s | msgs / node / s | of them heartbeats"
        " | bytes / node / s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["sizes"]:
        if "error" in r:
            lines.append(f"| {r['topology']} | {r['nodes']} | | | | {r['error']} | | | | | | | |")
            continue
        lines.append(
            f"| {r['topology']} | {r['nodes']} | {r['mean_degree']} | {r['apps']} |"
            f" {r['deployed']} | {r['startup_cpu_s']} | {r['startup_virtual_s']} |"
            f" {r['startup_rss_mb']} | {r['cpu_per_sim_s']} | {r['cpu_ms_per_node_per_sim_s']} |"
            f" {r['messages_per_node_s']} | {r['heartbeats_per_node_s']} |"
            f" {r['bytes_per_node_s']} |"
        )
    w = result.get("rwp")
    if w:
        lines += ["", "#### Random waypoint", ""]
        if "error" in w:
            lines.append(f"200 nodes: {w['error']}")
        else:
            lines += [
                "| N | apps | simulated s (asked) | wall s | CPU s / sim s | link changes"
                " | failures declared | failed but reachable at the end | msgs / node / s"
                " | membership msgs / node / s |",
                "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
                f"| {w['nodes']} | {w['apps']} | {w['reached_s']:g} ({w['asked_s']:g}) |"
                f" {w['wall_s']} | {w['cpu_per_sim_s']} | {w['link_changes']} |"
                f" {w['failures_declared']} | {w['failed_but_reachable']} |"
                f" {w['messages_per_node_s']} | {w['membership_per_node_s']} |",
            ]
    s = result.get("sweep")
    if s:
        lines += ["", "#### A sweep on 1 and 2 workers", ""]
        if "error" in s:
            lines.append(f"sweep: {s['error']}")
        else:
            lines += [
                "| runs | backend | s a run (simulated) | wall s, 1 worker | wall s, 2 workers"
                " | speed-up | Ray's start and stop s, 1 / 2 | with them: 1 / 2, speed-up |",
                "|---:|---|---:|---:|---:|---:|---:|---:|",
                f"| {s['runs']} | {s['backend']} | {s.get('run_s', 5.0):g} | {s['wall_s_1']} |"
                f" {s['wall_s_2']} | {s['speedup']}x | {s.get('start_s_1', '—')} /"
                f" {s.get('start_s_2', '—')} | {s.get('total_s_1', '—')} /"
                f" {s.get('total_s_2', '—')}, {s.get('speedup_total', '—')}x |",
            ]
    load = result["machine"]["load_average"]
    lines += ["", f"Load average when written: {load[0]:.1f} on {result['machine']['cpus']} CPUs."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=3, metavar=("TOPOLOGY", "N", "DURATION"), help=argparse.SUPPRESS)
    ap.add_argument("--rwp", nargs=3, metavar=("N", "DURATION", "LIMIT"), help=argparse.SUPPRESS)
    ap.add_argument("--sizes", default="25,50,100,200,400,1000")
    ap.add_argument("--topologies", default="grid,geometric")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rwp-duration", type=float, default=300.0)
    ap.add_argument("--sweep-runs", type=int, default=100)
    ap.add_argument("--sweep-run-s", type=float, default=5.0, help="Simulated s a sweep run.")
    ap.add_argument("--limit", type=float, default=1200.0, help="Wall seconds per measurement.")
    ap.add_argument("--quick", action="store_true", help="Sizes up to 100, short runs.")
    ap.add_argument(
        "--only", choices=("sizes", "rwp", "sweep"), help="One part, kept with the rest."
    )
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]), float(args.one[2]))))
        return
    if args.rwp:
        print(json.dumps(rwp(int(args.rwp[0]), float(args.rwp[1]), float(args.rwp[2]))))
        return
    sizes = [int(x) for x in args.sizes.split(",") if x]
    rwp_s, runs = args.rwp_duration, args.sweep_runs
    if args.quick:
        sizes, rwp_s, runs = [n for n in sizes if n <= 100], min(rwp_s, 20.0), min(runs, 8)
    say = Progress("scale")
    t0 = time.perf_counter()
    name = "scale-quick.json" if args.quick else "scale.json"
    result: dict[str, Any] = {"duration_s": args.duration, "sizes": []}
    if args.only:
        kept = RESULTS / name
        if kept.exists():
            result = json.loads(kept.read_text())
        if args.only != "sizes":
            sizes = []
        rwp_s = rwp_s if args.only == "rwp" else 0
        runs = runs if args.only == "sweep" else 0
        if args.only == "sizes":
            result |= {"duration_s": args.duration, "sizes": []}
    for topology in args.topologies.split(","):
        for n in sizes:
            say(f"{topology} {n}")
            r = _child(["--one", topology, str(n), str(args.duration)], args.limit)
            result["sizes"].append({"topology": topology, "nodes": n, **r})
    if rwp_s > 0:
        say(f"random waypoint 200 nodes, {rwp_s:g} s")
        result["rwp"] = _child(["--rwp", "200", str(rwp_s), str(args.limit)], args.limit + 120)
    if runs > 0:
        say(f"sweep of {runs} runs")
        try:
            result["sweep"] = sweep(runs, args.sweep_run_s)
        except Exception as exc:  # reported in the table, the rest is kept
            result["sweep"] = {"error": f"{type(exc).__name__}: {exc}"}
    result |= provenance()
    result["seconds"] = time.perf_counter() - t0
    kept = RESULTS / name
    if args.only and kept.exists():  # another part may have been written meanwhile: keep it
        part = {"sizes": ("sizes", "duration_s"), "rwp": ("rwp",), "sweep": ("sweep",)}
        latest = json.loads(kept.read_text())
        result = latest | {k: result[k] for k in part[args.only] if k in result} | provenance()
        result["seconds"] = time.perf_counter() - t0
    write_results(RESULTS / name, result, table(result))


if __name__ == "__main__":
    main()
