"""Documents cost what their size says (issue 27, Build 5): the worst a document within the
limits can cost a node to load, validate and plan.

Cases, each in a fresh child process (its peak RSS its own):

- ``flow``, ``block``, ``map``: 4 MiB documents of tiny scalars (``[0,0,...]`` in a policy's
  params, a block sequence of ``- 0``, a flow mapping of ``kN: 0``): 21 s and 1 GB to validate
  before the node limit; now refused (``more than 200,000 nodes``) after counting that many;
- ``largest``: the largest app the limits allow, 5,000 vertices and 20,000 edges (a random DAG
  whose every vertex has edges to the next 50, 510 pinned, on a random 30-node network):
  loaded and validated (``loads_app``), then planned (``plan``, the paper's split and bytes),
  and its chains' layout as each node derives it (``Layout``, with the parts it makes on
  first use: dependencies, kinds, stamped vertices, each edge's chain);
- ``largest-old``: the same plan with the reachability walk per chain it replaced, timed
  up to ``--old-limit`` seconds (it took 189 s; not run unless asked).

Figures are CPU seconds of the child (``time.process_time``, so that a loaded machine's
waiting does not count; the wall time is there too) and its peak RSS.

Usage: .venv/bin/python bench/documents.py [--repeat 3] [--out bench/results/documents.json]
"""

from __future__ import annotations

import argparse
import json
import random
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
CASES = ["flow", "block", "map", "largest"]
MIB4 = 4 * 1024 * 1024


def tiny_scalars(kind: str) -> str:
    if kind == "flow":
        head = "name: big\nvertices:\n  A: {}\npolicy:\n  code: m:P\n  params: {x: ["
        return head + "0," * ((MIB4 - len(head) - 10) // 2) + "0]}\n"
    if kind == "block":
        head = "name: big\nvertices:\n  A: {}\nx:\n"
        return head + "- 0\n" * ((MIB4 - len(head) - 1) // 4)
    head, parts, size, i = "name: big\nvertices:\n  A: {}\nx: {", [], 0, 0
    while size < MIB4 - len(head) - 100:
        parts.append(f"k{i}: 0,")
        size += len(parts[-1])
        i += 1
    return head + "".join(parts)[:-1] + "}\n"


def largest(seed: int = 1) -> tuple[str, Any]:
    """The largest app the limits allow, as its YAML, and a network to plan it on."""
    sys.path.insert(0, str(HERE))
    from mso.model.appfile import MAX_EDGES, MAX_VERTICES
    from placement import random_network

    rng = random.Random(seed)
    net = random_network(rng, 30)
    nodes = list(net.nodes)
    lines = ["name: biggest", "vertices:"]
    for i in range(MAX_VERTICES):
        pin = f", pinned: {rng.choice(nodes)}" if i % 10 == 0 or i >= MAX_VERTICES - 10 else ""
        lines.append(f"  v{i}: {{cost: {rng.uniform(0.5, 5):.2f}{pin}}}")
    lines.append("edges:")
    edges = {(i, i + 1) for i in range(MAX_VERTICES - 1)}
    while len(edges) < MAX_EDGES:
        a = rng.randrange(MAX_VERTICES - 1)
        edges.add((a, rng.randrange(a + 1, min(MAX_VERTICES, a + 50))))
    lines += [f"  - {{from: v{a}, to: v{b}, size: 100}}" for a, b in sorted(edges)]
    return "\n".join(lines) + "\n", net


def timed(fn: Any, repeat: int) -> dict[str, float]:
    cpu, wall = [], []
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return {"cpu_s": min(cpu), "wall_s": min(wall)}


def worker(case: str, repeat: int) -> dict[str, Any]:
    from mso.errors import MsoError
    from mso.model.appfile import loads_app
    from mso.planning.placement import Layout, plan

    out: dict[str, Any] = {"case": case}
    if case in ("flow", "block", "map"):
        text = tiny_scalars(case)
        out["bytes"] = len(text)

        def load() -> None:
            try:
                loads_app(text, resolve_code=False)
            except MsoError as exc:
                out["refused"] = str(exc)

        out["load"] = timed(load, repeat)
    else:
        text, net = largest()
        out["bytes"] = len(text)
        out["load"] = timed(lambda: loads_app(text), repeat)
        app = loads_app(text)
        out["vertices"], out["edges"] = len(app.vertices), len(app.edges)
        out["plan_paper"] = timed(lambda: plan(app, net, planner="paper"), repeat)
        out["plan_bytes"] = timed(lambda: plan(app, net, planner="bytes"), repeat)

        def layout() -> None:
            """As a deploying node derives it: what it makes on first use included."""
            lay = Layout(app, "n0")
            _ = lay.deps, lay.stamped, lay.kinds, lay.edge_chain, lay.out_edges

        out["layout"] = timed(layout, repeat)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def table(rows: list[dict[str, Any]], load: list[float]) -> str:
    lines = [
        f"Load average at the start: {' '.join(f'{x:.1f}' for x in load)} (2 CPUs). "
        "CPU s = the child's CPU time (fastest of the repeats); wall s beside it.",
        "",
        "| case | bytes | what | CPU s | wall s | peak RSS MB | outcome |",
        "|---|---:|---|---:|---:|---:|---|",
    ]
    for r in rows:
        steps = [k for k in ("load", "plan_paper", "plan_bytes", "layout") if k in r]
        for k in steps:
            outcome = r.get("refused", "ok") if k == "load" else "ok"
            lines.append(
                f"| {r['case']} | {r['bytes']:,} | {k} | {r[k]['cpu_s']:.2f} | "
                f"{r[k]['wall_s']:.2f} | {r['peak_rss_mb']:.0f} | {outcome} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "documents.json")
    ap.add_argument("--worker", choices=CASES)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.repeat)))
        return
    from mso.benchmarks.common import provenance, write_results

    start, prov, rows = time.monotonic(), provenance(), []
    for case in CASES:
        cmd = [sys.executable, __file__, "--worker", case, "--repeat", str(args.repeat)]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=True)
        rows.append(json.loads(done.stdout.splitlines()[-1]))
        print(json.dumps(rows[-1]), file=sys.stderr)
    result = {**prov, "cases": rows, "seconds": time.monotonic() - start}
    write_results(args.out, result, table(rows, prov["machine"]["load_average"]))


if __name__ == "__main__":
    main()
