"""Memory of a node hosting 100 vertices on idle edges.

A 2-node emulated scenario (N1 - N2, unshaped link). The node processes' resident set size
(VmRSS from /proc/<pid>/status) is read:

* ``idle``: the nodes started, no app;
* ``local``: an app of 100 vertices on N1 alone: 50 pipelines ``src_i -> sink_i``, every vertex
  pinned to N1, sources at 0.1 events/s (50 idle local edges);
* ``remote``: an app of 200 vertices: 100 sources pinned to N1 feeding 100 sinks pinned to N2,
  sources at 0.1 events/s: each node hosts 100 vertices and 100 idle inter-node edges;
* ``after undeploy``: both apps stopped.

After each deployment the benchmark waits until every sink has received the first event, then at
least one source period (11 s at 0.1 events/s) and until the RSS has settled (two samples 0.5 s
apart within 1%, bounded). Vertex code:
mso.benchmarks.vertices.dataplane (IdleSource, CountSink), a module of the package.

Usage: .venv/bin/python bench/memory.py [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import src_digest
from mso.emu.controller import Emulator
from mso.scenario import load_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.dataplane"  # the vertex code the nodes import
TARGET_MB = 100.0
RATE = 0.1

SCENARIO = """\
name: memory-pair
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


def app_yaml(name: str, pairs: int, sink_node: str) -> str:
    lines = [f"name: {name}", "vertices:"]
    for i in range(pairs):
        lines.append(
            f"  src{i}: {{code: {VERTICES}:IdleSource, pinned: N1, rate: {RATE},"
            f" output: {VERTICES}:Stamped}}"
        )
        lines.append(
            f"  sink{i}: {{code: {VERTICES}:CountSink, pinned: {sink_node},"
            f" input: {VERTICES}:Stamped}}"
        )
    lines.append("edges:")
    lines += [f"  - [src{i}, sink{i}]" for i in range(pairs)]
    return "\n".join(lines) + "\n"


def proc_status(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM of a process, in MB (MiB)."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM", "RssAnon", "RssFile"):
            out[key] = int(value.split()[0]) / 1024.0
    return out


async def settle(pids: dict[str, int], min_s: float, max_s: float) -> dict[str, dict[str, float]]:
    """Sample every 0.5 s for at least min_s, then until RSS changes by < 1% between samples
    (or max_s passes)."""
    prev = {n: proc_status(p) for n, p in pids.items()}
    start = time.monotonic()
    for _ in range(int(max_s / 0.5) + 1):
        await asyncio.sleep(0.5)
        cur = {n: proc_status(p) for n, p in pids.items()}
        stable = all(
            abs(cur[n]["VmRSS"] - prev[n]["VmRSS"]) <= 0.01 * prev[n]["VmRSS"] for n in pids
        )
        prev = cur
        waited = time.monotonic() - start
        if (stable and waited >= min_s) or waited > max_s:
            break
    return prev


async def wait_sinks(emu: Emulator, app: str, node: str, sinks: int, timeout: float) -> int:
    """Wait until every sink counted at least one event; returns how many did."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    got = 0
    for _ in range(1000):
        nodes = await emu.status()
        vertices = nodes[node]["apps"].get(app, {}).get("vertices", {})
        got = sum(
            1
            for v, s in vertices.items()
            if v.startswith("sink") and (s.get("stats") or {}).get("count", 0) >= 1
        )
        if got >= sinks or loop.time() > deadline:
            break
        await asyncio.sleep(0.2)
    return got


async def run(quick: bool) -> dict[str, Any]:
    # at least one whole source period (1/RATE) after deployment, so every source has emitted
    # twice and every timer of the app has been re-armed once, before RSS is read
    min_s, max_s = (1.0, 3.0) if quick else (1.0 / RATE + 1.0, 1.0 / RATE + 10.0)
    results: dict[str, Any] = {"phases": {}}
    with tempfile.TemporaryDirectory(prefix="mso-bench-memory-") as tmpdir:
        tmp = Path(tmpdir)
        (tmp / "memory-pair.yaml").write_text(SCENARIO)
        emu = Emulator(load_scenario(tmp / "memory-pair.yaml"), log_dir=tmp)
        try:
            await emu.start()
            pids = {}
            for n, node in emu.nodes.items():
                assert node.process is not None
                pids[n] = node.process.pid
            results["pids"] = pids
            results["phases"]["idle"] = {"rss": await settle(pids, 1.0, max_s)}
            for phase, pairs, sink_node in (("local", 50, "N1"), ("remote", 100, "N2")):
                name = f"mem_{phase}"
                doc = app_yaml(name, pairs, sink_node)
                (tmp / f"{name}.yaml").write_text(doc)
                t0 = time.perf_counter()
                reply = await emu.deploy(doc, str(tmp / f"{name}.yaml"), "N1")
                wall = (time.perf_counter() - t0) * 1e3
                entry: dict[str, Any] = {
                    "vertices": 2 * pairs,
                    "hosted": {"N1": 2 * pairs if sink_node == "N1" else pairs}
                    | ({"N2": pairs} if sink_node == "N2" else {}),
                    "deploy_ok": reply.ok,
                    "deploy_error": reply.error,
                    "deploy_elapsed_ms": reply.elapsed_ms,
                    "deploy_wall_ms": wall,
                }
                if reply.ok:
                    entry["sinks_with_events"] = await wait_sinks(emu, name, sink_node, pairs, 10.0)
                    entry["rss"] = await settle(pids, min_s, max_s)
                    status = await emu.status()
                    entry["hosted_status"] = {
                        n: len(st["apps"].get(name, {}).get("vertices", {}))
                        for n, st in status.items()
                    }
                results["phases"][phase] = entry
                await emu.undeploy(name, "N1")
                await asyncio.sleep(0.3)
            results["phases"]["after undeploy"] = {"rss": await settle(pids, 1.0, max_s)}
        finally:
            await emu.stop()
    return results


def render(res: dict[str, Any]) -> str:
    phases = res["phases"]
    idle = phases["idle"]["rss"]
    lines = [
        "| phase | vertices on N1 / N2 | N1 VmRSS MB | N2 VmRSS MB | N1 Δ vs idle MB "
        "| N1 KB per vertex | deploy ms (origin / wall) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for phase, entry in phases.items():
        rss = entry.get("rss")
        if rss is None:
            lines.append(f"| {phase} | - | - | - | - | - | failed: {entry.get('deploy_error')} |")
            continue
        hosted = entry.get("hosted_status") or {}
        n1, n2 = rss["N1"]["VmRSS"], rss["N2"]["VmRSS"]
        delta = n1 - idle["N1"]["VmRSS"]
        per = f"{delta * 1024 / hosted['N1']:.1f}" if hosted.get("N1") else "-"
        dep = (
            f"{entry['deploy_elapsed_ms']:.1f} / {entry['deploy_wall_ms']:.1f}"
            if "deploy_elapsed_ms" in entry
            else "-"
        )
        where = f"{hosted.get('N1', 0)} / {hosted.get('N2', 0)}" if hosted else "0 / 0"
        lines.append(f"| {phase} | {where} | {n1:.1f} | {n2:.1f} | {delta:+.1f} | {per} | {dep} |")
    lines.append("")
    worst = max(
        (e["rss"][n]["VmRSS"], p, n)
        for p, e in phases.items()
        if "rss" in e
        for n in e["rss"]
        if p in ("local", "remote")
    )
    verdict = "met" if worst[0] < TARGET_MB else "MISSED"
    lines.append(
        f"- largest RSS of a node hosting 100 vertices: {worst[0]:.1f} MB ({worst[2]}, "
        f"{worst[1]}) vs target < {TARGET_MB:.0f} MB: {verdict}"
    )
    for p, e in phases.items():
        if "sinks_with_events" in e:
            lines.append(
                f"- {p}: {e['sinks_with_events']} of {e['vertices'] // 2} sinks had received "
                "an event before the RSS was read"
            )
    lines.append(
        "- Δ vs idle is cumulative: the remote phase runs after the local one was undeployed "
        "(CPython keeps freed memory in its arenas)"
    )
    hwm = {n: phases["after undeploy"]["rss"][n]["VmHWM"] for n in ("N1", "N2")}
    lines.append(
        f"- peak RSS (VmHWM) over the whole run: N1 {hwm['N1']:.1f} MB, N2 {hwm['N2']:.1f} MB; "
        "MB = MiB"
    )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: shorter settling")
    args = ap.parse_args(argv)
    res = asyncio.run(run(args.quick))
    table = render(res)
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = "memory-quick" if args.quick else "memory"
    out = {
        "benchmark": "memory",
        "src_digest": src_digest(),
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "quick": args.quick,
        "target_mb": TARGET_MB,
        **res,
    }
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(table)
    print(table)
    ok = all(e.get("deploy_ok", True) for e in res["phases"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
