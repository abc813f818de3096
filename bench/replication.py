"""Chain replication: what the death of a stateful vertex's host costs, and what replicas cost.

Two parts, both in the simulator's virtual time (the node cores as they run everywhere, the
vertex code run inline; ``model_time``: each event takes its vertex's declared cost):

* **kill**: ``src -> counter -> sink`` on the 6-node mesh of tests/test_failure.py (a source
  of ``--rate`` events/s pinned to N1, the stateful ``Counter`` of
  ``mso.benchmarks.vertices.replication`` unpinned, a checking sink pinned to N6). For
  ``replicas`` 0, 1 and 2 and ``--runs`` kill times spread over a snapshot interval, the node
  hosting the counter is killed (routes converge 0.3 s later) and the run goes on
  ``--after`` s. The sink expects 0, 1, 2, ...: ``continuous`` means no number repeated or
  skipped (the counter's output equals a failure-free run's); ``resets`` are returns to 0;
  ``repeats`` numbers seen again; ``lost`` source events never counted at the end, minus
  those still in flight (emitted in the last 50 ms); ``recovery_ms`` the sink's largest gap
  between arrivals (the outage: detection, remap, restore, replay). The host's replication
  status just before the kill gives the cost: bytes per snapshot, bytes/s, snapshots.
* **convoy**: the convoy app (``src/mso/examples/convoy.yaml``) on its 4-robot line
  (``convoy-line.yaml``) for ``--convoy-s`` s, with ``replicas: 0`` on every vertex and with
  the default (1 for each vertex with state: odom_filter, localization, path_planning,
  blob_fusion, bayes_inference, target_map). Delays are the storage log's ``stored_at -
  stamp`` per row (the sources' stamp to the trailing robot's log); the overhead is the
  added p50/p99 against replicas 0 (target: at most 10 % added p50) and the snapshot bytes/s.

* **emulated** (``--emulate-s``, ``--emulate-runs`` pairs): the convoy on the user-space
  emulator, replicas 0 and the default alternated; besides each run's p50/p99, every row of a
  setting pooled and a 95 % interval of the pooled p50's ratio by resampling the pairs: the
  target is met if its upper end is at most +10 %, not met if its lower end is above.
* **kill -9** (``--kill-emulated N``): the kill part on real processes, N times each with
  replicas 0 and 1: the counter's host SIGKILLed once it has replicated a snapshot.

Usage: .venv/bin/python bench/replication.py [--runs 5] [--rate 200] [--after 6]
                                             [--convoy-s 60] [--emulate-s 20]
                                             [--emulate-runs 2] [--kill-emulated 0]
                                             [--json FILE]
Writes bench/results/replication.json and replication.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import re
import sqlite3
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.benchmarks.vertices import replication as rv
from mso.emu.controller import Emulator
from mso.examples.convoy import storage
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.scenario import loads_scenario
from mso.scenario.format import load_scenario
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
EXAMPLES = HERE.parent / "src" / "mso" / "examples"
MESH_LINKS = [
    ("N1", "N2"), ("N2", "N3"), ("N3", "N6"), ("N1", "N4"),
    ("N4", "N5"), ("N5", "N6"), ("N2", "N5"), ("N3", "N5"),
]  # fmt: skip
V = "mso.benchmarks.vertices.replication"
COUNTER = f"""
name: pipe
planner: paper  # the counter's host (killed) interior (bytes: on the source's node)
vertices:
  src: {{code: {V}:Source, pinned: N1, rate: RATE, cost: 0.05, output: {V}:Num}}
  counter: {{code: {V}:Counter, cost: 0.5, output: {V}:Num, replicas: REPLICAS}}
  sink: {{code: {V}:CheckSink, pinned: N6, cost: 0.05}}
edges: [[src, counter], [counter, sink]]
"""
IN_FLIGHT_S = 0.05
SETTLE_S = 1.5  # flowing before the first kill time


def mesh() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 7)]
    return Network(nodes, [LinkSpec(a, b, delay_ms=1.0) for a, b in MESH_LINKS])


def _placed(sim: Simulation, app: str, vertex: str) -> str:
    (node,) = [
        n for n, c in sim.cores.items() if n not in sim.killed and vertex in c.instances(app)
    ]
    return node


def _vertices(node_status: dict[str, Any], app: str) -> dict[str, Any]:
    """``app``'s vertices as a node's status lists them; none at a node that holds none of it
    (only its origin, hosts and replicas' nodes do: issue 24.1)."""
    got: dict[str, Any] = node_status["apps"].get(app, {}).get("vertices", {})
    return got


def kill_run(replicas: int, kill_at: float, rate: float, after: float) -> dict[str, Any]:
    """One run: flow, kill the counter's host at ``kill_at``, go on ``after`` s."""
    sim = Simulation(mesh(), model_time=True)
    rv.set_clock(lambda: sim.now)
    try:
        doc = COUNTER.replace("RATE", f"{rate:g}").replace("REPLICAS", str(replicas))
        sim.request("N1", m.DeployRequest(doc, "pipe.yaml"))
        sim.run_until(kill_at)
        host = _placed(sim, "pipe", "counter")
        app = sim.cores[host].status(sim.now)["apps"]["pipe"]
        cost = app["replication"].get("counter")
        sim.kill(host, convergence_s=0.3)
        sim.run_until(kill_at + after)
        sink_node = _placed(sim, "pipe", "sink")
        st = sim.cores[sink_node].status(sim.now)["apps"]["pipe"]["vertices"]["sink"]["stats"]
        src = sim.cores["N1"].instances("pipe")["src"]
        emitted = src.emitted
        tail = int(rate * IN_FLIGHT_S) + 1
        recs = [
            r for c in sim.cores.values() if "pipe" in c.apps for r in c.apps["pipe"].recoveries
        ]
        return {
            "replicas": replicas,
            "kill_at": round(kill_at, 3),
            "host": host,
            "restored_on": _placed(sim, "pipe", "counter"),
            "continuous": st["repeats"] == 0 and st["skipped"] == 0 and st["next"] == st["count"],
            "resets": st["resets"],
            "repeats": st["repeats"],
            "skipped": st["skipped"],
            "received": st["count"],
            "emitted": emitted,
            "lost": max(0, emitted - tail - st["count"]),
            "recovery_ms": st["gap_ms"],
            "remap_ms": recs[-1]["took_ms"] if recs and "took_ms" in recs[-1] else None,
            "replication": cost,
        }
    finally:
        rv.set_clock(time.monotonic)


def kill_emulated(replicas: int, rate: float) -> dict[str, Any]:
    """The kill part on real processes (the user-space emulator, the same mesh and app): once
    the counter's host has replicated a snapshot, SIGKILL it; wait until a live node runs the
    counter again and the sink has counted everything the source emitted by then."""

    async def run() -> dict[str, Any]:
        net = "".join(f"  - [{a}, {b}]\n" for a, b in MESH_LINKS)
        scenario = loads_scenario(
            "name: mesh\nlink_defaults: {delay_ms: 1.0}\n"
            f"nodes: {{{', '.join(f'N{i}: {{}}' for i in range(1, 7))}}}\nlinks:\n{net}"
        )
        emu = Emulator(scenario, convergence_s=0.3, manage=False)
        await emu.start()
        try:
            doc = COUNTER.replace("RATE", f"{rate:g}").replace("REPLICAS", str(replicas))
            reply = await emu.deploy(doc, "pipe.yaml", "N1")
            if not reply.ok:
                raise RuntimeError(f"deployment failed: {reply.error}")
            host = reply.placement["counter"]
            loop = asyncio.get_running_loop()
            deadline = loop.time() + 20
            cost: dict[str, Any] = {}
            while loop.time() < deadline:  # a snapshot replicated (replicas 0: 2 s of flow)
                await asyncio.sleep(0.2)
                st = await emu.status(via=host)
                cost = st[host]["apps"]["pipe"]["replication"].get("counter") or {}
                if (cost.get("snapshots", 0) >= 1) if replicas else loop.time() > deadline - 18:
                    break
            killed = emu.kill(host)
            restored, st = None, {}
            while loop.time() < killed + 30:
                await asyncio.sleep(0.1)
                st = await emu.status("N1")
                hosts = [  # (only the app's holders hold it: issue 24.1)
                    n for n, s in st.items() if "counter" in _vertices(s, "pipe")
                ]
                if restored is None and host not in st and hosts and hosts[0] != host:
                    restored = loop.time() - killed
                    emitted = int(st["N1"]["apps"]["pipe"]["vertices"]["src"]["emitted"])
                if restored is not None:
                    got = st["N6"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
                    if got["count"] >= emitted:
                        break
            if restored is None:
                raise RuntimeError(f"counter not restored off {host} within 30 s")
            got = st["N6"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
            emitted = int(st["N1"]["apps"]["pipe"]["vertices"]["src"]["emitted"])
            tail = int(rate * 0.2) + 1  # emitted since the last status: in flight
            return {
                "replicas": replicas,
                "host": host,
                "continuous": got["repeats"] == 0
                and got["skipped"] == 0
                and got["next"] == got["count"],
                "resets": got["resets"],
                "repeats": got["repeats"],
                "skipped": got["skipped"],
                "received": got["count"],
                "emitted": emitted,
                "lost": max(0, emitted - tail - got["count"]),
                "restored_s": round(restored, 3),
                "recovery_ms": got["gap_ms"],
                "replication": cost if replicas else None,
            }
        finally:
            await emu.stop()

    try:
        return asyncio.run(run())
    except Exception as exc:  # reported in the table, never a traceback
        return {"replicas": replicas, "error": f"{type(exc).__name__}: {exc}"}


def convoy_doc(replicas_zero: bool) -> str:
    doc = (EXAMPLES / "convoy.yaml").read_text(encoding="utf-8")
    if replicas_zero:  # every vertex with state: no replica
        doc = re.sub(r"(\n  \w+: +\{code: mso\.examples\.convoy:\w+,)", r"\1 replicas: 0,", doc)
        doc = doc.replace("replicas: 0, pinned: N1, rate", "pinned: N1, rate")  # (sources)
    return doc


@contextlib.contextmanager
def logging_to(db: Path, sim: Simulation) -> Iterator[None]:
    """The convoy's storage logs into ``db``, stamped with the simulator's clock (undone after)."""
    old = os.environ.get(storage.DB_ENV)
    os.environ[storage.DB_ENV] = str(db)
    storage.set_clock(lambda: sim.now)
    try:
        yield
    finally:
        storage.set_clock(time.monotonic)
        if old is None:
            os.environ.pop(storage.DB_ENV, None)
        else:
            os.environ[storage.DB_ENV] = old


def convoy_run(replicas_zero: bool, seconds: float, db: Path) -> dict[str, Any]:
    """The convoy for ``seconds`` of virtual time; delays from its storage log."""
    doc = convoy_doc(replicas_zero)
    net = load_scenario(EXAMPLES / "convoy-line.yaml").network
    sim = Simulation(net, manage=False, model_time=True)
    with logging_to(db, sim):
        sim.request("N1", m.DeployRequest(doc, "convoy.yaml"))
        sim.run_until(seconds)
        replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
        if not replies or not replies[0].ok:
            raise RuntimeError(f"convoy deployment failed: {replies}")
        cost: dict[str, Any] = {}
        for c in sim.cores.values():
            if "convoy" in c.apps:  # (only the app's holders hold it: issue 24.1)
                cost |= c.status(sim.now)["apps"]["convoy"]["replication"]
        sent = sum(out for out, _ in sim.bytes.values())
    return _figures(replicas_zero, _delays(db), cost) | {
        "bytes_sent_per_s": round(sent / seconds, 1)
    }


def _figures(replicas_zero: bool, delays: list[float], cost: dict[str, Any]) -> dict[str, Any]:
    """A convoy run's delays and replication cost, as the table shows them."""
    return {
        "replicas": "0" if replicas_zero else "default",
        "rows": len(delays),
        "p50_ms": round(_pct(delays, 50), 3),
        "p99_ms": round(_pct(delays, 99), 3),
        "replicated": sorted(cost),
        "snapshot_bytes_per_s": round(sum(v["bytes_per_s"] for v in cost.values()), 1),
        "bytes_per_snapshot": {v: c["bytes_per_snapshot"] for v, c in sorted(cost.items())},
    }


def _delays(db: Path, since: float = 0.0) -> list[float]:
    """Each stored row's delay in ms (the storage log's ``stored_at - stamp``), sorted."""
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return sorted(
            (r[0] - r[1]) * 1e3
            for table in ("trajectory", "targets")
            for r in conn.execute(
                f"SELECT stored_at, stamp FROM {table} WHERE stamp >= ?", (since,)
            )
        )
    finally:
        conn.close()


def convoy_emulated(replicas_zero: bool, seconds: float, db: Path) -> dict[str, Any]:
    """The convoy on the user-space emulator (one ``mso node`` process per robot, real time)
    for ``seconds`` after a 3 s warm-up; delays from its storage log."""
    doc = convoy_doc(replicas_zero)
    old = os.environ.get(storage.DB_ENV)
    os.environ[storage.DB_ENV] = str(db)  # the node processes inherit it

    async def run() -> dict[str, Any]:
        emu = Emulator(load_scenario(EXAMPLES / "convoy-line.yaml"))
        await emu.start()
        try:
            reply = await emu.deploy(doc, "convoy.yaml", "N1")
            if not reply.ok:
                raise RuntimeError(f"convoy deployment failed: {reply.error}")
            await asyncio.sleep(3.0)  # warm-up: imports, first snapshots
            status = await emu.status()
            t0 = max(_stamps(db), default=0.0)
            await asyncio.sleep(seconds)
            status = await emu.status()
            return {"t0": t0, "status": status}
        finally:
            await emu.stop()

    try:
        out = asyncio.run(run())
    finally:
        if old is None:
            os.environ.pop(storage.DB_ENV, None)
        else:
            os.environ[storage.DB_ENV] = old
    cost: dict[str, Any] = {}
    for st in out["status"].values():  # (only the app's holders hold it: issue 24.1)
        cost |= st["apps"].get("convoy", {}).get("replication", {})
    delays = _delays(db, since=out["t0"])
    return _figures(replicas_zero, delays, cost) | {"delays_ms": [round(d, 3) for d in delays]}


def _stamps(db: Path) -> list[float]:
    if not db.exists():
        return []
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [r[0] for r in conn.execute("SELECT stamp FROM trajectory")]
    except sqlite3.OperationalError:
        return []
    finally:
        conn.close()


def _pct(xs: list[float], p: float) -> float:
    if not xs:
        return float("nan")
    k = min(len(xs) - 1, max(0, round(p / 100 * (len(xs) - 1))))
    return xs[k]


def _emulated(runs: list[dict[str, Any]], seconds: float) -> dict[str, Any]:
    """The emulated runs and the added p50/p99 of replicas: from the medians of the runs, from
    every row of each setting pooled, and a 95 % interval of the pooled p50's ratio by
    resampling the alternated pairs (a pair shares the machine's load of its moment)."""
    if not runs:
        return {}
    med = {}
    for which in ("0", "default"):
        rs = [r for r in runs if r["replicas"] == which]
        med[which] = {
            "p50_ms": statistics.median(r["p50_ms"] for r in rs),
            "p99_ms": statistics.median(r["p99_ms"] for r in rs),
        }
    base, rep = med["0"], med["default"]
    pairs = [(runs[i], runs[i + 1]) for i in range(0, len(runs) - 1, 2)]

    def pooled(ps: list[tuple[dict[str, Any], dict[str, Any]]], k: int, q: float) -> float:
        return _pct(sorted(d for p in ps for d in p[k].get("delays_ms", [])), q)

    rng = random.Random(1)
    ratios = sorted(
        pooled(b, 1, 50) / pooled(b, 0, 50)
        for b in ([rng.choice(pairs) for _ in pairs] for _ in range(2000))
    )
    p50 = (pooled(pairs, 0, 50), pooled(pairs, 1, 50))
    p99 = (pooled(pairs, 0, 99), pooled(pairs, 1, 99))
    return {
        "seconds": seconds,
        "runs": runs,
        "median": med,
        "added_p50_pct": round((rep["p50_ms"] / base["p50_ms"] - 1) * 100, 2),
        "added_p99_pct": round((rep["p99_ms"] / base["p99_ms"] - 1) * 100, 2),
        "pooled": {"p50_ms": p50, "p99_ms": p99},
        "pooled_added_p50_pct": round((p50[1] / p50[0] - 1) * 100, 2),
        "pooled_added_p99_pct": round((p99[1] / p99[0] - 1) * 100, 2),
        "pooled_added_p50_ci95_pct": [
            round((ratios[int(0.025 * len(ratios))] - 1) * 100, 2),
            round((ratios[int(0.975 * len(ratios)) - 1] - 1) * 100, 2),
        ],
        "pairs_faster_with_replicas": sum(p[1]["p50_ms"] <= p[0]["p50_ms"] for p in pairs),
    }


def render(result: dict[str, Any]) -> str:
    lines = [
        f"### Chain replication: the host of a stateful vertex killed under load "
        f"({result['rate']:g} events/s, {result['runs']} kill times per setting, virtual time)",
        "",
        "| replicas | runs continuous | resets | repeats | skipped | lost | recovery ms "
        "(median, max) | bytes/snapshot | snapshot bytes/s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r, s in result["kill"]["summary"].items():
        lines.append(
            f"| {r} | {s['continuous']}/{s['runs']} | {s['resets']} | {s['repeats']} | "
            f"{s['skipped']} | {s['lost']} | {s['recovery_ms_median']:.0f}, "
            f"{s['recovery_ms_max']:.0f} | {s['bytes_per_snapshot']} | {s['bytes_per_s']} |"
        )
    c = result["convoy"]
    base, rep = c["runs"]
    lines += [
        "",
        f"### Chain replication's cost on the convoy ({c['seconds']:g} s, 4-robot line, "
        "virtual time)",
        "",
        "| replicas | rows | p50 ms | p99 ms | snapshot bytes/s | all bytes sent/s |",
        "|---|---:|---:|---:|---:|---:|",
        *[
            f"| {r['replicas']} | {r['rows']} | {r['p50_ms']} | {r['p99_ms']} | "
            f"{r['snapshot_bytes_per_s']} | {r['bytes_sent_per_s']} |"
            for r in (base, rep)
        ],
        "",
        f"Added latency with replicas: p50 {c['added_p50_pct']:+.1f} % (target at most +10 %), "
        f"p99 {c['added_p99_pct']:+.1f} %; replicated vertices: {', '.join(rep['replicated'])}.",
    ]
    e = result["emulated"]
    if e:
        lines += [
            "",
            f"### The same on the user-space emulator (real processes, {e['seconds']:g} s a run, "
            f"{len(e['runs']) // 2} runs each, alternated)",
            "",
            "| replicas | rows | p50 ms | p99 ms | snapshot bytes/s |",
            "|---|---:|---:|---:|---:|",
            *[
                f"| {r['replicas']} | {r['rows']} | {r['p50_ms']} | {r['p99_ms']} | "
                f"{r['snapshot_bytes_per_s']} |"
                for r in e["runs"]
            ],
            "",
            f"Added latency with replicas (medians of the runs): p50 {e['added_p50_pct']:+.1f} % "
            f"(target at most +10 %), p99 {e['added_p99_pct']:+.1f} %.",
        ]
        if "pooled" in e:
            lo, hi = e["pooled_added_p50_ci95_pct"]
            verdict = (
                "met" if hi <= 10 else "not met" if lo > 10 else "neither met nor contradicted"
            )
            lines += [
                "",
                f"Every row of each setting pooled: p50 {e['pooled']['p50_ms'][0]:.3f} -> "
                f"{e['pooled']['p50_ms'][1]:.3f} ms ({e['pooled_added_p50_pct']:+.1f} %, 95 % "
                f"interval {lo:+.1f} .. {hi:+.1f} % over the pairs resampled), p99 "
                f"{e['pooled']['p99_ms'][0]:.3f} -> {e['pooled']['p99_ms'][1]:.3f} ms "
                f"({e['pooled_added_p99_pct']:+.1f} %); replicas no slower in "
                f"{e['pairs_faster_with_replicas']} of {len(e['runs']) // 2} pairs. The <= 10 % "
                f"p50 target: {verdict}.",
            ]
    k = result.get("kill_emulated") or []
    if k:
        lines += [
            "",
            "### The counter's host killed with SIGKILL on the user-space emulator (real "
            f"processes, the same mesh, {result['rate']:g} events/s)",
            "",
            "| replicas | continuous | resets | repeats | skipped | lost | restored s | "
            "recovery ms (sink's gap) | snapshot bytes/s |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in k:
            if "error" in r:
                lines.append(f"| {r['replicas']} | error: {r['error']} |" + " |" * 7)
                continue
            cost = r["replication"] or {}
            lines.append(
                f"| {r['replicas']} | {'yes' if r['continuous'] else 'no'} | {r['resets']} | "
                f"{r['repeats']} | {r['skipped']} | {r['lost']} | {r['restored_s']:.2f} | "
                f"{r['recovery_ms']:.0f} | {cost.get('bytes_per_s', 0)} |"
            )
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--after", type=float, default=6.0)
    ap.add_argument("--convoy-s", type=float, default=60.0)
    ap.add_argument("--emulate-s", type=float, default=20.0)
    ap.add_argument("--emulate-runs", type=int, default=2)
    ap.add_argument("--kill-emulated", type=int, default=0, help="SIGKILL runs per replicas 0|1")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not (1 <= args.runs <= 100 and 0 < args.rate <= 5000 and 2 <= args.after <= 60):
        ap.error("--runs 1..100, --rate up to 5000, --after 2..60 s")
    if not 5 <= args.convoy_s <= 600:
        ap.error("--convoy-s: 5..600 s")
    if not (args.emulate_s == 0 or 5 <= args.emulate_s <= 300) or not 1 <= args.emulate_runs <= 20:
        ap.error("--emulate-s: 0 (skip) or 5..300 s; --emulate-runs 1..20")
    if not 0 <= args.kill_emulated <= 20:
        ap.error("--kill-emulated: 0..20")
    out: Path = args.json or RESULTS / "replication.json"
    started = time.monotonic()
    runs = []
    for replicas in (0, 1, 2):
        for k in range(args.runs):
            kill_at = SETTLE_S + k / args.runs  # spread over a snapshot interval (1 s)
            runs.append(kill_run(replicas, kill_at, args.rate, args.after))
            print(f"kill: replicas {replicas} run {k}: {runs[-1]['continuous']}", file=sys.stderr)
    summary = {}
    for replicas in (0, 1, 2):
        rs = [r for r in runs if r["replicas"] == replicas]
        rec = [r["recovery_ms"] for r in rs]
        costs = [r["replication"] for r in rs if r["replication"]]
        summary[str(replicas)] = {
            "runs": len(rs),
            "continuous": sum(r["continuous"] for r in rs),
            "resets": sum(r["resets"] for r in rs),
            "repeats": sum(r["repeats"] for r in rs),
            "skipped": sum(r["skipped"] for r in rs),
            "lost": sum(r["lost"] for r in rs),
            "recovery_ms_median": statistics.median(rec),
            "recovery_ms_max": max(rec),
            "bytes_per_snapshot": max((c["bytes_per_snapshot"] for c in costs), default=0),
            "bytes_per_s": round(statistics.mean(c["bytes_per_s"] for c in costs), 1)
            if costs
            else 0.0,
        }
    with tempfile.TemporaryDirectory(prefix="mso-bench-replication-") as tmp:
        base = convoy_run(True, args.convoy_s, Path(tmp) / "base.sqlite")
        print(f"convoy replicas 0: {base}", file=sys.stderr)
        rep = convoy_run(False, args.convoy_s, Path(tmp) / "rep.sqlite")
        print(f"convoy replicas default: {rep}", file=sys.stderr)
        emulated: list[dict[str, Any]] = []
        for k in range(args.emulate_runs if args.emulate_s else 0):
            for zero in (True, False):  # alternated: the machine's load drifts
                db = Path(tmp) / f"emu-{k}-{int(zero)}.sqlite"
                emulated.append(convoy_emulated(zero, args.emulate_s, db))
                print(f"emulated convoy: {emulated[-1]}", file=sys.stderr)
    kills = []
    for _ in range(args.kill_emulated):
        for replicas in (0, 1):
            kills.append(kill_emulated(replicas, args.rate))
            print(f"kill -9 emulated: {kills[-1]}", file=sys.stderr)
    result: dict[str, Any] = {
        "benchmark": "replication",
        "rate": args.rate,
        "runs": args.runs,
        "after_s": args.after,
        "kill": {"summary": summary, "runs": runs},
        "convoy": {
            "seconds": args.convoy_s,
            "runs": [base, rep],
            "added_p50_pct": round((rep["p50_ms"] / base["p50_ms"] - 1) * 100, 2),
            "added_p99_pct": round((rep["p99_ms"] / base["p99_ms"] - 1) * 100, 2),
        },
        "emulated": _emulated(emulated, args.emulate_s),
        "kill_emulated": kills,
        "seconds": time.monotonic() - started,
    } | provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
