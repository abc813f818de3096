"""The emulator never gives up: seeded random fault sequences on the user-space backend.

Each run starts a fresh emulator on a 5-node mesh (N1..N5, 0.5 ms links; N1 and N5 each hear
the three relays N2, N3, N4, so no single failure cuts them apart), deploys
``src (N1) -> mid -> sink (N5)`` (``mso.benchmarks.vertices.failure``: a counting source at
100 events/s, a pass-through, an order-checking sink), lets it flow for a second, then plays one
seeded sequence of ``--steps`` faults (``mso.emu.faultplay.random_sequence``: a ``kill -9`` by
hand, ``fail``, ``restart``, ``cut``, ``heal`` and ``move`` in random order, ``--gap`` seconds
apart; links follow positions, radio range 150 m; the source's and the sink's nodes are never
failed, only cut off or moved out of range), then restarts every node still down, heals every
cut and moves every node back home. Commands go through the same path as the console's
(:class:`mso.emu.commands.Commands`); a kill is a SIGKILL by PID that no command announced.

Figures per run:

* completed: the run ended (no exception, within ``RUN_TIMEOUT_S``) with its summary, i.e. a
  final status that every node answered (nodes that restarted included), within 30 s of the
  last step;
* refused: commands the emulator refused (a valid sequence has none), not_back: nodes told
  "did not come back";
* lost: events the source sent (read after the drain) that the sink never got -- its holes
  plus what lies beyond its highest seq; of them, dropped_parked: events dropped at the
  source's side while the chain had no route or no host (a cut, a failed ``mid`` not yet
  restored: mso parks a chain and does not buffer); the rest went down with a node that
  failed before it was detected (fail-stop, no replication). duplicated: events the sink got
  twice. Both are counted over the runs whose source and sink instances lived through:
  a node cut off long enough to be declared failed is reset (as a new incarnation it drops
  its apps) and its vertices are started again by the recovery. A replaced sink starts
  mid-stream (its first event is not 0: ``sink_replaced``); a replaced source numbers its
  events from 0 again (this bench's source keeps its own count, which a reset loses), so the
  sink sees them as repeats (``source_replaced``). A node's incarnation changing between the
  deployment and the end says it was reset. Such runs still count as completed; their figures
  are in the JSON.

Usage: .venv/bin/python bench/emulator_faults.py [--runs 50] [--steps 10] [--gap 0.3]
                                                [--seed 1] [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.emu.commands import Commands
from mso.emu.controller import Emulator
from mso.emu.faultplay import Step, random_sequence
from mso.errors import MsoError
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.failure"
RATE = 100.0
STEADY_S = 1.0
SETTLE_S = 30.0  # bound on every node answering after the last step
DRAIN_S = 5.0  # bound on the sink catching up with the source
RUN_TIMEOUT_S = 120.0
SCENARIO = """\
name: faults5
link_defaults: {delay_ms: 0.5}
radio_range: 150
nodes:
  N1: {pos: [0, 0]}
  N2: {pos: [100, 100]}
  N3: {pos: [100, -100]}
  N4: {pos: [100, 0]}
  N5: {pos: [200, 0]}
"""
APP = f"""\
name: faults
vertices:
  src:  {{code: {VERTICES}:CountingSource, pinned: N1, rate: {RATE:g}, output: {VERTICES}:Seq}}
  mid:  {{code: {VERTICES}:PassThrough, input: {VERTICES}:Seq, output: {VERTICES}:Seq}}
  sink: {{code: {VERTICES}:GapSink, pinned: N5, input: {VERTICES}:Seq}}
edges:
  - [src, mid]
  - [mid, sink]
"""


def _vertex(nodes: dict[str, Any], vertex: str) -> dict[str, Any] | None:
    for st in nodes.values():
        found = st.get("apps", {}).get("faults", {}).get("vertices", {}).get(vertex)
        if found is not None:
            return dict(found)
    return None


async def _everyone(emu: Emulator) -> dict[str, Any] | None:
    """The status once every node answers it (None if that does not happen in time)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + SETTLE_S
    while loop.time() < deadline:
        try:
            nodes = await emu.status()
        except MsoError:
            nodes = {}
        if sorted(nodes) == sorted(emu.nodes):
            return nodes
        await asyncio.sleep(0.25)  # polling the overlay: there is no event to wait on
    return None


async def _play(emu: Emulator, steps: list[Step], gap: float) -> int:
    """Play the steps; how many commands were refused."""
    commands = Commands(emu)
    refused = 0
    for step in steps:
        if step.kind == "kill":
            proc = emu.nodes[step.node].process
            if proc is not None and proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)  # a user's kill -9: no command
                await asyncio.to_thread(proc.wait, 10)
        else:
            answer = await commands.reply(step.line)
            if not answer["ok"]:
                refused += 1
                print(f"    refused {step.line!r}: {answer['error']}", file=sys.stderr)
        await asyncio.sleep(gap)  # the pace of the faults
    return refused


async def one_run(seed: int, steps_n: int, gap: float) -> dict[str, Any]:
    scenario = loads_scenario(SCENARIO)
    links = sorted(scenario.network.links)
    home = {n: s.pos for n, s in scenario.network.nodes.items() if s.pos is not None}
    steps = random_sequence(
        seed, list(scenario.network.nodes), links, steps_n, keep=("N1", "N5"), area=(200, 100),
        home=home,
    )  # fmt: skip
    told: list[str] = []
    logs = tempfile.TemporaryDirectory(prefix="mso-emu-bench-")  # removed, crashes or not
    emu = Emulator(scenario, manage=False, log_dir=Path(logs.name))
    emu.tell = lambda at, text: told.append(f"{at:.1f} {text}")
    row: dict[str, Any] = {"seed": seed, "steps": [s.line for s in steps], "completed": False}
    t = time.monotonic()
    await emu.start()
    try:
        reply = await emu.deploy(APP, "faults.yaml", "N1")
        if not reply.ok:
            row["error"] = f"deploy: {reply.error}"
            return row
        await asyncio.sleep(STEADY_S)
        ends = ("N1", "N5")  # the source's and the sink's nodes: a reset replaces their vertex
        before = await emu.status()
        incarnations = {n: before[n]["incarnation"] for n in ends if n in before}
        row["refused"] = await _play(emu, steps, gap)
        final = await _everyone(emu)
        row["summary"] = final is not None
        if final is None:
            row["error"] = "not every node answered within 30 s of the last step"
            return row
        loop = asyncio.get_running_loop()
        deadline = loop.time() + DRAIN_S
        src = _vertex(final, "src") or {}
        sent = int(src.get("stats", {}).get("sent", 0))
        sink: dict[str, Any] = {}
        while loop.time() < deadline:
            nodes = await emu.status()
            sink = (_vertex(nodes, "sink") or {}).get("stats", {})
            if int(sink.get("next", 0)) >= sent:
                break
            await asyncio.sleep(0.1)
        first = int(sink.get("first_seq", 0))
        parked: dict[str, int] = {}  # edge -> events dropped while its chain had no route
        for st in nodes.values():
            app = st.get("apps", {}).get("faults", {})
            for edge, k in app.get("dropped_parked", {}).items():
                parked[edge] = max(parked.get(edge, 0), int(k))
        row.update(
            dropped_parked=sum(parked.values()),
            completed=True,
            sent=sent,
            received=int(sink.get("count", 0)),
            sink_replaced=first > 0 or final["N5"]["incarnation"] != incarnations.get("N5"),
            source_replaced=final["N1"]["incarnation"] != incarnations.get("N1"),
            lost=int(sink.get("missing", 0)) + max(0, sent - int(sink.get("next", 0))),
            duplicated=int(sink.get("repeats", 0)),
            not_back=sum("did not come back" in line for line in told),
        )
        return row
    finally:
        await emu.stop()
        logs.cleanup()
        row["seconds"] = round(time.monotonic() - t, 1)
        row["told"] = told[-40:]


def table(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    done = [r for r in rows if r["completed"]]
    whole = [r for r in done if not r["sink_replaced"] and not r["source_replaced"]]
    kinds: dict[str, int] = {}
    for r in rows:
        for line in r["steps"]:
            kinds[line.split()[0]] = kinds.get(line.split()[0], 0) + 1
    sent = sum(r["sent"] for r in whole)
    lost = sum(r["lost"] for r in whole)
    parked = sum(min(r["lost"], r["dropped_parked"]) for r in whole)
    lines = [
        "| sequences | completed with summary | refused commands | not back | events sent "
        "(source and sink kept) | lost | of which dropped while parked | duplicated "
        "| source or sink replaced | s/run (p50) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {len(rows)} | {len(done)} of {len(rows)} | {sum(r.get('refused', 0) for r in rows)} "
        f"| {sum(r.get('not_back', 0) for r in done)} | {sent} | {lost} | {parked} "
        f"| {sum(r['duplicated'] for r in whole)} | {len(done) - len(whole)} "
        f"| {statistics.median(r['seconds'] for r in rows):.1f} |",
        "",
        f"{args.steps} faults a sequence, {args.gap:g} s apart, seeds {args.seed}.."
        f"{args.seed + len(rows) - 1}; steps played: "
        + ", ".join(f"{k} {n}" for k, n in sorted(kinds.items()))
        + " (a kill is a SIGKILL by hand, no command).",
    ]
    bad = [r for r in rows if not r["completed"]]
    for r in bad:
        lines.append(f"- seed {r['seed']}: {r.get('error', 'did not complete')}")
    return "\n".join(lines) + "\n"


async def main_async(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    budget = time.monotonic() + args.runs * RUN_TIMEOUT_S
    for i in range(args.runs):
        seed = args.seed + i
        if time.monotonic() > budget:
            break
        try:
            row = await asyncio.wait_for(one_run(seed, args.steps, args.gap), RUN_TIMEOUT_S)
        except (TimeoutError, MsoError) as exc:
            row = {"seed": seed, "steps": [], "completed": False, "error": repr(exc)}
            row["seconds"] = RUN_TIMEOUT_S
        rows.append(row)
        print(
            f"seed {seed}: completed={row['completed']} lost={row.get('lost')} "
            f"(parked {row.get('dropped_parked')}) "
            f"dup={row.get('duplicated')} refused={row.get('refused')} ({row['seconds']} s)",
            file=sys.stderr,
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--gap", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="5 sequences")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if args.quick:
        args.runs = 5
    if not 1 <= args.runs <= 500 or not 1 <= args.steps <= 100 or not 0 <= args.gap <= 10:
        ap.error("--runs 1..500, --steps 1..100, --gap 0..10")
    t = time.monotonic()
    rows = asyncio.run(main_async(args))
    name = "emulator_faults-quick.json" if args.quick else "emulator_faults.json"
    out = args.json or RESULTS / name
    result = {
        "benchmark": "emulator_faults",
        "runs": rows,
        "settings": {"steps": args.steps, "gap_s": args.gap, "seed": args.seed, "rate": RATE},
        "completed": sum(r["completed"] for r in rows),
        "seconds": time.monotonic() - t,
        **provenance(),
    }
    write_results(out, result, table(rows, args))


if __name__ == "__main__":
    main()
