"""The floor under issue 24's "<= 1 ms of CPU per node per simulated second": the least work
any Python simulator must do for the same beats, measured beside the real simulator in one run.

At 1,000 nodes nearly all the simulator's messages are heartbeats (57.5 of 58 a node a second
on the grid). The floor does for those beats only what no design can skip, on the same
topology (``bench/scale.py``'s builder: ``mso scenario generate``, seed 1) and with the real
codec:

- per node, a minimal core: a dict of its neighbours' last-heard times (and the figures the
  last beat that carried them said);
- one event on a heap per node per beat period (``HEARTBEAT_S``, every node starting at 0 as
  in the simulator); its copies reach the neighbours at once, with no event of their own;
- per event, the real ``Heartbeat`` of the real size (its monitor's figures, with hops to the
  nodes within two hops, on one beat in ten as ``MONITOR_PERIOD_S`` says) encoded in its
  envelope with ``mso.protocol.messages.wrap``;
- ``floor``: decoded once (``unwrap``, ``decode``) and noted at each neighbour (the simulator
  too decodes a broadcast once, its receivers sharing it); ``floor, decoded at each``: decoded
  once per neighbour, the frame as each receiver's own (the brief's example; more work than
  the simulator does, so not a floor of it).

Nothing else: no liveness judgement (silence), no routes, no census, no byte counters per hop,
no data plane, no monitor. Beside it, in alternated child processes: ``bench/scale.py --one``
itself (N/20 apps, the issue's setting) and the simulator with no app (beats, monitor ticks,
nothing else). Each measures the CPU of ``--duration`` simulated
seconds after start-up.

Usage: .venv/bin/python bench/beat_floor.py [--topologies grid,geometric] [--nodes 1000]
       [--duration 10] [--rounds 2]
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import Progress, provenance, write_results

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VARIANTS = (
    "simulator",
    "simulator, no app",
    "floor",
    "floor, decoded at each",
    "no codec",
)


def _scale() -> Any:
    """bench/scale.py, whose builder and child runner this uses."""
    sys.path.insert(0, str(HERE))
    import scale

    return scale


def _scenario(topology: str, n: int) -> Any:
    return _scale()._scenario(topology, n)


def floor(topology: str, n: int, duration: float, codec: str) -> dict[str, Any]:
    """The floor's beats on ``topology``: ``duration`` simulated seconds after the first;
    ``codec``: ``once`` a beat, at ``each`` receiver, or ``none``."""
    from mso.protocol import messages as m
    from mso.protocol.procedures.membership.liveness import HEARTBEAT_S
    from mso.protocol.procedures.membership.peers import MONITOR_PERIOD_S

    net = _scenario(topology, n).network
    names = list(net.nodes)
    index = {x: i for i, x in enumerate(names)}
    around = [tuple(index[y] for y in sorted(net.neighbours(x))) for x in names]
    figures = []  # each node's figures as its beat carries them: hops to those within two
    for i in range(n):
        near = {j: 1 for j in around[i]}
        for j in around[i]:
            for k in around[j]:
                if k != i:
                    near.setdefault(k, 2)
        hops = {names[j]: h for j, h in sorted(near.items())}
        figures.append(m.Figures(1.0, 0.0, 0.5, None, None, (0.5, 1.5, 0.2, 0.1), hops))
    leader = min(names)
    heard: list[dict[str, float]] = [{} for _ in names]  # the minimal core
    said: list[dict[str, m.Figures]] = [{} for _ in names]
    period, every = HEARTBEAT_S, max(1, round(MONITOR_PERIOD_S / HEARTBEAT_S))
    beats = [0] * n
    count = {"beats": 0, "copies": 0, "bytes": 0}
    names_bytes = [len(m.encode(m.Heartbeat(x))) - len(m.encode(m.Heartbeat(""))) for x in names]
    heap = [(period, i) for i in range(n)]
    wrap, unwrap, decode, push, pop = m.wrap, m.unwrap, m.decode, heapq.heappush, heapq.heappop

    def run(until: float) -> None:
        while heap[0][0] <= until:
            at, i = pop(heap)
            k = beats[i]
            beats[i] = k + 1
            to = around[i]
            if codec == "none":
                count["copies"] += len(to)
                for j in to:
                    heard[j][names[i]] = at
                push(heap, (at + period, i))
                continue
            beat = m.Heartbeat(names[i], 0, {}, leader, 0, figures[i] if k % every == 0 else None)
            frame = wrap(names[i], names[to[0]], beat)
            count["beats"] += 1
            count["copies"] += len(to)
            count["bytes"] += len(to) * (len(frame) - names_bytes[to[0]]) + sum(
                names_bytes[j] for j in to
            )
            if codec == "each":
                for j in to:
                    got = decode(unwrap(frame).body)
                    assert isinstance(got, m.Heartbeat)
                    heard[j][got.node] = at
                    if got.figures is not None:
                        said[j][got.node] = got.figures
            else:
                got = decode(unwrap(frame).body)
                assert isinstance(got, m.Heartbeat)
                src, fig = got.node, got.figures
                for j in to:
                    heard[j][src] = at
                    if fig is not None:
                        said[j][src] = fig
            push(heap, (at + period, i))

    run(1.0)  # (as the simulator's start-up: every core built, a second of beats)
    before = dict(count)
    c0 = time.process_time()
    run(1.0 + duration)
    cpu = time.process_time() - c0
    per = n * duration
    return {
        "cpu_ms_per_node_per_sim_s": round(cpu / duration / n * 1e3, 3),
        "cpu_per_sim_s": round(cpu / duration, 3),
        "heartbeats_per_node_s": round((count["copies"] - before["copies"]) / per, 1),
        "bytes_per_node_s": round((count["bytes"] - before["bytes"]) / per, 1),
        "mean_degree": round(2 * len(net.links) / n, 2),
    }


def no_app(topology: str, n: int, duration: float) -> dict[str, Any]:
    """The simulator with no app deployed: its beats and monitor ticks alone."""
    from mso.sim.runner import Simulation

    sim = Simulation(_scenario(topology, n).network)
    sim.run_until(1.0)
    beats0 = sim.census.by_type.get("Heartbeat", 0)
    bytes0 = sum(b[0] for b in sim.bytes.values())
    c0 = time.process_time()
    sim.run_until(1.0 + duration)
    cpu = time.process_time() - c0
    per = n * duration
    return {
        "cpu_ms_per_node_per_sim_s": round(cpu / duration / n * 1e3, 3),
        "cpu_per_sim_s": round(cpu / duration, 3),
        "heartbeats_per_node_s": round((sim.census.by_type["Heartbeat"] - beats0) / per, 1),
        "bytes_per_node_s": round((sum(b[0] for b in sim.bytes.values()) - bytes0) / per, 1),
    }


def _measure(variant: str, topology: str, n: int, duration: float) -> dict[str, Any]:
    """One variant in a fresh process (its own memory), with the load when it started."""
    load = round(os.getloadavg()[0], 2)
    if variant == "simulator":  # bench/scale.py itself
        r = _scale()._child(["--one", topology, str(n), str(duration)], 1200.0)
        keep = ("cpu_ms_per_node_per_sim_s", "cpu_per_sim_s", "heartbeats_per_node_s")
        if "error" not in r:
            r = {k: r[k] for k in (*keep, "bytes_per_node_s", "messages_per_node_s")}
    else:
        which = {
            "simulator, no app": "sim",
            "floor": "once",
            "floor, decoded at each": "each",
            "no codec": "none",
        }
        args = ["--one", which[variant], topology, str(n), str(duration)]
        r = _scale()._child(args, 1200.0, script=__file__)
    return {"variant": variant, "topology": topology, "nodes": n, "load": load, **r}


def table(result: dict[str, Any]) -> str:
    lines = [
        "### The floor under a beat: the simulator beside the least work for the same beats",
        "",
        f"{result['nodes']} nodes, {result['duration_s']:g} simulated seconds after start-up,"
        " default heartbeats, the wire encoding on; alternated child processes"
        f" ({result['rounds']} rounds); CPU ms per node per simulated second, each round and"
        " the median.",
        "",
        "| topology | variant | CPU ms / node / sim s (each round) | median | x the floor"
        " | beats / node / s | bytes / node / s | load |",
        "|---|---|---|---:|---:|---:|---:|---|",
    ]
    for topology, rows in result["by_topology"].items():
        base = rows["floor"]["median"]
        for variant in VARIANTS:
            r = rows[variant]
            each = ", ".join(f"{x:g}" for x in r["runs"])
            ratio = f"{r['median'] / base:.1f}x" if base else "—"
            lines.append(
                f"| {topology} | {variant} | {each} | **{r['median']:g}** | {ratio} |"
                f" {r['heartbeats_per_node_s']:g} | {r['bytes_per_node_s']:g} | {r['loads']} |"
            )
    load = result["machine"]["load_average"]
    lines += ["", f"Load average when written: {load[0]:.1f} on {result['machine']['cpus']} CPUs."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--one", nargs=4, metavar=("WHICH", "TOPOLOGY", "N", "S"), help=argparse.SUPPRESS
    )
    ap.add_argument("--topologies", default="grid,geometric")
    ap.add_argument("--nodes", type=int, default=1000)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    if args.one:
        which, topology, n, s = args.one[0], args.one[1], int(args.one[2]), float(args.one[3])
        if which == "sim":
            print(json.dumps(no_app(topology, n, s)))
        else:
            print(json.dumps(floor(topology, n, s, which)))
        return
    say = Progress("beat_floor")
    t0 = time.perf_counter()
    runs: list[dict[str, Any]] = []
    for topology in args.topologies.split(","):
        for k in range(args.rounds):
            for variant in VARIANTS:
                say(f"{topology} round {k + 1}: {variant}")
                runs.append(_measure(variant, topology, args.nodes, args.duration))
    by: dict[str, dict[str, Any]] = {}
    for topology in args.topologies.split(","):
        by[topology] = {}
        for variant in VARIANTS:
            rs = [r for r in runs if r["topology"] == topology and r["variant"] == variant]
            ok = [r for r in rs if "error" not in r]
            if not ok:
                raise SystemExit(f"{topology} {variant}: {[r.get('error') for r in rs]}")
            by[topology][variant] = {
                "runs": [r["cpu_ms_per_node_per_sim_s"] for r in ok],
                "median": round(statistics.median(r["cpu_ms_per_node_per_sim_s"] for r in ok), 3),
                "heartbeats_per_node_s": ok[0]["heartbeats_per_node_s"],
                "bytes_per_node_s": ok[0]["bytes_per_node_s"],
                "loads": "-".join(f"{r['load']:.1f}" for r in rs),
            }
    result: dict[str, Any] = {
        "nodes": args.nodes,
        "duration_s": args.duration,
        "rounds": args.rounds,
        "runs": runs,
        "by_topology": by,
    }
    result |= provenance()
    result["seconds"] = time.perf_counter() - t0
    write_results(RESULTS / "beat_floor.json", result, table(result))


if __name__ == "__main__":
    main()
