"""A partition that heals: the sink's node is out of reach for a while, then comes back.

Simulator (virtual time, the default): a source pinned to N1 makes 10 events/s of 50 KB; a
recording sink pinned to N2 (``mso.sim.vertices``); one link between them. After 5 s of flow the
link goes down for each ``--outage`` (default 10 s, 60 s and 600 s), then comes back; the run
goes on until the sink has caught up (at most ``CATCH_UP_S`` virtual seconds). Each node's spill
store is the daemon's SQLite file (``mso.daemon.spill``) in a temporary directory, so the disk
figures are the real file's. The edge's bound is raised to 1 GiB (``buffer_bytes``): 10 min at
500 KB/s is 300 MB, past the default 256 MiB, where the default ``buffer`` policy would hold the
source (samples not taken, none lost). Figures per outage:

* emitted / delivered: events numbered on the source's edge / distinct events at the sink;
* duplicates, lost (a sequence number never delivered), out of order: target 0;
* catch-up after heal: virtual seconds from the heal until the sink holds every event emitted
  before the heal, to the 0.1 s step (the simulator models each hop's latency, not its
  bandwidth: this is the rejoin and the drain's round trips, not the transfer time);
* held MB: the most the edge held (memory and store); disk MB: the store file's largest size,
  and its size once drained;
* sent again: events (and MB) the source's node sent more than once on the edge (go-back-N
  after the heal): the radio the heal cost beyond the backlog itself.

``--emulated`` also runs the 10 s case on the user-space emulator (real ``mso node``
processes, a ``--state-dir`` each, the link N1-N2 down and up via ``Emulator.set_link``),
``--emulated-runs`` times (3: the load of the machine moves its figures); each
``--emulated-outage S`` one more emulated cut of S seconds (the 54 Mbit/s link's rate shows in
the catch-up there; the edge's held and spilled bytes and N1's state directory are polled). A
row also says whether a node reset (a new incarnation) and how many failures were declared:
a cut of a pair is to end with neither.

Usage: .venv/bin/python bench/partition.py [--outage S ...] [--emulated] [--emulated-runs N]
                                           [--emulated-outage S ...] [--json FILE]
Writes bench/results/partition.json and partition.md.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.daemon.spill import SqliteSpill
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim import vertices
from mso.sim.runner import Simulation

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
RATE = 10.0
SIZE = 50_000
STEADY_S = 5.0
CATCH_UP_S = 120.0
STEP_S = 0.1
OUTAGES = (10.0, 60.0, 600.0)
BOUND = 1 << 30
LINK = {"delay_ms": 1.0, "bandwidth_mbps": 54.0}


def app_yaml(run: str) -> str:
    ev = "output: mso.sim.vertices:Ev"
    return (
        "name: part\nvertices:\n"
        f"  src: {{code: mso.sim.vertices:Source, params: {{name: src, size: {SIZE}}}, "
        f"rate: {RATE:g}, pinned: N1, {ev}}}\n"
        f"  sink: {{code: mso.sim.vertices:Sink, params: {{run: '{run}', name: sink}}, "
        "pinned: N2}\n"
        f"edges: [{{from: src, to: sink, buffer_bytes: {BOUND}}}]\n"
    )


def delivered(run: str) -> tuple[int, int, int, int]:
    """(distinct events, duplicates, never delivered below the highest, out of order) at
    the sink, over its instances and the source's streams."""
    seen: dict[tuple[str, float], set[int]] = {}
    dups = reordered = 0
    for rec in vertices.RUNS.get(run, []):
        for key, s in rec.streams.items():
            dups += s.duplicates + len(seen.get(key, set()) & s.seen)
            reordered += s.reordered
            seen.setdefault(key, set()).update(s.seen)
    n = sum(len(s) for s in seen.values())
    lost = sum(max(s) + 1 - len(s) for s in seen.values() if s)
    return n, dups, lost, reordered


def sim_run(outage: float, tmp: Path) -> dict[str, Any]:
    run = f"partition-{outage:g}"
    vertices.RUNS.pop(run, None)
    net = Network([NodeSpec("N1"), NodeSpec("N2")], [LinkSpec("N1", "N2", **LINK)])
    stores: dict[str, SqliteSpill] = {}

    def store(node: str) -> SqliteSpill:
        stores[node] = SqliteSpill(tmp / run / node)
        return stores[node]

    wall = time.monotonic()
    sim = Simulation(net, spill=store, manage=False)
    sim.request("N1", m.DeployRequest(app_yaml(run), "partition.yaml"))
    sim.run_until(STEADY_S)
    sim.network.remove_link("N1", "N2")
    sim.links_changed()
    held = disk = 0.0
    end = sim.now + outage
    while sim.now < end:
        sim.run_until(min(end, sim.now + 1.0))
        out = sim.cores["N1"].apps["part"].out.get(0)
        held = max(held, out.kept_bytes if out is not None else 0)
        disk = max(disk, stores["N1"].disk_bytes())
    heal = sim.now
    made = sim.cores["N1"].apps["part"].out[0].next_seq
    sim.network.add_link(LinkSpec("N1", "N2", **LINK))
    sim.links_changed()
    caught_up = None
    while sim.now < heal + CATCH_UP_S:
        sim.run_until(sim.now + STEP_S)
        out = sim.cores["N1"].apps["part"].out.get(0)
        held = max(held, out.kept_bytes if out is not None else 0)
        disk = max(disk, stores["N1"].disk_bytes())
        if delivered(run)[0] >= made:
            caught_up = sim.now - heal
            break
    sim.run_until(sim.now + 2.0)  # what came after the heal arrives too; acks drain the store
    while stores["N1"].tidy():  # (the daemon's keep_tidy, a step per loop turn)
        pass
    emitted = max(  # (at the app's holders: only they hold it, issue 24.1)
        c.apps["part"].out[0].next_seq
        for c in sim.cores.values()
        if "part" in c.apps and 0 in c.apps["part"].out
    )
    n, dups, lost, reordered = delivered(run)
    out = sim.cores["N1"].apps["part"].out[0]
    given_up = sum(
        sum(c.status(sim.now)["apps"]["part"]["given_up"].values())
        for c in sim.cores.values()
        if c.apps.get("part")
    )
    row = {
        "outage_s": outage,
        "emitted": emitted,
        "emitted_before_heal": made,
        "delivered": n,
        "duplicates": dups,
        "lost": lost,
        "out_of_order": reordered,
        "given_up": given_up,
        "catch_up_s": caught_up,
        "held_mb": held / 1e6,
        "disk_mb": disk / 1e6,
        "disk_after_mb": stores["N1"].disk_bytes() / 1e6,
        "resent": out.resent,
        "resent_mb": out.resent_bytes / 1e6,
        "wall_s": time.monotonic() - wall,
    }
    for s in stores.values():
        s.close()
    vertices.RUNS.pop(run, None)
    return row


async def emulated_run(outage: float, tmp: Path) -> dict[str, Any]:
    """One cut of ``outage`` s on real node processes (each with its own ``--state-dir``): the
    edge's held and spilled bytes and N1's state directory polled every 0.2 s from the cut
    until the sink has caught up."""
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    scenario = loads_scenario(
        "name: pair\nlink_defaults: {delay_ms: 1.0, bandwidth_mbps: 54}\n"
        "nodes: {N1: {}, N2: {}}\nlinks: [[N1, N2]]\n"
    )
    app = (
        "name: part\nvertices:\n"
        f"  src: {{code: mso.benchmarks.vertices.dataplane:StampSource, rate: {RATE:g}, "
        f"pinned: N1, params: {{size: {SIZE}}}}}\n"
        "  sink: {code: mso.benchmarks.vertices.dataplane:LatencySink, pinned: N2}\n"
        f"edges: [{{from: src, to: sink, buffer_bytes: {BOUND}}}]\n"
    )
    logs = tmp / f"emulated-{outage:g}-{time.monotonic_ns()}"
    logs.mkdir()
    emu = Emulator(scenario, log_dir=logs, manage=False)
    row: dict[str, Any] = {"outage_s": outage, "error": None}
    held = spilled = disk = 0

    def state_bytes() -> int:
        return sum(f.stat().st_size for f in (logs / "state" / "N1").glob("*") if f.is_file())

    def part(st: dict[str, Any], node: str) -> dict[str, Any]:
        """``node``'s edge, or why it has none (a node that reset runs no app until told)."""
        app = st.get(node, {}).get("apps", {}).get("part")
        if app is None:
            why = "out of reach" if node not in st else f"incarnation {st[node]['incarnation']}"
            raise RuntimeError(f"{node} runs no app 'part' ({why})")
        e: dict[str, Any] = app["edges"].get("src->sink", {})
        return e

    async def edge() -> dict[str, Any]:
        nonlocal held, spilled, disk
        st = await emu.status(via="N1", timeout=10.0)
        out = part(st, "N1")
        held, spilled = max(held, out["held_bytes"]), max(spilled, out["spilled_bytes"])
        disk = max(disk, state_bytes())
        return out

    try:
        await emu.start()
        await emu.deploy(app, "partition.yaml", "N1", check=True)
        await asyncio.sleep(STEADY_S)
        first = await emu.status()
        link = scenario.network.link("N1", "N2") or LinkSpec("N1", "N2")
        loop = asyncio.get_running_loop()
        await emu.set_link("N1", "N2", False)
        cut = loop.time()
        while loop.time() < cut + outage:
            await asyncio.sleep(min(1.0, max(0.0, cut + outage - loop.time())))
            await edge()
        heal = loop.time()
        await emu.set_link("N1", "N2", True, link)
        made_before = 0
        while loop.time() < heal + max(60.0, outage / 5):
            await asyncio.sleep(0.2)
            st = await emu.status()
            out = await edge()
            if "N2" not in st:  # (it missed this round)
                continue
            got = part(st, "N2").get("delivered", 0)
            made_before = made_before or out["sent"]  # (the first poll: about the heal)
            if got >= made_before:
                row["catch_up_s"] = loop.time() - heal
                break
        # then what the source made meanwhile (it went on at the same rate behind the backlog)
        made = out["sent"]
        while loop.time() < heal + max(60.0, outage / 5) * 2:
            await asyncio.sleep(0.5)
            st = await emu.status()
            if "N2" in st and part(st, "N2").get("delivered", 0) >= made:
                row["drained_s"] = loop.time() - heal
                break
        await asyncio.sleep(1.0)
        for _ in range(40):  # the drained store's pages go back a step per loop turn
            if state_bytes() < max(disk // 20, 1 << 20):
                break
            await asyncio.sleep(0.5)
        for _ in range(20):  # a loaded node may miss one status round: asked again
            st = await emu.status()
            if "N1" in st and "N2" in st:
                break
            await asyncio.sleep(0.5)
        out, inc = part(st, "N1"), part(st, "N2")
        row |= {
            "sent": out["sent"],
            "sent_before_heal": made_before,
            "delivered": inc.get("delivered"),
            "duplicates": inc.get("duplicates"),
            "dropped": out["dropped"],
            "resent": out["resent"],
            "resent_mb": out["resent_bytes"] / 1e6,
            "held_mb": held / 1e6,
            "spilled_mb": spilled / 1e6,
            "disk_mb": disk / 1e6,
            "disk_after_mb": state_bytes() / 1e6,
            # a node that reset or restarted has a new incarnation; declared: failures recorded
            "reset": [n for n in ("N1", "N2") if st[n]["incarnation"] != first[n]["incarnation"]],
            "declared": sum(len(st[n]["failures"]) for n in ("N1", "N2")),
        }
    except Exception as exc:  # reported, never a traceback in the table
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        await emu.stop()
    return row


def render(result: dict[str, Any]) -> str:
    lines = [
        f"### A sink out of reach, then back ({RATE:g} events/s x {SIZE // 1000} KB, "
        "simulator, the daemon's SQLite spill store)",
        "",
        "| outage | emitted | delivered | duplicates | lost | out of order | catch-up after "
        "heal s | held MB (max) | disk MB (max / drained) | sent again (MB) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        up = "-" if r["catch_up_s"] is None else f"{r['catch_up_s']:.1f}"
        lines.append(
            f"| {r['outage_s']:g} s | {r['emitted']:,} | {r['delivered']:,} | {r['duplicates']} "
            f"| {r['lost']} | {r['out_of_order']} | {up} | {r['held_mb']:,.1f} "
            f"| {r['disk_mb']:,.1f} / {r['disk_after_mb']:,.2f} "
            f"| {r['resent']} ({r['resent_mb']:,.1f}) |"
        )
    emulated = result.get("emulated", [])
    if emulated:
        lines += [
            "",
            "### The same on the user-space emulator (two `mso node` processes, 54 Mbit/s, 1 ms)",
            "",
            "| outage | sent | delivered | duplicates | given up | sent again (MB) | catch-up s "
            "| held MB (max) | spilled MB (max) | disk MB (max / after) | reset / declared |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
    for r in emulated:
        if r["error"]:
            lines.append(f"| {r['outage_s']:g} s | error: {r['error']} |" + " |" * 9)
            continue
        up = r.get("catch_up_s")
        lines.append(
            f"| {r['outage_s']:g} s | {r['sent']:,} | {r['delivered']:,} | {r['duplicates']} "
            f"| {r['dropped']} | {r['resent']} ({r['resent_mb']:,.1f}) "
            f"| {'-' if up is None else f'{up:.1f}'} | {r['held_mb']:,.1f} "
            f"| {r['spilled_mb']:,.1f} | {r['disk_mb']:,.1f} / {r['disk_after_mb']:,.2f} "
            f"| {', '.join(r['reset']) or 'none'} / {r['declared']} |"
        )
    if emulated:
        lines += [
            "",
            "Delivered counts the sink's events (the newest may be in flight); catch-up is wall "
            "clock from the heal until the sink holds what was sent before it, polled every "
            "0.2 s (and the run goes on until it holds what was sent by then: the source made "
            "events behind the backlog all along); disk is N1's state directory (the SQLite "
            "spill store), its size at the end after it.",
        ]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--outage", type=float, action="append", help="seconds (repeat)")
    ap.add_argument("--emulated", action="store_true", help="also the 10 s case, emulated")
    ap.add_argument("--emulated-runs", type=int, default=3, help="how many (1..10)")
    ap.add_argument(
        "--emulated-outage", type=float, action="append", help="one more emulated cut, s (repeat)"
    )
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not 1 <= args.emulated_runs <= 10:
        ap.error("--emulated-runs: 1..10")
    outages = tuple(args.outage or OUTAGES)
    if any(o <= 0 or o > 3600 for o in outages):
        ap.error("--outage: seconds in (0, 3600]")
    cuts = [10.0] * (args.emulated_runs if args.emulated else 0) + (args.emulated_outage or [])
    if any(o <= 0 or o > 3600 for o in cuts) or len(cuts) > 20:
        ap.error("--emulated-outage: seconds in (0, 3600], at most 20 emulated runs")
    out: Path = args.json or RESULTS / "partition.json"
    started = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory(prefix="mso-partition-") as tmp:
        for outage in outages:
            row = sim_run(outage, Path(tmp))
            print(row, file=sys.stderr)
            rows.append(row)
        emulated = []
        for cut in cuts:
            emulated.append(asyncio.run(emulated_run(cut, Path(tmp))))
            print(emulated[-1], file=sys.stderr)
    result: dict[str, Any] = {
        "benchmark": "partition",
        "rate": RATE,
        "size": SIZE,
        "rows": rows,
        "emulated": emulated,
        "seconds": time.monotonic() - started,
    } | provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
