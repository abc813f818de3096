"""Membership at scale, in virtual time: what one node failure costs, and membership under mobility.

For grids of N nodes (N = 25, 100, 400 by default) with one 4-vertex pipeline deployed across
them, the node running an interior vertex is killed, and the simulator's taps count every
control message (not data, not an ack, not a heartbeat) from the kill until the network is
quiet: in total, the most any one node sent or received, and by type. Detection time is the
first survivor's declaration after the kill, recovery time the coordinator's restore done, lost
the events the sink missed. Heartbeat bytes are the encoded size of the beats a node sent per
second (they must not grow with N), also split into beats per node per second (10 to each
neighbour: the mean degree, which a grid's border lowers at small N) and bytes per beat.

A restart of that node (its links back, a new incarnation, nothing hosted) 3 s after the kill
is counted the same way: the control messages from the restart to quiescence, and the beats
that are hellos (to or from the restarted node over more than one hop).

Then 200 nodes in random waypoint (mean degree ~5, links by radio range) run for ``--mobile-s``
simulated seconds: membership messages (heartbeats and the detector's own) per node per second,
and, sampled every second, how many (node, peer) pairs hold a peer failed that they reach.

Usage: .venv/bin/python bench/membership.py [--sizes 25,100,400] [--mobile-s 60]
Writes bench/results/membership.json and membership.md.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
NOT_CONTROL = (m.Data, m.Ack, m.Heartbeat)
MEMBERSHIP = (m.Heartbeat, m.NodeDown, m.NodeUp, m.Suspect, m.Hears)
RATE = 20  # events per second from the source


def name(i: int) -> str:
    return f"N{i:04d}"


def grid(side: int) -> Network:
    nodes = [NodeSpec(name(i)) for i in range(side * side)]
    links = []
    for r in range(side):
        for c in range(side):
            i = r * side + c
            if c + 1 < side:
                links.append(LinkSpec(name(i), name(i + 1), delay_ms=1.0))
            if r + 1 < side:
                links.append(LinkSpec(name(i), name(i + side), delay_ms=1.0))
    return Network(nodes, links)


def app(src: str, sink: str) -> str:
    """src -> a -> b -> sink; ``planner: paper`` puts a and b on interior nodes, one of which
    the failure study kills (the bytes split would keep them on the source's node)."""
    ev = "output: mso.sim.vertices:Ev"
    return f"""
name: bench
planner: paper
vertices:
  src: {{code: mso.sim.vertices:Source, params: {{name: src}}, rate: {RATE}, pinned: {src}, {ev}}}
  a: {{code: mso.sim.vertices:Pass, cost: 2, {ev}}}
  b: {{code: mso.sim.vertices:Pass, cost: 2, {ev}}}
  sink: {{code: mso.sim.vertices:Sink, params: {{run: membership, name: sink}}, pinned: {sink}}}
edges: [[src, a], [a, b], [b, sink]]
"""


def deployed(side: int) -> tuple[Simulation, str]:
    """The pipeline deployed on a side x side grid, and the interior node that runs ``a``."""
    n = side * side
    sim = Simulation(grid(side), wire=False, manage=False)
    src, sink = name(0), name(3 * side + 3 if side > 4 else n - 1)
    sim.request(src, m.DeployRequest(app(src, sink), "bench.yaml"))
    sim.run_until(3.0)
    replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    assert replies and replies[0].ok, replies
    (victim,) = sim.hosts("bench", "a")
    assert victim not in (src, sink), victim
    return sim, victim


def failure(side: int, convergence_s: float) -> dict[str, Any]:
    """One interior node of a side x side grid killed: the cost of its detection and recovery."""
    n = side * side
    wall = time.perf_counter()
    sim, victim = deployed(side)
    counts: Counter[str] = Counter()
    per_node: Counter[str] = Counter()
    beat_bytes = [0, 0]  # bytes, beats

    def tap(a: str, b: str, msg: m.Message) -> None:
        if isinstance(msg, m.Heartbeat):
            beat_bytes[0] += len(m.encode(msg))
            beat_bytes[1] += 1
        if isinstance(msg, NOT_CONTROL):
            return
        counts[m.name_of(msg)] += 1
        per_node[a] += 1
        per_node[b] += 1

    t_beats = sim.now
    sim.taps.append(tap)
    sim.run_until(sim.now + 1.0)  # a quiet second: heartbeat bytes at rest, no control
    beats_per_node_s = beat_bytes[0] / n / (sim.now - t_beats)
    beats = beat_bytes[1] / n / (sim.now - t_beats)
    per_beat = beat_bytes[0] / max(1, beat_bytes[1])
    quiet = sum(counts.values())
    counts.clear()
    per_node.clear()
    t0 = sim.now
    sim.kill(victim, convergence_s=convergence_s)
    sim.run_until(t0 + 8.0)
    declared = [f["at"] for c in sim.cores.values() for f in c.failures if f["node"] == victim]
    recs = [
        r
        for c in sim.cores.values()
        if "bench" in c.apps
        for r in c.apps["bench"].recoveries
        if r["ok"]
    ]
    sinks = [sim.instance(h, "bench", "sink") for h in sim.hosts("bench", "sink")]
    missing = sum(s.missing for rec in sinks for s in rec.record.streams.values())
    return {
        "nodes": n,
        "convergence_s": convergence_s,
        "control_messages": sum(counts.values()),
        "per_node_max": max(per_node.values(), default=0),
        "nodes_involved": len(per_node),
        "by_type": dict(sorted(counts.items())),
        "quiet_control_messages": quiet,
        "detection_s": round(min(declared) - t0, 4) if declared else None,
        "declared_by_all_s": round(max(declared) - t0, 4) if declared else None,
        "recovery_s": (
            round(recs[0]["at"] + recs[0].get("took_ms", 0) / 1e3 - t0, 4) if recs else None
        ),
        "recoveries": len(recs),
        "lost": missing,
        "heartbeat_bytes_per_node_s": round(beats_per_node_s, 1),
        "heartbeats_per_node_s": round(beats, 1),
        "heartbeat_bytes_per_beat": round(per_beat, 1),
        "wall_s": round(time.perf_counter() - wall, 1),
    }


def restart(side: int, down_s: float = 3.0) -> dict[str, Any]:
    """The interior node of :func:`deployed` killed, declared and recovered from, then back
    after ``down_s`` (its links too) as a new incarnation: what its return costs."""
    wall = time.perf_counter()
    sim, victim = deployed(side)
    links = [sim.network.link(victim, p) for p in sim.network.neighbours(victim)]
    sim.kill(victim)
    sim.run_until(sim.now + down_s)
    counts: Counter[str] = Counter()
    involved: set[str] = set()
    hellos = [0]

    def tap(a: str, b: str, msg: m.Message) -> None:
        if isinstance(msg, m.Heartbeat):
            if victim in (a, b) and sim.network.link(a, b) is None:
                hellos[0] += 1
            return
        if isinstance(msg, NOT_CONTROL):
            return
        counts[m.name_of(msg)] += 1
        involved.update((a, b))

    sim.taps.append(tap)
    for link in links:
        if link is not None:
            sim.network.add_link(link)
    t0 = sim.now
    sim.revive(victim)
    sim.run_until(t0 + 3.0)
    back = [
        j["at"] for c in sim.cores.values() for j in c.rejoins if j["node"] == victim
    ]  # (the nodes that took it back, and when)
    return {
        "nodes": side * side,
        "control_messages": sum(counts.values()),
        "nodes_involved": len(involved),
        "by_type": dict(sorted(counts.items())),
        "hellos": hellos[0],
        "taken_back_by": len(back),
        "taken_back_by_all_s": round(max(back) - t0, 4) if back else None,
        "held_failed_after": sum(victim in c.failed for c in sim.cores.values()),
        "synced": "bench" in sim.cores[victim].apps,
        "wall_s": round(time.perf_counter() - wall, 1),
    }


def mobile(n: int, seconds: float, seed: int = 1, spread: float = 3.35) -> dict[str, Any]:
    """``n`` nodes in random waypoint on a square sized for a mean degree of about 5.

    The square is sized for a mean degree of ``spread`` with nodes spread evenly, as they start;
    random waypoint then gathers them toward the middle (a square sized for 5 gave a mean degree
    of 7.56 over 300 s), and 3.35 gives about 5 over the run.
    """
    rng = random.Random(seed)
    radius = 100.0
    side = math.sqrt(n * math.pi * radius * radius / spread)
    pos = {name(i): (rng.uniform(0, side), rng.uniform(0, side)) for i in range(n)}
    goal = {k: (rng.uniform(0, side), rng.uniform(0, side)) for k in pos}
    speed = {k: rng.uniform(1.0, 5.0) for k in pos}

    def links() -> set[tuple[str, str]]:
        ids = sorted(pos)
        out = set()
        for i, a in enumerate(ids):
            ax, ay = pos[a]
            for b in ids[i + 1 :]:
                bx, by = pos[b]
                if (ax - bx) ** 2 + (ay - by) ** 2 <= radius * radius:
                    out.add((a, b))
        return out

    current = links()
    net = Network(
        [NodeSpec(k) for k in sorted(pos)], [LinkSpec(a, b, delay_ms=1.0) for a, b in current]
    )
    wall = time.perf_counter()
    sim = Simulation(net, wire=False, manage=False)
    sim.run_until(2.0)
    counts: Counter[str] = Counter()

    def tap(a: str, b: str, msg: m.Message) -> None:
        if isinstance(m.carried(msg), MEMBERSHIP):
            counts[m.name_of(msg)] += 1

    sim.taps.append(tap)
    t0 = sim.now
    held: list[int] = []
    degree: list[float] = []
    while sim.now < t0 + seconds:
        for k, (x, y) in pos.items():  # one second of movement toward each node's waypoint
            gx, gy = goal[k]
            d = math.hypot(gx - x, gy - y)
            if d <= speed[k]:
                pos[k] = goal[k]
                goal[k] = (rng.uniform(0, side), rng.uniform(0, side))
            else:
                pos[k] = (x + (gx - x) * speed[k] / d, y + (gy - y) * speed[k] / d)
        now_links = links()
        for a, b in current - now_links:
            net.remove_link(a, b)
        for a, b in now_links - current:
            net.add_link(LinkSpec(a, b, delay_ms=1.0))
        current = now_links
        degree.append(2 * len(current) / n)
        sim.links_changed(0.2)
        sim.run_until(sim.now + 1.0)
        held.append(
            sum(
                1
                for k, c in sim.cores.items()
                for p in c.failed
                if net.route(k, p) is not None and p not in sim.killed
            )
        )
    total = sum(counts.values())
    return {
        "nodes": n,
        "seconds": seconds,
        "mean_degree": round(sum(degree) / len(degree), 2),
        "membership_msgs_per_node_s": round(total / n / seconds, 2),
        "by_type": dict(sorted(counts.items())),
        "reachable_but_failed_max": max(held, default=0),
        "reachable_but_failed_final": held[-1] if held else 0,
        "wall_s": round(time.perf_counter() - wall, 1),
    }


def table(
    rows: list[dict[str, Any]], mob: dict[str, Any] | None, back: list[dict[str, Any]] | None = None
) -> str:
    out = [
        "### Membership: one node failure on a grid (simulator, kill with routes converging "
        "in the given time)",
        "",
        "| N | convergence s | control msgs | per node max | nodes involved | detection s "
        "| recovery s | lost | heartbeat B/node/s | beats/node/s | B/beat |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r['nodes']} | {r['convergence_s']:g} | {r['control_messages']:,} "
            f"| {r['per_node_max']} | {r['nodes_involved']} | {r['detection_s']} "
            f"| {r['recovery_s']} | {r['lost']} | {r['heartbeat_bytes_per_node_s']:,} "
            f"| {r.get('heartbeats_per_node_s', '')} | {r.get('heartbeat_bytes_per_beat', '')} |"
        )
    if back:
        out += [
            "",
            "### Membership: that node back 3 s later, a new incarnation (its links too)",
            "",
            "| N | control msgs | nodes involved | by type | hellos (beats over > 1 hop) "
            "| taken back by | all within s | held failed after | app synced |",
            "|---:|---:|---:|---|---:|---:|---:|---:|---|",
        ]
        for r in back:
            kinds = ", ".join(f"{k} {v}" for k, v in r["by_type"].items())
            out.append(
                f"| {r['nodes']} | {r['control_messages']:,} | {r['nodes_involved']} | {kinds} "
                f"| {r['hellos']:,} | {r['taken_back_by']} | {r['taken_back_by_all_s']} "
                f"| {r['held_failed_after']} | {'yes' if r['synced'] else 'no'} |"
            )
    if mob:
        out += [
            "",
            f"Random waypoint, {mob['nodes']} nodes, mean degree {mob['mean_degree']}, "
            f"{mob['seconds']:g} simulated s: {mob['membership_msgs_per_node_s']} membership "
            f"messages per node per second; reachable peers held failed: at most "
            f"{mob['reachable_but_failed_max']}, at the end {mob['reachable_but_failed_final']}.",
        ]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="25,100,400", help="grid sizes (square numbers)")
    ap.add_argument("--convergence", default="0.3,0", help="route convergence times (s)")
    ap.add_argument("--mobile-n", type=int, default=200)
    ap.add_argument(
        "--mobile-s",
        type=float,
        default=60.0,
        help="0: skip the mobility run (the kept results' run stays)",
    )
    ap.add_argument("--json", type=Path, default=RESULTS / "membership.json")
    args = ap.parse_args(argv)
    try:
        sides = [math.isqrt(int(s)) for s in args.sizes.split(",")]
        convs = [float(c) for c in args.convergence.split(",")]
    except ValueError as exc:
        print(f"error: --sizes/--convergence: {exc}", file=sys.stderr)
        return 2
    if any(s < 3 for s in sides) or any(c < 0 for c in convs):
        print("error: grids of at least 9 nodes, convergence >= 0", file=sys.stderr)
        return 2
    start = time.perf_counter()
    rows = []
    for side in sides:
        for conv in convs:
            rows.append(failure(side, conv))
            print(rows[-1], flush=True)
    back = []
    for side in sides:
        back.append(restart(side))
        print(back[-1], flush=True)
    mob = mobile(args.mobile_n, args.mobile_s) if args.mobile_s > 0 else None
    if mob is None and args.json.exists():  # a longer run measured before stays
        mob = json.loads(args.json.read_text()).get("mobility")
    result = {
        "provenance": provenance(),
        "failures": rows,
        "restarts": back,
        "mobility": mob,
        "seconds": time.perf_counter() - start,
    }
    write_results(args.json, result, table(rows, mob, back))
    return 0


if __name__ == "__main__":
    sys.exit(main())
