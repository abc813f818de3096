"""The energy study: the real convoy with battery-limited robots under four placements.

(a) everything on the leader (the `source` baseline), (b) Algorithm 1's placement kept for
good (rules off), (c) mso with its rules (default `lifetime` policy), (d) the optimal static
placement for energy per event (the ILP baseline). Each runs the convoy app
(examples/convoy.yaml, costs measured by `mso profile`) on examples/convoy-study.yaml in the
virtual-time simulator with ``model_time`` (each call takes its vertex's modelled CPU time):
the same node code as the daemon, the real vertex code, hours of battery in seconds. Static
placements are imposed by pinning every vertex where the placement puts it.

Reported per strategy: leader lifetime (its battery empty), network lifetime (first robot
empty), energy per stored result (all robots' joules until the run ends / rows stored),
results stored and their completeness (rows against events emitted), end-to-end delay
p50/p99 from the SQLite log, the relocations the rules made; plus a PNG per strategy of every
robot's battery over time with the relocations marked.

    mso bench lifetime [--out bench/results/lifetime.json] [--plots docs/img] [--limit-s S]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from mso.benchmarks.common import provenance, write_results
from mso.examples.convoy import storage
from mso.model.appfile import loads_app
from mso.planning.baselines import BASELINES
from mso.planning.placement import plan
from mso.protocol import messages as m
from mso.scenario import load_scenario
from mso.sim.runner import Simulation

ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = ROOT / "src" / "mso" / "examples"
APP_FILE = EXAMPLES / "convoy.yaml"
SCENARIO_FILE = EXAMPLES / "convoy-study.yaml"
LEADER = "N1"
STRATEGIES = ("all-on-leader", "algorithm1-kept", "mso-rules", "ilp-optimal")


def pinned_doc(doc: str, placement: dict[str, str]) -> str:
    """The app with every vertex pinned where ``placement`` puts it (a static placement)."""
    data = yaml.safe_load(doc)
    for v, attrs in data["vertices"].items():
        attrs["pinned"] = placement[v]
    return str(yaml.safe_dump(data, sort_keys=False))


def placement_for(strategy: str, doc: str) -> dict[str, str] | None:
    app = loads_app(doc, file=str(APP_FILE))
    net = load_scenario(SCENARIO_FILE).network
    if strategy == "all-on-leader":
        return dict(BASELINES["source"](app, net, seed=0, objective="energy"))
    if strategy == "ilp-optimal":
        return dict(BASELINES["optimal"](app, net, seed=0, objective="energy"))
    if strategy == "algorithm1-kept":
        return dict(plan(app, net).placement)
    return None  # mso-rules: Algorithm 1 as deployed, then the rules


def run(strategy: str, limit_s: float, db: Path, step_s: float = 5.0) -> dict[str, Any]:
    doc = APP_FILE.read_text(encoding="utf-8")
    placement = placement_for(strategy, doc)
    if placement is not None:
        doc = pinned_doc(doc, placement)
    scenario = load_scenario(SCENARIO_FILE)
    sim = Simulation(scenario.network, manage=strategy == "mso-rules", model_time=True)
    os.environ[storage.DB_ENV] = str(db)
    storage.set_clock(lambda: sim.now)
    try:
        sim.request(LEADER, m.DeployRequest(doc, "convoy.yaml"))
        sim.run_until(2.0)
        replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
        if not replies or not replies[0].ok:
            raise RuntimeError(f"{strategy}: deployment failed: {replies}")
        deployed = dict(replies[0].placement)
        mons = {n: c.monitor for n, c in sim.cores.items()}
        battery: dict[str, list[tuple[float, float]]] = {n: [] for n in mons}
        died: dict[str, float] = {}
        started = time.perf_counter()
        while sim.now < limit_s and LEADER not in died:
            sim.run_until(sim.now + step_s)
            for n, mon in mons.items():
                frac = (mon.remaining_j or 0.0) / (mon.capacity_j or 1.0)
                battery[n].append((round(sim.now, 1), round(frac, 5)))
                if frac <= 0.0 and n not in died:
                    died[n] = sim.now
        wall = time.perf_counter() - started
        emitted = {
            v: h.emitted
            for v, h in sim.cores[LEADER].apps["convoy"].stones.items()
            if v in ("laser", "visible_camera")
        }
        relocations = sorted(
            (float(d.split(" ", 1)[0]), d.split(" ", 1)[1])
            for c in sim.cores.values()
            for d in c.manager.done
        )
        final = {v: n for c in sim.cores.values() for v in c.apps["convoy"].stones for n in [c.id]}
    finally:
        storage.set_clock(time.monotonic)
        os.environ.pop(storage.DB_ENV, None)
    s = storage.summary(db)
    stored = s["trajectory"]["distinct"] + s["targets"]["distinct"]
    energy = sum(mon.energy_j for mon in mons.values())
    return {
        "strategy": strategy,
        "leader_lifetime_s": died.get(LEADER),
        "network_lifetime_s": min(died.values()) if died else None,
        "first_to_die": min(died, key=lambda n: died[n]) if died else None,
        "energy_j": round(energy, 2),
        "energy_per_result_j": round(energy / stored, 4) if stored else None,
        "results_stored": stored,
        "events_emitted": emitted,
        "complete": s["trajectory"]["gaps"] == s["trajectory"]["repeats"] == 0
        and s["targets"]["gaps"] == s["targets"]["repeats"] == 0
        and s["trajectory"]["distinct"] >= emitted.get("laser", 0) - 5
        and s["targets"]["distinct"] >= emitted.get("visible_camera", 0) - 1,
        "delay_ms_p50": s["delay_ms_p50"],
        "delay_ms_p99": s["delay_ms_p99"],
        "localization_error_m_max_straight": s["localization_error_m_max_straight"],
        "survivors_found": s["survivors_found"],
        "survivors_in_view": s["survivors_in_view"],
        "phantom_targets": s["phantom_targets"],
        "relocations": relocations,
        "placement_deployed": deployed,
        "placement_final": final,
        "average_drain_w": {
            n: round(mon.energy_j / max(sim.now - mon.started_at, 1e-9), 4)
            for n, mon in mons.items()
        },
        "battery": battery,
        "virtual_s": round(sim.now, 1),
        "wall_s": round(wall, 1),
    }


def plot(results: list[dict[str, Any]], out: Path) -> list[Path]:
    """One PNG per strategy: every robot's battery over time, the rules' relocations marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for r in results:
        fig, ax = plt.subplots(figsize=(6.4, 3.2), dpi=100)
        for node, series in r["battery"].items():
            ax.plot([t for t, _ in series], [100 * f for _, f in series], label=node)
        for t, _what in r["relocations"]:
            ax.axvline(t, color="grey", linestyle=":", linewidth=0.8)
        ax.set_title(f"{r['strategy']}: battery per robot" + (
            f" ({len(r['relocations'])} relocations, dotted)" if r["relocations"] else ""
        ))  # fmt: skip
        ax.set_xlabel("virtual time (s)")
        ax.set_ylabel("battery (%)")
        ax.set_ylim(0, 101)
        ax.legend(loc="lower left", fontsize=8)
        fig.tight_layout()
        path = out / f"lifetime-{r['strategy']}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


def markdown(results: list[dict[str, Any]]) -> str:
    def fmt(x: float | None, spec: str = ".0f") -> str:
        return "-" if x is None else format(x, spec)

    lines = [
        "| strategy | leader lifetime (s) | network lifetime (s) | energy / stored result (J) "
        "| results stored (complete) | e2e p50 / p99 (ms) | relocations |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r['strategy']} | {fmt(r['leader_lifetime_s'])} | "
            f"{fmt(r['network_lifetime_s'])} | {fmt(r['energy_per_result_j'], '.3f')} | "
            f"{r['results_stored']} ({'yes' if r['complete'] else 'NO'}) | "
            f"{fmt(r['delay_ms_p50'], '.1f')} / {fmt(r['delay_ms_p99'], '.1f')} | "
            f"{len(r['relocations'])} |"
        )
    by = {r["strategy"]: r for r in results}

    def ratio(a: str, b: str, key: str) -> str:
        x, y = by[a][key], by[b][key]
        return "-" if not x or not y else f"{x / y:.2f}×"

    lines += [
        "",
        f"Leader lifetime, rules against all-on-leader: "
        f"{ratio('mso-rules', 'all-on-leader', 'leader_lifetime_s')} (target ≥ 4×); against "
        f"Algorithm 1 kept: {ratio('mso-rules', 'algorithm1-kept', 'leader_lifetime_s')} "
        f"(target ≥ 2×). Network lifetime, rules against Algorithm 1 kept: "
        f"{ratio('mso-rules', 'algorithm1-kept', 'network_lifetime_s')} (target ≥ 1.3×). "
        f"Energy per stored result, rules against the ILP optimum: "
        f"{ratio('mso-rules', 'ilp-optimal', 'energy_per_result_j')} (target ≤ 1.10×).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--limit-s", type=float, default=3600.0, help="virtual time cap per run")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "lifetime.json")
    ap.add_argument("--plots", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--only", choices=STRATEGIES, action="append", help="run these only")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = []
    with tempfile.TemporaryDirectory(prefix="mso-lifetime-") as tmp:
        for strategy in args.only or STRATEGIES:
            results.append(run(strategy, args.limit_s, Path(tmp) / f"{strategy}.sqlite"))
            print(f"{strategy}: done in {results[-1]['wall_s']} s", flush=True)
    plots = plot(results, args.plots)
    table = markdown(results)
    result = {
        "scenario": str(SCENARIO_FILE.relative_to(ROOT)),
        "app": str(APP_FILE.relative_to(ROOT)),
        "results": results,
        "plots": [str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p) for p in plots],
        "seconds": time.perf_counter() - t0,
        **provenance(),
    }
    write_results(args.out, result, table)
    return 0
