"""Where a node's memory goes against N (issue 24: "per-node memory independent of N beyond
what its own apps need").

Builds ``bench/scale.py``'s scenario (a generated grid or random geometric graph, seed 1, N/20
apps of 4 vertices deployed from their sources' nodes, the wire encoding on, default
heartbeats), runs the start-up and ``--settle`` simulated seconds, then walks the objects each
node's core reaches (``gc.get_referents`` and ``sys.getsizeof``, a dict's keys too), one
component (an attribute of the core, or of its membership, data plane, ...) at a time, and then
the simulator's own structures. An object is charged once, to the first node or component that
reaches it (a ``Layout`` shared by every node that holds its app is charged to the first), so
the columns add up to the heap the walk saw; classes, modules, functions and bound methods are
not walked (they are code, or a way back into a core or the simulator).

Per component: the mean bytes per node (the total over all nodes / N: what N nodes cost, shared
objects included) and the median over the nodes that host no instance and over those that host
one (what one node holds of its own). Each size runs in a process of its own, so its RSS is its
own.

Usage: .venv/bin/python bench/node_memory.py [--sizes 100,200,400,1000]
       [--topologies grid,geometric] [--settle 2] [--limit 1200]
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE))


def measure(topology: str, n: int, settle: float) -> dict[str, Any]:
    """One size, in this process: start-up, ``settle`` simulated seconds, then the walk."""
    from mso.benchmarks.footprint import Walker, by_component
    from mso.sim.runner import Simulation
    from scale import _deploy, _replies, _rss_mb, _scenario

    c0 = time.process_time()
    sc = _scenario(topology, n)
    sim = Simulation(sc.network)
    apps = _deploy(sim, list(sc.network.nodes), max(1, n // 20))
    while _replies(sim)[0] < apps and sim.now < 30.0:  # bounded: 30 virtual seconds
        sim.run_until(sim.now + 0.1)
    sim.run_until(sim.now + settle)
    startup_cpu = time.process_time() - c0
    rss = _rss_mb()
    gc.collect()
    cores = sim.cores
    walker = Walker([sim, sim.network, cores, *cores.values()])
    per_node: dict[str, dict[str, int]] = {}
    apps_held: dict[str, int] = {}
    hosts: set[str] = set()
    c1 = time.process_time()
    for x, core in cores.items():
        row = by_component(walker, core)
        row["apps held, all"] = sum(v for k, v in row.items() if k.startswith("apps"))
        per_node[x] = dict(row)
        apps_held[x] = len(core.apps)
        if any(dep.instances for dep in core.apps.values()):
            hosts.add(x)
    simulator: dict[str, int] = {}
    for name, val in vars(sim).items():
        if name != "cores":
            simulator[name] = walker.size(val)
    walk_cpu = time.process_time() - c1
    names = sorted({k for r in per_node.values() for k in r})
    idle = [x for x in cores if x not in hosts]
    rows: list[dict[str, Any]] = []
    for k in names:
        vals = [per_node[x].get(k, 0) for x in cores]
        rows.append(
            {
                "component": k,
                "mean": round(sum(vals) / n),
                "median_idle": round(statistics.median([per_node[x].get(k, 0) for x in idle]))
                if idle
                else 0,
                "median_host": round(statistics.median([per_node[x].get(k, 0) for x in hosts]))
                if hosts
                else 0,
                "max": max(vals),
            }
        )
    rows.sort(key=lambda r: -int(r["mean"]))
    node_total = sum(
        sum(v for k, v in r.items() if k != "apps held, all") for r in per_node.values()
    )
    return {
        "topology": topology,
        "nodes": n,
        "apps": apps,
        "deployed": _replies(sim)[1],
        "hosts": len(hosts),
        "apps_held_median": statistics.median(apps_held.values()),
        "app_held_bytes": round(
            sum(per_node[x]["apps held, all"] for x in idle)
            / max(1, sum(apps_held[x] for x in idle))
        ),
        "startup_cpu_s": round(startup_cpu, 2),
        "walk_cpu_s": round(walk_cpu, 2),
        "rss_mb": rss,
        "nodes_bytes_per_node": round(node_total / n),
        "simulator_bytes_per_node": round(sum(simulator.values()) / n),
        "components": rows,
        "simulator": dict(sorted(simulator.items(), key=lambda kv: -kv[1])),
    }


def _kb(b: float) -> str:
    return f"{b / 1024:,.1f}"


def table(result: dict[str, Any], top: int = 14) -> str:
    runs = [r for r in result["sizes"] if "error" not in r]
    lines = [
        "### Where a node's memory goes against N",
        "",
        f"bench/scale.py's scenario, {result['settle_s']:g} simulated seconds after start-up;"
        " KiB per node by component (mean over all nodes: total / N, shared objects charged"
        " once; median over nodes hosting no instance / hosting one).",
        "",
        "| topology | N | apps | hosts | apps held (median) | bytes per app held (idle nodes)"
        " | RSS MB | nodes' heap KiB / node | simulator's heap KiB / node |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["sizes"]:
        if "error" in r:
            lines.append(f"| {r['topology']} | {r['nodes']} | {r['error']} | | | | | | |")
            continue
        lines.append(
            f"| {r['topology']} | {r['nodes']} | {r['apps']} | {r['hosts']} |"
            f" {r['apps_held_median']:g} | {r['app_held_bytes']:,} | {r['rss_mb']} |"
            f" {_kb(r['nodes_bytes_per_node'])} |"
            f" {_kb(r['simulator_bytes_per_node'])} |"
        )
    for topology in dict.fromkeys(r["topology"] for r in runs):
        mine = [r for r in runs if r["topology"] == topology]
        big = mine[-1]
        keys = [
            c["component"]
            for c in big["components"]
            if not c["component"].startswith("apps") or c["component"] == "apps held, all"
        ]
        keys = keys[:top]
        lines += [
            "",
            f"#### {topology}: KiB per node, mean (median idle / median host)",
            "",
            "| component | " + " | ".join(f"N={r['nodes']}" for r in mine) + " |",
            "|---|" + "---:|" * len(mine),
        ]
        for k in keys:
            cells = []
            for r in mine:
                c = next((c for c in r["components"] if c["component"] == k), None)
                cells.append(
                    "0"
                    if c is None
                    else f"{_kb(c['mean'])} ({_kb(c['median_idle'])} / {_kb(c['median_host'])})"
                )
            lines.append(f"| {k} | " + " | ".join(cells) + " |")
        skeys = list(big["simulator"])[:6]
        lines.append(
            "| *simulator:* "
            + ", ".join(skeys)
            + " | "
            + " | ".join(
                _kb(sum(r["simulator"].get(k, 0) for k in skeys) / r["nodes"]) for r in mine
            )
            + " |"
        )
    load = result["machine"]["load_average"]
    lines += ["", f"Load average when written: {load[0]:.1f} on {result['machine']['cpus']} CPUs."]
    return "\n".join(lines) + "\n"


def main() -> None:
    from mso.benchmarks.common import Progress, provenance, write_results
    from scale import _child

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=3, metavar=("TOPOLOGY", "N", "SETTLE"), help=argparse.SUPPRESS)
    ap.add_argument("--sizes", default="100,200,400,1000")
    ap.add_argument("--topologies", default="grid,geometric")
    ap.add_argument("--settle", type=float, default=2.0)
    ap.add_argument("--limit", type=float, default=1200.0, help="Wall seconds per size.")
    ap.add_argument("--out", default="node_memory.json")
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure(args.one[0], int(args.one[1]), float(args.one[2]))))
        return
    say = Progress("node_memory")
    t0 = time.perf_counter()
    result: dict[str, Any] = {"settle_s": args.settle, "sizes": []}
    for topology in args.topologies.split(","):
        for n in (int(x) for x in args.sizes.split(",") if x):
            say(f"{topology} {n}")
            r = _child(["--one", topology, str(n), str(args.settle)], args.limit, __file__)
            result["sizes"].append({"topology": topology, "nodes": n, **r})
    result |= provenance()
    result["seconds"] = time.perf_counter() - t0
    write_results(RESULTS / args.out, result, table(result))


if __name__ == "__main__":
    main()
