"""Placement at deploy time (issue 25): the paper's split, the bytes planner and the ILP optimum.

For each case: energy per event (:func:`mso.planning.objectives.energy_per_event`, mJ) and
end-to-end hops of Algorithm 1 with ``planner: paper``, with ``planner: bytes``, and of the exact
optimum of energy within every node's CPU capacity (``optimal(..., capacity=True)``). Cases: the
convoy on its 4-node line, the camera pipeline on a 5-node line, the paper's Fig. 2 app on
line4, and 50 seeded random apps (1-2 pinned sources at 1-10 Hz, 3-8 operators of cost 0.5-20,
pinned sinks, edge sizes log-uniform 16 B-64 KB) on random connected topologies of 5-30 nodes
(cpu 0.5-2, tx 1-4 / rx 0.5-2 µJ per byte, cpu_w 2-8 W). Also the planning time of ``plan``
for a 126-vertex app on 30 nodes (CPU time of the planning thread, median and fastest of 20).

After a remap and after a recovery: the camera pipeline deployed with ``planner: paper`` once
the rules moved ``downscale`` to R1, remapped globally and recovered from its tracker's node
failing, in the simulator, with remaps that start from the current placement and with remaps
that replan (the old way): which vertices moved against the placement before, and the energy
per event after.

A slow link: a camera's 4 Mb/s frames, a slow CPU beside them and a 2 Mb/s first link, planned
with and without the probed link rates: where ``downscale`` goes, the energy, the slow link's
load and the time an event spends on the air.

Usage: .venv/bin/python bench/placement.py [--random 50] [--seed 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import random
import statistics
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import src_digest
from mso.model.app import App
from mso.model.appfile import load_app
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.planning import baselines
from mso.planning.objectives import (
    busiest_cpu,
    busiest_link,
    end_to_end_hops,
    energy_per_event,
    route_tables,
)
from mso.planning.placement import plan
from mso.scenario import load_scenario

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
EXAMPLES = ROOT / "examples"


def random_network(rng: random.Random, n: int) -> Network:
    """A connected random MANET: a random spanning tree plus nearby extra links."""
    nodes = [
        NodeSpec(
            f"n{i}",
            cpu=rng.choice([0.5, 1.0, 1.0, 1.5, 2.0]),
            power=PowerModel(
                cpu_w=rng.uniform(2, 8),
                tx_uj_per_byte=rng.uniform(1, 4),
                rx_uj_per_byte=rng.uniform(0.5, 2),
            ),
        )
        for i in range(n)
    ]
    links = [LinkSpec(f"n{rng.randrange(i)}", f"n{i}") for i in range(1, n)]
    have = {tuple(sorted((lk.a, lk.b))) for lk in links}
    for _ in range(n // 2):
        a, b = rng.sample(range(n), 2)
        key = tuple(sorted((f"n{a}", f"n{b}")))
        if key not in have and abs(a - b) <= 3:
            have.add(key)
            links.append(LinkSpec(*key))
    return Network(nodes, links)


def random_app(rng: random.Random, net: Network, n_ops: int | None = None) -> App:
    nodes = list(net.nodes)
    app = App("random")
    order: list[str] = []
    for s in range(rng.randint(1, 2)):
        app.vertex(
            f"s{s}", pinned=rng.choice(nodes), cost=rng.uniform(0.5, 5), rate=rng.randint(1, 10)
        )
        order.append(f"s{s}")

    def size() -> int:
        return int(math.exp(rng.uniform(math.log(16), math.log(65536))))

    ops = n_ops if n_ops is not None else rng.randint(3, 8)
    for i in range(ops):
        v = f"o{i}"
        app.vertex(v, cost=rng.uniform(0.5, 20))
        preds = {rng.choice(order[-3:])}
        if rng.random() < 0.2:
            preds.add(rng.choice(order))
        for p in sorted(preds):
            app.edge(p, v, size=size())
        order.append(v)
    has_out = {e.src for e in app.edges}
    leaves = [v for v in order if v not in has_out]
    for k, leaf in enumerate(leaves):
        app.vertex(f"t{k}", pinned=rng.choice(nodes), cost=rng.uniform(0.5, 2))
        app.edge(leaf, f"t{k}", size=size())
    return app.validate(resolve_code=False)


def score(app: App, net: Network) -> dict[str, Any]:
    t = route_tables(net)
    out: dict[str, Any] = {}
    for name in ("paper", "bytes"):
        pl = plan(app, net, planner=name).placement
        out[name] = {
            "energy_mj": energy_per_event(app, net, pl, tables=t) * 1e3,
            "hops": end_to_end_hops(app, net, pl, tables=t),
            "peak_load": busiest_cpu(app, net, pl),
        }
    try:
        opt = baselines.optimal(app, net, "energy", time_limit=60.0)
        out["ilp"] = {
            "energy_mj": energy_per_event(app, net, opt, tables=t) * 1e3,
            "hops": end_to_end_hops(app, net, opt, tables=t),
        }
    except Exception as exc:
        out["ilp"] = {"error": str(exc)}
    return out


def slow_link_case() -> dict[str, Any]:
    """A link too slow for an edge energy alone would put on it: a 10 Hz camera's 50 KB frames
    (4 Mb/s) on R1, whose CPU is slow (cpu 0.1: downscaling there costs 200 mJ per event
    against 170 mJ for carrying the frame to R2 and downscaling there), and a 2 Mb/s R1-R2
    link. The bytes planner with the probed rates, the same planner with no rates known
    (energy alone), the paper's split and the ILP optimum of energy with and without the links'
    rates (within every CPU both)."""
    app = load_app(EXAMPLES / "camera-slow.yaml", resolve_code=False)
    shaped = load_scenario(EXAMPLES / "slow-link.yaml").network
    unshaped = Network(
        list(shaped.nodes.values()),
        [dataclasses.replace(lk, bandwidth_mbps=None) for lk in shaped.links.values()],
    )
    placements = {
        "paper": plan(app, shaped, planner="paper").placement,
        "bytes, energy alone (no rates probed)": plan(app, unshaped, planner="bytes").placement,
        "bytes, energy and link rates": plan(app, shaped, planner="bytes").placement,
        "ILP optimum of energy, no rates": baselines.optimal(app, unshaped, "energy"),
        "ILP optimum of energy within the links' rates": baselines.optimal(app, shaped, "energy"),
    }
    out: dict[str, Any] = {}
    for name, pl in placements.items():
        air_ms = 0.0
        for e in app.edges:
            route = shaped.route(pl[e.src], pl[e.dst]) or []
            for a, b in itertools.pairwise(route):
                bw = shaped.link(a, b).bandwidth_mbps  # type: ignore[union-attr]
                if bw:
                    air_ms += (e.size or 0) * 8 / (bw * 1e6) * 1e3
        out[name] = {
            "downscale": pl["downscale"],
            "energy_mj": energy_per_event(app, shaped, pl) * 1e3,
            "slow_link_load": busiest_link(app, shaped, pl),
            "air_ms_per_event": air_ms,
        }
    return out


def planning_time(seed: int, reps: int = 20) -> dict[str, float]:
    rng = random.Random(seed)
    net = random_network(rng, 30)
    app = random_app(rng, net, n_ops=96)
    out = {"vertices": float(len(app.vertices)), "nodes": 30.0}
    names = ("paper", "bytes")
    times: dict[str, list[float]] = {name: [] for name in names}
    for name in names:
        plan(app, net, planner=name)  # warm: the first run pays for imports and caches
    for _ in range(reps):  # interleaved, so both splits see the same load on a shared machine
        for name in names:
            t0 = time.thread_time()  # CPU time: on a shared machine wall time counts others'
            plan(app, net, planner=name)
            times[name].append(time.thread_time() - t0)
    for name in names:
        out[f"{name}_ms"] = statistics.median(times[name]) * 1e3
        out[f"{name}_min_ms"] = min(times[name]) * 1e3  # on a shared machine, the least disturbed
    return out


AROUND_R4 = [("R3", "R6"), ("R6", "R7"), ("R7", "R5")]


def _camera_sim(net: Network) -> Any:
    from mso.model.appfile import with_planner
    from mso.protocol import messages as m
    from mso.sim.runner import Simulation

    sim = Simulation(net)
    # deployed with the paper's split, which puts downscale on R2 (the default bytes split puts
    # it on R1 from the start): the remaps then re-place with the paper's split too
    doc = with_planner((EXAMPLES / "camera.yaml").read_text(), "paper")
    sim.request("R1", m.DeployRequest(doc, "camera.yaml"))
    sim.run_until(1.0)
    # the rules' move issue 25 describes (downscale: R2 -> R1), here asked for directly
    sim.request("R2", m.RelocateRequest("camera", "downscale", target="R1"))
    sim.run_until(sim.now + 1.0)
    return sim


def after_remaps() -> dict[str, Any]:
    """The camera pipeline after the rules moved ``downscale`` to R1, then (a) "remap the app"
    (a global remap) on camera-line.yaml, (b) a recovery from the tracker's node failing (a
    5-node line with a longer way around R4): how many vertices changed node against the placement
    just before, and the energy per event after, with remaps that start from the current
    placement and with remaps that take the new plan whatever (the behaviour before)."""
    from mso.protocol import messages as m
    from mso.protocol.procedures import remap as remap_mod

    app = load_app(EXAMPLES / "camera.yaml", resolve_code=False)
    keep = remap_mod.KEEP_MARGIN
    out: dict[str, Any] = {}
    try:
        for mode, margin in (("keeps", keep), ("replans", -1e18)):
            remap_mod.KEEP_MARGIN = margin
            line = load_scenario(EXAMPLES / "camera-line.yaml").network  # a run changes it
            bypass = Network(  # a longer way around R4: R3-R6-R7-R5
                [*line.nodes.values(), NodeSpec("R6"), NodeSpec("R7")],
                [*line.links.values(), *(LinkSpec(a, b) for a, b in AROUND_R4)],
            )
            sim = _camera_sim(line)
            before = dict(sim.cores["R1"].placement("camera"))
            sim.request("R3", m.RemapRequest("camera", [], everything=True))
            sim.run_until(sim.now + 2.0)
            after = dict(sim.cores["R1"].placement("camera"))
            remap = {
                "changed": sorted(v for v in after if after[v] != before[v]),
                "energy_mj_before": energy_per_event(app, line, before) * 1e3,
                "energy_mj_after": energy_per_event(app, line, after) * 1e3,
            }
            sim = _camera_sim(bypass)
            before = dict(sim.cores["R1"].placement("camera"))
            victim = before["tracker"]
            sim.kill(victim, convergence_s=0.3)
            sim.run_until(sim.now + 10.0)
            after = dict(sim.cores["R1"].placement("camera"))
            recovery = {
                "failed": victim,
                "changed": sorted(v for v in after if after[v] != before[v]),
                "energy_mj_after": energy_per_event(app, bypass, after) * 1e3,
            }
            out[mode] = {"remap": remap, "recovery": recovery}
    finally:
        remap_mod.KEEP_MARGIN = keep
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--random", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    baselines.MAX_ILP_VARIABLES = 500_000  # a benchmark's yardstick may be large
    cases: dict[str, Any] = {}
    for name, app_file, net_file in [
        ("convoy", "convoy.yaml", "convoy-line.yaml"),
        ("camera", "camera.yaml", "camera-line.yaml"),
        ("fig2", "fig2.yaml", "line4.yaml"),
    ]:
        app = load_app(EXAMPLES / app_file, resolve_code=False)
        cases[name] = score(app, load_scenario(EXAMPLES / net_file).network)
    rng = random.Random(args.seed)
    rand = []
    for i in range(args.random):
        net = random_network(rng, rng.randint(5, 30))
        app = random_app(rng, net)
        r = score(app, net)
        r["nodes"], r["vertices"], r["index"] = len(net.nodes), len(app.vertices), i
        rand.append(r)
    ok = [r for r in rand if "error" not in r["ilp"]]

    def ratios(key: str) -> list[float]:
        return sorted(r[key]["energy_mj"] / r["ilp"]["energy_mj"] for r in ok)

    fits = [r for r in rand if r["paper"]["peak_load"] <= 1 + 1e-9]
    summary: dict[str, Any] = {
        "random_cases": len(rand),
        "random_with_ilp": len(ok),
        "paper_over_ilp": {
            "median": statistics.median(ratios("paper")),
            "worst": max(ratios("paper")),
        },
        "bytes_over_ilp": {
            "median": statistics.median(ratios("bytes")),
            "worst": max(ratios("bytes")),
        },
        "bytes_over_paper": {
            "median": statistics.median(
                r["bytes"]["energy_mj"] / r["paper"]["energy_mj"] for r in rand
            ),
            "worst": max(r["bytes"]["energy_mj"] / r["paper"]["energy_mj"] for r in rand),
        },
        # the paper's split ignores capacity: against it only where it fits
        "bytes_over_paper_within_capacity": {
            "cases": len(fits),
            "worst": max(r["bytes"]["energy_mj"] / r["paper"]["energy_mj"] for r in fits),
        },
        "paper_over_capacity": [r["index"] for r in rand if r["paper"]["peak_load"] > 1 + 1e-9],
        "hops_bytes_minus_paper": {
            "median": statistics.median(r["bytes"]["hops"] - r["paper"]["hops"] for r in rand),
            "worst": max(r["bytes"]["hops"] - r["paper"]["hops"] for r in rand),
        },
    }
    timing = planning_time(args.seed)
    remaps = after_remaps()
    slow = slow_link_case()
    result = {
        "src": src_digest(),
        "seed": args.seed,
        "cases": cases,
        "random": rand,
        "summary": summary,
        "planning_time": timing,
        "after_remaps": remaps,
        "slow_link": slow,
    }
    out_dir = HERE / "results"
    out_dir.mkdir(exist_ok=True)
    (out_dir / "placement.json").write_text(json.dumps(result, indent=1))
    lines = [
        "| case | paper mJ/event (hops) | bytes mJ/event (hops) "
        "| ILP within capacity mJ/event (hops) | bytes / ILP |",
        "|---|---|---|---|---|",
    ]
    for name, c in cases.items():
        ilp = c["ilp"]
        ilp_s = f"{ilp['energy_mj']:.3f} ({ilp['hops']:g})" if "error" not in ilp else "n/a"
        ratio = (
            f"{c['bytes']['energy_mj'] / ilp['energy_mj']:.2f}×" if "error" not in ilp else "n/a"
        )
        lines.append(
            f"| {name} | {c['paper']['energy_mj']:.3f} ({c['paper']['hops']:g}) "
            f"| {c['bytes']['energy_mj']:.3f} ({c['bytes']['hops']:g}) | {ilp_s} | {ratio} |"
        )
    s = summary
    lines.append(
        f"| {len(rand)} random, / ILP ({len(ok)} solved): median | "
        f"{s['paper_over_ilp']['median']:.2f}× | {s['bytes_over_ilp']['median']:.2f}× | 1 | |"
    )
    lines.append(
        f"| {len(rand)} random, / ILP: worst | {s['paper_over_ilp']['worst']:.2f}× "
        f"| {s['bytes_over_ilp']['worst']:.2f}× | 1 | |"
    )
    lines.append("")
    lines.append(
        f"bytes / paper on the random set: median {s['bytes_over_paper']['median']:.2f}×, "
        f"worst {s['bytes_over_paper']['worst']:.2f}× (on the "
        f"{s['bytes_over_paper_within_capacity']['cases']} cases where the paper's split fits "
        f"every node's CPU: worst {s['bytes_over_paper_within_capacity']['worst']:.2f}×; it "
        f"overloads a node on cases {s['paper_over_capacity']}); "
        "end-to-end hops bytes − paper: median "
        f"{s['hops_bytes_minus_paper']['median']:+g}, "
        f"worst {s['hops_bytes_minus_paper']['worst']:+g}. "
        f"Planning time, {timing['vertices']:g} vertices on 30 nodes (`plan`, CPU ms, median of "
        f"20; fastest): paper {timing['paper_ms']:.2f} ms ({timing['paper_min_ms']:.2f}), "
        f"bytes {timing['bytes_ms']:.2f} ms ({timing['bytes_min_ms']:.2f})."
    )
    lines += [
        "",
        "| camera pipeline, after the rules moved downscale to R1 | vertices moved | "
        "mJ/event after |",
        "|---|---|---|",
    ]
    for mode, label in (("keeps", "starts from the current placement"), ("replans", "replans")):
        r = remaps[mode]
        for what in ("remap", "recovery"):
            x = r[what]
            lost = f" (failed {x['failed']})" if what == "recovery" else ""
            name = "global remap" if what == "remap" else "recovery"
            lines.append(
                f"| {name}{lost}, remap {label} | {', '.join(x['changed']) or 'none'} "
                f"| {x['energy_mj_after']:.1f} |"
            )
    lines += [
        "",
        "| slow link: 10 Hz 50 KB frames, R1 cpu 0.1, R1-R2 at 2 Mb/s | downscale on "
        "| mJ/event | R1-R2 load (of its rate) | ms on the air per event |",
        "|---|---|---|---|---|",
    ]
    for name, r in slow.items():
        lines.append(
            f"| {name} | {r['downscale']} | {r['energy_mj']:.1f} | {r['slow_link_load']:.0%} "
            f"| {r['air_ms_per_event']:.1f} |"
        )
    md = "\n".join(lines) + "\n"
    (out_dir / "placement.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
