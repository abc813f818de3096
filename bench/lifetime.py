"""The leader robot's battery lifetime with the energy rule on and off (issue: ≥ 2× with it on).

Runs the convoy app (examples/convoy.yaml) on the convoy line with a battery-bound leader
(examples/convoy-energy.yaml) in the virtual-time simulator — the same node code as the daemon,
so hours of battery take seconds — once with the management rules off (the placement stays as
deployed) and once with them on (the default lifetime policy). The leader's lifetime is the
virtual time at which its monitor shows an empty battery. Also reported: where the vertices
ended up, the relocations the rules made, every node's average drain, and the events the
storage sink received (nothing may be lost by the moves).

    .venv/bin/python bench/lifetime.py [--limit-s 20000] [--out bench/results]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from mso.protocol import messages as m
from mso.scenario import load_scenario
from mso.sim.runner import Simulation

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "src" / "mso" / "examples"
LEADER = "N1"


def run(manage: bool, limit_s: float, step_s: float = 10.0) -> dict[str, Any]:
    """Deploy, then advance until the leader's battery is empty (or ``limit_s``)."""
    scenario = load_scenario(EXAMPLES / "convoy-energy.yaml")
    doc = (EXAMPLES / "convoy.yaml").read_text(encoding="utf-8")
    sim = Simulation(scenario.network, manage=manage)
    sim.request(LEADER, m.DeployRequest(doc, "convoy.yaml"))
    sim.run_until(1.0)
    replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    if not replies or not replies[0].ok:
        raise SystemExit(f"deployment failed: {replies}")
    deployed = dict(replies[0].placement)
    leader = sim.cores[LEADER].monitor
    started = time.perf_counter()
    while sim.now < limit_s and (leader.remaining_j or 0.0) > 0.0:
        sim.run_until(sim.now + step_s)
    wall = time.perf_counter() - started
    dep = sim.cores["N4"].apps["convoy"]
    storage = dep.stones["storage"].processed if "storage" in dep.stones else 0
    sources = sum(
        s.emitted for s in sim.cores[LEADER].apps["convoy"].stones.values() if s.kind == "source"
    )
    return {
        "management": manage,
        "leader_lifetime_s": round(sim.now, 1),
        "leader_battery_j": leader.capacity_j,
        "leader_empty": (leader.remaining_j or 0.0) <= 0.0,
        "average_drain_w": {
            n: round(c.monitor.energy_j / max(sim.now - c.monitor.started_at, 1e-9), 3)
            for n, c in sim.cores.items()
        },
        "leader_load": round(leader.load, 3),
        "relocations": [d for c in sim.cores.values() for d in c.manager.done],
        "placement_deployed": deployed,
        "placement_final": dict(dep.placed),
        "events_from_sources": sources,
        "events_at_storage": storage,
        "wall_s": round(wall, 2),
    }


def markdown(off: dict[str, Any], on: dict[str, Any], ratio: float) -> str:
    moved = {
        v: f"{off['placement_final'][v]} → {n}"
        for v, n in on["placement_final"].items()
        if off["placement_final"][v] != n
    }
    lines = [
        "| energy rule | leader lifetime (s) | leader avg drain (W) | relocations |",
        "|---|---:|---:|---:|",
        f"| off | {off['leader_lifetime_s']:.0f} | {off['average_drain_w'][LEADER]:.2f} | 0 |",
        f"| on | {on['leader_lifetime_s']:.0f} | {on['average_drain_w'][LEADER]:.2f} | "
        f"{len(on['relocations'])} |",
        "",
        f"Lifetime ratio on/off: **{ratio:.2f}×** (target ≥ 2×). Moved by the rules: "
        + (", ".join(f"{v} {w}" for v, w in sorted(moved.items())) or "nothing")
        + ".",
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--limit-s", type=float, default=20000.0, help="virtual time cap per run")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    args = ap.parse_args()
    off = run(False, args.limit_s)
    on = run(True, args.limit_s)
    ratio = on["leader_lifetime_s"] / off["leader_lifetime_s"]
    result = {"off": off, "on": on, "lifetime_ratio": round(ratio, 3), "target_ratio": 2.0}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "lifetime.json").write_text(json.dumps(result, indent=2) + "\n")
    table = markdown(off, on, ratio)
    (args.out / "lifetime.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
