"""The energy study: the real convoy with battery-limited robots under four placements.

(a) everything on the leader (the `source` baseline), (b) Algorithm 1's placement kept for
good (rules off), (c) mso with its rules (default `lifetime` policy), (d) the optimal static
placement for energy per event (the ILP baseline). Each runs the convoy app
(examples/convoy.yaml, costs measured by `mso profile`) on examples/convoy-study.yaml in the
virtual-time simulator with ``model_time`` (each call takes its vertex's modelled CPU time):
the same node code as the daemon, the real vertex code, hours of battery in seconds. Static
placements are imposed by pinning every vertex where the placement puts it.

Two accountings, each a full set of runs:

- ``board``: the whole board drains the battery — idle power included (a Raspberry Pi 3 B
  idles at ~1.1 W, which no placement changes);
- ``app``: only the energy the app causes drains it — CPU above idle and radio, the budget a
  MagnetOS-style study counts (idle_w 0, a smaller battery so a run still ends).

Reported per strategy: leader lifetime (its battery empty), network lifetime (first robot
empty), energy per stored result — all robots' joules / rows stored, over the whole run (the
app's own share beside it) and while every robot lives (past the first robot's end its joules
are in no battery, and in a line the app would be cut there) — results stored and their
completeness (rows against events emitted), end-to-end delay p50/p99 from the SQLite log, the
relocations and remaps the rules made; plus a PNG per accounting of every robot's battery
over time, one panel per strategy, the relocations (dotted) and remaps (dashed) marked. A
robot whose battery is empty keeps running in the simulation (its time of death is recorded),
so the leader's lifetime is measured even when a relay dies first.

    mso bench lifetime [--out bench/results/lifetime.json] [--plots docs/img] [--limit-s S]
                       [--accounting board|app] [--only STRATEGY]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from mso.benchmarks.common import provenance, write_results
from mso.examples.convoy import storage
from mso.management import RuleSettings
from mso.model.appfile import loads_app, with_planner
from mso.model.network import Network
from mso.planning.baselines import BASELINES
from mso.planning.placement import plan
from mso.protocol import messages as m
from mso.scenario import load_scenario
from mso.sim.runner import Simulation

ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = ROOT / "src" / "mso" / "examples"
APP_FILE = EXAMPLES / "convoy.yaml"
# the study weighs the rules against Algorithm 1 as the paper splits chains (its figures were
# measured so); the default bytes split starts nearer the optimum (docs/benchmarks.md)
PLANNER = "paper"
SCENARIO_FILE = EXAMPLES / "convoy-study.yaml"
LEADER = "N1"
# mso with its rules, as shipped; then two ablations: energy remaps free to put the join on a
# robot that runs pinned vertices (the leader, the trailing robot), and no energy remaps at all
# (a draining node only relocates)
RULES = {
    "mso-rules": RuleSettings(),
    "mso-rules-no-spare-pinned": RuleSettings(spare_pinned=False),
    "mso-rules-no-energy-remap": RuleSettings(energy_remap=False),
}
STRATEGIES = ("all-on-leader", "algorithm1-kept", *RULES, "ilp-optimal")
ACCOUNTINGS = ("board", "app")
APP_BUDGET_WH = 0.005  # the app's own budget: its tens of mW drain it in minutes of virtual time


def network_for(accounting: str, scenario: Path = SCENARIO_FILE) -> Network:
    """The study's line under an accounting: as written (``board``), or with idle power out
    of the battery and the app's budget in it (``app``)."""
    net = load_scenario(scenario).network
    if accounting == "board":
        return net
    if accounting != "app":
        raise ValueError(
            f"accounting: expected one of {', '.join(ACCOUNTINGS)}, got {accounting!r}"
        )
    nodes = [
        dataclasses.replace(
            n, battery_wh=APP_BUDGET_WH, power=dataclasses.replace(n.power, idle_w=0.0)
        )
        for n in net.nodes.values()
    ]
    return Network(nodes, list(net.links.values()))


def pinned_doc(doc: str, placement: dict[str, str]) -> str:
    """The app with every vertex pinned where ``placement`` puts it (a static placement)."""
    data = yaml.safe_load(doc)
    for v, attrs in data["vertices"].items():
        attrs["pinned"] = placement[v]
    return str(yaml.safe_dump(data, sort_keys=False))


def placement_for(strategy: str, doc: str, net: Network) -> dict[str, str] | None:
    app = loads_app(doc, file=str(APP_FILE))
    if strategy == "all-on-leader":
        return dict(BASELINES["source"](app, net, seed=0, objective="energy"))
    if strategy == "ilp-optimal":
        return dict(BASELINES["optimal"](app, net, seed=0, objective="energy"))
    if strategy == "algorithm1-kept":
        return dict(plan(app, net, planner=PLANNER).placement)
    if strategy in RULES:
        return None  # Algorithm 1 as deployed, then the rules
    raise ValueError(f"strategy: expected one of {', '.join(STRATEGIES)}, got {strategy!r}")


def run(
    strategy: str,
    limit_s: float,
    db: Path,
    *,
    accounting: str = "board",
    step_s: float = 5.0,
    network: Network | None = None,
    until_leader_dies: bool = True,
    placement: dict[str, str] | None = None,
) -> dict[str, Any]:
    """One strategy under one accounting, until the leader's battery is empty (or ``limit_s``
    of virtual time; with ``until_leader_dies`` False, exactly ``limit_s``). ``placement``
    imposes a static placement of its own (``strategy`` then only names the run)."""
    doc = with_planner(APP_FILE.read_text(encoding="utf-8"), PLANNER, file=str(APP_FILE))
    net = network if network is not None else network_for(accounting)
    if placement is None:
        placement = placement_for(strategy, doc, net)
    if placement is not None:
        doc = pinned_doc(doc, placement)
    sim = Simulation(net, manage=strategy in RULES, rules=RULES.get(strategy), model_time=True)
    old_db = os.environ.get(storage.DB_ENV)
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
        alive_j = (sim.now, 0.0)
        started = time.perf_counter()
        while sim.now < limit_s and not (until_leader_dies and LEADER in died):
            sim.run_until(min(sim.now + step_s, limit_s))
            for n, mon in mons.items():
                frac = (mon.remaining_j or 0.0) / (mon.capacity_j or 1.0)
                battery[n].append((round(sim.now, 1), round(frac, 5)))
                if frac <= 0.0 and n not in died:
                    died[n] = sim.now
            if not died:  # the energy spent while every robot lives (see network_energy)
                alive_j = (sim.now, sum(mon.energy_j for mon in mons.values()))
        wall = time.perf_counter() - started
        # only the nodes that take part in the app hold it (issue 24.1): read its holders
        holders = [c.apps["convoy"] for c in sim.cores.values() if "convoy" in c.apps]
        emitted = {
            v: h.emitted
            for dep in holders
            for v, h in dep.instances.items()
            if v in ("laser", "visible_camera")
        }
        relocations = sorted(
            (float(d.split(" ", 1)[0]), d.split(" ", 1)[1])
            for c in sim.cores.values()
            for d in c.manager.done
        )
        final = {
            v: c.id
            for c in sim.cores.values()
            if "convoy" in c.apps
            for v in c.apps["convoy"].instances
        }
    finally:
        storage.set_clock(time.monotonic)
        if old_db is None:
            os.environ.pop(storage.DB_ENV, None)
        else:
            os.environ[storage.DB_ENV] = old_db
    s = storage.summary(db)
    stored = s["trajectory"]["distinct"] + s["targets"]["distinct"]
    alive_stored = storage.stored_by(db, alive_j[0])
    energy = sum(mon.energy_j for mon in mons.values())
    app_energy = sum(mon.cpu_energy_j + mon.radio_energy_j for mon in mons.values())
    return {
        "strategy": strategy,
        "accounting": accounting,
        "leader_lifetime_s": died.get(LEADER),
        "network_lifetime_s": min(died.values()) if died else None,
        "first_to_die": min(died, key=lambda n: died[n]) if died else None,
        "died": died,
        "energy_j": round(energy, 3),
        "app_energy_j": round(app_energy, 3),
        "energy_per_result_j": round(energy / stored, 5) if stored else None,
        "app_energy_per_result_j": round(app_energy / stored, 5) if stored else None,
        "network_energy_per_result_j": round(alive_j[1] / alive_stored, 5)
        if alive_stored
        else None,
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
            n: round(mon.energy_j / max(sim.now - mon.started_at, 1e-9), 5)
            for n, mon in mons.items()
        },
        "average_cpu_radio_w": {
            n: (
                round(mon.cpu_energy_j / max(sim.now - mon.started_at, 1e-9), 5),
                round(mon.radio_energy_j / max(sim.now - mon.started_at, 1e-9), 5),
            )
            for n, mon in mons.items()
        },
        "battery": battery,
        "virtual_s": round(sim.now, 1),
        "wall_s": round(wall, 1),
    }


def plot(results: list[dict[str, Any]], out: Path) -> list[Path]:
    """One PNG per accounting, a panel per strategy: every robot's battery over time, the
    rules' relocations dotted, their remaps dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for accounting in dict.fromkeys(r["accounting"] for r in results):
        runs = [r for r in results if r["accounting"] == accounting]
        rows = (len(runs) + 1) // 2
        fig, axes = plt.subplots(
            rows, 2, figsize=(10, 3 * rows), dpi=100, sharey=True, squeeze=False
        )
        for ax, r in zip(axes.flat, runs, strict=False):
            for node, series in r["battery"].items():
                ax.plot([t for t, _ in series], [100 * f for _, f in series], label=node)
            for t, what in r["relocations"]:
                remap = what.startswith("remap")
                style = {"color": "black", "linestyle": "--"} if remap else {"linestyle": ":"}
                ax.axvline(t, **({"color": "grey", "linewidth": 0.8} | style))
            moves, remaps = _counts(r)
            shown = [f"{moves} relocations, dotted"] if moves else []
            shown += [f"{remaps} remaps, dashed"] if remaps else []
            title = r["strategy"] + (f"\n{'; '.join(shown)}" if shown else "")
            ax.set_title(title, fontsize=10)  # two lines: long names overlapped their neighbour
            ax.set_xlabel("virtual time (s)")
            ax.set_ylabel("battery (%)")
            ax.set_ylim(0, 101)
            ax.legend(loc="lower left", fontsize=8)
        for ax in list(axes.flat)[len(runs) :]:
            ax.set_visible(False)
        what = "whole board (idle included)" if accounting == "board" else "the app's own energy"
        fig.suptitle(f"battery per robot — accounting: {what}")
        fig.tight_layout()
        path = out / f"lifetime-{accounting}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


TARGETS = (  # (what, a, b, key, target, at least?)
    ("leader lifetime, rules / all-on-leader", "mso-rules", "all-on-leader",
     "leader_lifetime_s", 4.0, True),
    ("leader lifetime, rules / Algorithm 1 kept", "mso-rules", "algorithm1-kept",
     "leader_lifetime_s", 2.0, True),
    ("network lifetime, rules / Algorithm 1 kept", "mso-rules", "algorithm1-kept",
     "network_lifetime_s", 1.3, True),
    ("energy per stored result, rules / ILP optimum", "mso-rules", "ilp-optimal",
     "energy_per_result_j", 1.1, False),
    ("energy per stored result while every robot lives, rules / ILP optimum", "mso-rules",
     "ilp-optimal", "network_energy_per_result_j", 1.1, False),
)  # fmt: skip


def ratios(results: list[dict[str, Any]], accounting: str) -> list[dict[str, Any]]:
    """Each target's ratio under ``accounting`` and whether it is met (None: not measured)."""
    by = {r["strategy"]: r for r in results if r["accounting"] == accounting}
    out = []
    for what, a, b, key, target, at_least in TARGETS:
        x = by.get(a, {}).get(key)
        y = by.get(b, {}).get(key)
        ratio = None if not x or not y else x / y
        met = None if ratio is None else (ratio >= target if at_least else ratio <= target)
        out.append({"what": what, "ratio": ratio, "target": target, "at_least": at_least,
                    "met": met})  # fmt: skip
    return out


def _counts(r: dict[str, Any]) -> tuple[int, int]:
    """(relocations, remaps) the rules made in a run."""
    remaps = sum(1 for _, what in r["relocations"] if what.startswith("remap"))
    return len(r["relocations"]) - remaps, remaps


def markdown(results: list[dict[str, Any]]) -> str:
    def fmt(x: float | None, spec: str = ".0f") -> str:
        return "-" if x is None else format(x, spec)

    lines: list[str] = []
    for accounting in dict.fromkeys(r["accounting"] for r in results):
        title = (
            "whole board, idle included"
            if accounting == "board"
            else "the app's own energy (CPU above idle + radio)"
        )
        lines += [
            f"Accounting **{accounting}** — {title}:",
            "",
            "| strategy | leader lifetime (s) | network lifetime (s) (first) "
            "| energy / stored result (J): whole run; every robot alive | of which the app's (J) "
            "| results stored (complete) | e2e p50 / p99 (ms) | relocations / remaps |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in (r for r in results if r["accounting"] == accounting):
            first = f" ({r['first_to_die']})" if r["first_to_die"] else ""
            lines.append(
                f"| {r['strategy']} | {fmt(r['leader_lifetime_s'])} | "
                f"{fmt(r['network_lifetime_s'])}{first} | "
                f"{fmt(r['energy_per_result_j'], '.4f')}; "
                f"{fmt(r['network_energy_per_result_j'], '.4f')} | "
                f"{fmt(r['app_energy_per_result_j'], '.4f')} | "
                f"{r['results_stored']} ({'yes' if r['complete'] else 'NO'}) | "
                f"{fmt(r['delay_ms_p50'], '.1f')} / {fmt(r['delay_ms_p99'], '.1f')} | "
                "{} / {} |".format(*_counts(r))
            )
        lines.append("")
        for t in ratios(results, accounting):
            sign = "≥" if t["at_least"] else "≤"
            verdict = {None: "not measured", True: "met", False: "NOT met"}[t["met"]]
            shown = "-" if t["ratio"] is None else f"{t['ratio']:.2f}×"
            lines.append(f"- {t['what']}: **{shown}** (target {sign} {t['target']:g}×, {verdict})")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--limit-s", type=float, default=3600.0, help="virtual time cap per run")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "lifetime.json")
    ap.add_argument("--plots", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--only", choices=STRATEGIES, action="append", help="run these only")
    ap.add_argument("--accounting", choices=ACCOUNTINGS, action="append", help="these only")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = []
    with tempfile.TemporaryDirectory(prefix="mso-lifetime-") as tmp:
        for accounting in args.accounting or ACCOUNTINGS:
            for strategy in args.only or STRATEGIES:
                db = Path(tmp) / f"{accounting}-{strategy}.sqlite"
                results.append(run(strategy, args.limit_s, db, accounting=accounting))
                print(f"{accounting} {strategy}: done in {results[-1]['wall_s']} s", flush=True)
    plots = plot(results, args.plots)
    table = markdown(results)
    result = {
        "scenario": str(SCENARIO_FILE.relative_to(ROOT)),
        "app": str(APP_FILE.relative_to(ROOT)),
        "app_budget_wh": APP_BUDGET_WH,
        "results": results,
        "targets": {a: ratios(results, a) for a in dict.fromkeys(r["accounting"] for r in results)},
        "plots": [str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p) for p in plots],
        "seconds": time.perf_counter() - t0,
        **provenance(),
    }
    write_results(args.out, result, table)
    return 0
