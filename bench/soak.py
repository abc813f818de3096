"""Soak: the convoy in the emulator for ten minutes, a relocation every second, links flapping.

The convoy app (paper Fig. 6) on the 4-robot line (``convoy-line.yaml``), management rules off
so that only the soak moves vertices. Every ``--relocate-every`` seconds a random vertex inside a
chain (chain ends are never relocated) goes to a random other node; every ``--flap-every``
seconds one of the shortcut links N1-N3, N2-N4, N1-N4 appears or disappears (routes change, the
line itself stays, so no node is cut off). Every 30 s each node process's RSS (VmRSS), open
file descriptors (/proc/PID/fd), threads, and the asyncio tasks and timers its driver reports
are sampled.

At the end the soak stops moving things, waits ``--settle`` s, reads every edge's ``sent``
count, waits ``--drain`` s more and checks each edge's consumer has ``delivered`` at least
that many: an event sent and never delivered is lost. Targets: 0 lost, RSS growth < 10%
(from the first sample after warm-up to the end), no growth in fds or tasks.

Usage: .venv/bin/python bench/soak.py [--duration 600] [--quick] [--seed 1] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.emu.controller import Emulator
from mso.model.appfile import load_app
from mso.model.chains import form_chains
from mso.model.network import LinkSpec
from mso.model.yamlfile import read_text_file
from mso.scenario import load_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"
SHORTCUTS = [("N1", "N3"), ("N2", "N4"), ("N1", "N4")]


def proc_sample(pid: int) -> dict[str, int]:
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    fields = {ln.split(":")[0]: ln.split(":")[1].split() for ln in status if ":" in ln}
    return {
        "rss_kb": int(fields["VmRSS"][0]),
        "threads": int(fields["Threads"][0]),
        "fds": len(os.listdir(f"/proc/{pid}/fd")),
    }


async def sample(emu: Emulator, t: float) -> dict[str, Any]:
    nodes = await emu.status()
    out: dict[str, Any] = {"t": round(t, 1)}
    for name, node in emu.nodes.items():
        assert node.process is not None
        st = nodes.get(name, {})
        out[name] = proc_sample(node.process.pid) | {
            "tasks": st.get("tasks", -1),
            "timers": st.get("timers", -1),
        }
    return out


def edges(nodes: dict[str, Any]) -> dict[str, dict[str, int]]:
    """Per edge: the most any node reports sent and delivered (each end reports its side)."""
    out: dict[str, dict[str, int]] = {}
    for st in nodes.values():
        for e, c in st.get("apps", {}).get("convoy", {}).get("edges", {}).items():
            agg = out.setdefault(e, {"sent": 0, "delivered": 0})
            agg["sent"] = max(agg["sent"], int(c.get("sent", 0)))
            agg["delivered"] = max(agg["delivered"], int(c.get("delivered", 0)))
    return out


async def soak(args: argparse.Namespace) -> dict[str, Any]:
    rng = random.Random(args.seed)
    app_file = EXAMPLES / "convoy.yaml"
    app = load_app(app_file)
    # chain ends are never relocated (the node refuses): only the inside of chains moves
    movable = sorted({v for c in form_chains(app) for v in c.vertices[1:-1]})
    emu = Emulator(load_scenario(EXAMPLES / "convoy-line.yaml"), manage=False)
    await emu.start()
    loop = asyncio.get_running_loop()
    moves: dict[str, Any] = {"ok": 0, "refused": 0, "errors": []}
    flaps = 0
    samples = []
    try:
        reply = await emu.deploy(read_text_file(app_file), str(app_file), "N1")
        assert reply.ok, reply.error
        placement = dict(reply.placement)
        await asyncio.sleep(args.warmup)
        t0 = loop.time()
        samples.append(await sample(emu, 0.0))
        next_move, next_flap, next_sample = t0, t0 + args.flap_every, t0 + 30.0
        up: set[tuple[str, str]] = set()
        while (now := loop.time()) < t0 + args.duration:
            if now >= next_move:
                next_move += args.relocate_every
                v = rng.choice(movable)
                target = rng.choice([n for n in emu.nodes if n != placement.get(v)])
                try:
                    r = await emu.relocate("convoy", v, target=target)
                    if r.ok:
                        moves["ok"] += 1
                        placement[v] = r.node
                    else:
                        moves["refused"] += 1
                        if len(moves["errors"]) < 20:
                            moves["errors"].append(f"{v}->{target}: {r.error}")
                except Exception as exc:  # a failed call is counted, the soak goes on
                    moves["refused"] += 1
                    moves["errors"].append(f"{v}->{target}: {type(exc).__name__}: {exc}")
            if now >= next_flap:
                next_flap += args.flap_every
                link = rng.choice(SHORTCUTS)
                if link in up:
                    up.discard(link)
                    await emu.set_link(*link, up=False)
                else:
                    up.add(link)
                    await emu.set_link(*link, up=True, link=LinkSpec(*link, delay_ms=0.1))
                flaps += 1
            if now >= next_sample:
                next_sample += 30.0
                samples.append(await sample(emu, now - t0))
                print(f"t={now - t0:.0f}s {moves['ok']} moves, {flaps} flaps, "
                      f"RSS {[samples[-1][n]['rss_kb'] // 1024 for n in emu.nodes]} MB",
                      file=sys.stderr)  # fmt: skip
            await asyncio.sleep(max(0.0, min(next_move, next_flap, next_sample) - loop.time()))
        for link in sorted(up):  # back to the line
            await emu.set_link(*link, up=False)
        await asyncio.sleep(args.settle)
        sent = edges(await emu.status())
        await asyncio.sleep(args.drain)
        final = await emu.status()
        delivered = edges(final)
        samples.append(await sample(emu, loop.time() - t0))
        lost = {
            e: sent[e]["sent"] - delivered[e]["delivered"]
            for e in sent
            if delivered.get(e, {}).get("delivered", 0) < sent[e]["sent"]
        }
        return {
            "duration_s": args.duration,
            "moves": moves,
            "flaps": flaps,
            "edges": {e: {"sent_at_end": sent[e]["sent"], **delivered[e]} for e in sent},
            "lost": lost,
            "failed_nodes": sorted(
                {f for st in final.values() for f in st.get("failed_nodes", [])}
            ),
            "samples": samples,
        }
    finally:
        await emu.stop()


def growth(samples: list[dict[str, Any]], node: str, key: str) -> float:
    first, last = samples[0][node][key], samples[-1][node][key]
    return (last - first) / first * 100 if first else 0.0


def render(r: dict[str, Any]) -> str:
    load = r["machine"]["load_average"]
    s = r["samples"]
    lines = [
        f"### Soak: convoy, {r['duration_s']:g} s, a relocation every {r['relocate_every_s']:g} s, "
        f"links flapping every {r['flap_every_s']:g} s",
        "",
        f"Machine: {r['machine']['cpus']} vCPUs, load average "
        f"{', '.join(f'{x:.1f}' for x in load)} (shared, loaded). Relocations: "
        f"{r['moves']['ok']} done, {r['moves']['refused']} refused; {r['flaps']} link flaps; "
        f"events lost: {sum(r['lost'].values())}; failed nodes: {r['failed_nodes'] or 'none'}.",
        "",
        "| node | RSS start MB | RSS end MB | growth | fds start / end | threads start / end "
        "| tasks start / end | timers start / end |",
        "|---|---:|---:|---:|---|---|---|---|",
    ]
    for n in ("N1", "N2", "N3", "N4"):
        a, b = s[0][n], s[-1][n]
        lines.append(
            f"| {n} | {a['rss_kb'] / 1024:.1f} | {b['rss_kb'] / 1024:.1f} "
            f"| {growth(s, n, 'rss_kb'):+.1f}% | {a['fds']} / {b['fds']} "
            f"| {a['threads']} / {b['threads']} | {a['tasks']} / {b['tasks']} "
            f"| {a['timers']} / {b['timers']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--relocate-every", type=float, default=1.0)
    ap.add_argument("--flap-every", type=float, default=3.0)
    ap.add_argument("--warmup", type=float, default=10.0)
    ap.add_argument("--settle", type=float, default=5.0)
    ap.add_argument("--drain", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="60 s")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.quick:
        args.duration = 60.0
    if not 10 <= args.duration <= 4 * 3600 or not 0.1 <= args.relocate_every <= 60:
        ap.error("--duration 10..14400 s, --relocate-every 0.1..60 s")
    out: Path = args.json or RESULTS / ("soak-quick.json" if args.quick else "soak.json")
    t0 = time.monotonic()
    result = asyncio.run(soak(args))
    result |= {
        "benchmark": "soak",
        "seed": args.seed,
        "relocate_every_s": args.relocate_every,
        "flap_every_s": args.flap_every,
        "seconds": time.monotonic() - t0,
    }
    result |= provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
