"""Route convergence on the netns backend: babeld's re-route after a link break, and when the
middleware sees it.

A square N1-N2-N4 / N1-N3-N4 on the netns testbed (a namespace per node, babeld with the
testbed's settings, every node on the kernel routing view). Each run breaks the link N1 uses
toward N4 (read from N1's kernel table) and measures, from the moment the nft set no longer
lets the link's frames through:

* kernel_hole_ms: when N1's kernel route to N4 through the broken link goes (babeld notices
  the lost hellos and, its feasibility condition permitting, switches at once; where it must
  first ask for a new sequence number the destination is unreachable meanwhile);
* kernel_reroute_ms: when N1's kernel route to N4 goes through the other neighbour (netlink
  events in N1's namespace, timestamped as they arrive);
* mso_reroute_ms: when N1's mso node reports its route to N4 through that neighbour (its own
  status, polled every 10 ms on a connection inside its namespace);
* lag_ms: mso_reroute_ms - kernel_reroute_ms, what the kernel view adds (netlink event, a
  20 ms debounce, a table dump, then the core);
* flow_gap_ms: a 200 events/s flow from N1 to N4 runs throughout (``vertices.netns``): the
  sink's inter-arrival gap that spans the break, i.e. how long the app saw nothing; events
  lost, repeated or out of order are counted over all breaks.
* declared_failed: every failure any node recorded (nobody dies: each is a live node declared
  failed -- it resets, and its vertices are restored, which repeats events at the sink).

Then the link comes back and the run waits until both agree on a route again. Also the
testbed's start: namespaces + babeld + nodes until every node is connected to every other.

Usage: .venv/bin/python bench/netns_routes.py [--runs 10] [--json FILE]
(root, or a user namespace; babeld and nftables installed: `make netns-deps`)
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import percentile, provenance, write_results
from mso.emu.netns.emulator import NetnsEmulator, check_available
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.netns"  # the vertex code the nodes import
FLOW = f"""
name: flow
vertices:
  src: {{code: {VERTICES}:BeatSource, pinned: N1, rate: 200, output: {VERTICES}:Beat}}
  sink: {{code: {VERTICES}:GapTimer, pinned: N4, input: {VERTICES}:Beat}}
edges: [[src, sink]]
"""
SQUARE = """
name: square
link_defaults: {bandwidth_mbps: 100}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N4], [N1, N3], [N3, N4]]
"""
POLL_S = 0.01
RUN_TIMEOUT_S = 15.0


class KernelWatch:
    """N1's kernel routes to one destination, as netlink events arrive (loop time)."""

    def __init__(self, netns: str, dst: str) -> None:
        self.netns, self.dst = netns, dst
        self.events: list[tuple[float, str, str | None]] = []  # (t, NEW/DEL, gateway)
        self._task: asyncio.Task[None] | None = None
        self._ipr: Any = None

    async def start(self) -> None:
        from pyroute2 import AsyncIPRoute

        self._ipr = AsyncIPRoute(netns=self.netns)
        await self._ipr.bind(groups=0x40)
        self._task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            async for msg in self._ipr.get():
                if msg.get("dst") == self.dst and msg["family"] == socket.AF_INET:
                    kind = "DEL" if msg["event"] == "RTM_DELROUTE" else "NEW"
                    self.events.append((loop.time(), kind, msg.get("gateway")))

    def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self._ipr is not None:
            self._ipr.close()


async def mso_route(emu: NetnsEmulator, node: str, dst: str) -> list[Any] | None:
    nodes = await emu.overlay(node).status(everywhere=False, timeout=5.0)
    route: list[Any] | None = nodes[node]["routes"].get(dst)
    return route


async def kernel_gateway(emu: NetnsEmulator, node: str, dst_ip: str) -> str | None:
    assert emu.testbed is not None
    proc = await asyncio.create_subprocess_exec(
        "ip", "-n", emu.testbed.netns(node), "-4", "route", "get", dst_ip,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    out, _ = await proc.communicate()
    words = out.decode().split()
    return words[words.index("via") + 1] if "via" in words else None


async def one_break(emu: NetnsEmulator, watch: KernelWatch, k: int) -> dict[str, Any]:
    tb = emu.testbed
    assert tb is not None
    loop = asyncio.get_running_loop()
    gw_ip = await kernel_gateway(emu, "N1", tb.address("N4"))
    by_ip = {tb.address(n): n for n in tb.nodes}
    old = by_ip.get(gw_ip or "")
    if old not in ("N2", "N3"):
        return {"run": k, "error": f"N1 routes to N4 via {gw_ip}"}
    new = "N3" if old == "N2" else "N2"
    new_ip = tb.address(new)
    row: dict[str, Any] = {"run": k, "broken": f"N1-{old}", "error": None}
    watch.events.clear()
    t0 = loop.time()
    await emu.set_link("N1", old, False)
    mso_at = None
    deadline = t0 + RUN_TIMEOUT_S
    while loop.time() < deadline:
        route = await mso_route(emu, "N1", "N4")
        if route is not None and route[0] == new:
            mso_at = loop.time()
            break
        await asyncio.sleep(POLL_S)
    hole = next((t for t, kind, _ in watch.events if kind == "DEL"), None)
    reroute = next((t for t, kind, gw in watch.events if kind == "NEW" and gw == new_ip), None)
    row["kernel_hole_ms"] = None if hole is None else (hole - t0) * 1e3
    row["kernel_reroute_ms"] = None if reroute is None else (reroute - t0) * 1e3
    row["mso_reroute_ms"] = None if mso_at is None else (mso_at - t0) * 1e3
    if reroute is not None and mso_at is not None:
        row["lag_ms"] = (mso_at - reroute) * 1e3
    if mso_at is None or reroute is None:
        row["error"] = "no re-route seen in time"
    await asyncio.sleep(1.0)  # the flow resumes (a pause, then read the gap that spans t0)
    sink = await sink_stats(emu)
    spans = [(a, b) for a, b in sink["gaps"] if a <= t0 + 0.05 and b >= t0]
    row["flow_gap_ms"] = max(((b - a) * 1e3 for a, b in spans), default=None)
    # the link comes back; wait until both sides agree on some route again
    await emu.set_link("N1", old, True)
    await asyncio.sleep(3.0)  # let babeld settle before the next break (a pause, not a sync)
    for _ in range(500):
        route = await mso_route(emu, "N1", "N4")
        gw = await kernel_gateway(emu, "N1", tb.address("N4"))
        if route is not None and by_ip.get(gw or "") == route[0]:
            break
        await asyncio.sleep(POLL_S * 5)
    return row


async def declarations(emu: NetnsEmulator) -> list[list[str]]:
    """Every [failed, detector] any node recorded: the breaks kill nobody, so each is a live
    node declared failed (a reset follows, and its vertices are restored)."""
    out = []
    for node in emu.nodes:
        st = (await emu.overlay(node).status(everywhere=False, timeout=5.0))[node]
        out += [[f["node"], f["detector"]] for f in st["failures"]]
    return out


async def sink_stats(emu: NetnsEmulator) -> dict[str, Any]:
    nodes = await emu.overlay("N4").status(everywhere=False, timeout=5.0)
    stats: dict[str, Any] = nodes["N4"]["apps"]["flow"]["vertices"]["sink"]["stats"]
    return stats


def summary(values: list[float]) -> dict[str, Any]:
    if not values:
        return {"n": 0, "p50_ms": None, "p90_ms": None, "max_ms": None, "mean_ms": None}
    return {
        "n": len(values),
        "p50_ms": percentile(values, 50),
        "p90_ms": percentile(values, 90),
        "max_ms": max(values),
        "mean_ms": sum(values) / len(values),
    }


async def run(runs: int) -> dict[str, Any]:
    check_available()
    t_start = time.monotonic()
    emu = NetnsEmulator(loads_scenario(SQUARE), manage=False)
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    await emu.start()
    started_ms = (loop.time() - t0) * 1e3
    assert emu.testbed is not None
    watch = KernelWatch(emu.testbed.netns("N1"), emu.testbed.address("N4"))
    rows = []
    sink: dict[str, Any] = {}
    declared: list[list[str]] = []
    try:
        await watch.start()
        await emu.deploy(FLOW, "flow.yaml", "N1", check=True)
        await asyncio.sleep(1.0)
        for k in range(runs):
            row = await one_break(emu, watch, k)
            print(row, file=sys.stderr)
            rows.append(row)
        sink = await sink_stats(emu)
        declared = await declarations(emu)
    finally:
        watch.close()
        await emu.stop()
    ok = [r for r in rows if not r["error"]]
    return {
        "benchmark": "netns_routes",
        "scenario": "square N1-N2-N4 / N1-N3-N4, babeld (wired, split-horizon off, hello 0.5 s, "
        "smoothing-half-life 0)",
        "runs": runs,
        "start_ms": started_ms,
        "kernel_hole_ms": summary([r["kernel_hole_ms"] for r in ok if r["kernel_hole_ms"]]),
        "kernel_reroute_ms": summary([r["kernel_reroute_ms"] for r in ok]),
        "mso_reroute_ms": summary([r["mso_reroute_ms"] for r in ok]),
        "lag_ms": summary([r["lag_ms"] for r in ok]),
        "flow_gap_ms": summary([r["flow_gap_ms"] for r in ok if r.get("flow_gap_ms")]),
        "flow": {k: sink.get(k) for k in ("count", "repeats", "out_of_order")},
        "declared_failed": declared,
        "failures": [r for r in rows if r["error"]],
        "rows": rows,
        "seconds": time.monotonic() - t_start,
    } | provenance()


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f}"


def render(result: dict[str, Any]) -> str:
    lines = [
        f"Route convergence after a link break, netns backend ({result['scenario']}), "
        f"{result['runs']} breaks:",
        "",
        "| figure | p50 ms | p90 ms | max ms | n |",
        "|---|---:|---:|---:|---:|",
    ]
    for key, label in (
        ("kernel_hole_ms", "babeld drops the old route (kernel)"),
        ("kernel_reroute_ms", "babeld installs the new route (kernel)"),
        ("mso_reroute_ms", "mso's node reports the new route"),
        ("lag_ms", "mso after the kernel"),
        ("flow_gap_ms", "a 200 events/s flow N1 -> N4 sees nothing for"),
    ):
        s = result[key]
        lines.append(
            f"| {label} | {_f(s['p50_ms'])} | {_f(s['p90_ms'])} | {_f(s['max_ms'])} | {s['n']} |"
        )
    lines.append("")
    lines.append(
        f"- start (namespaces, babeld, 4 nodes connected to each other): "
        f"{result['start_ms']:.0f} ms; failures: {len(result['failures'])}"
    )
    f = result["flow"]
    lines.append(
        f"- the flow over all breaks: {f['count']} events delivered, {f['repeats']} repeated, "
        f"{f['out_of_order']} out of order (a gap in the sequence: lost)"
    )
    lines.append(
        f"- live nodes declared failed (every node's records, summed): "
        f"{len(result['declared_failed'])}"
    )
    load = result.get("machine", {}).get("load_average")
    lines.append(f"- load average at the end: {load} (a shared 2-vCPU VM, other agents running)")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--runs", type=int, default=10, help="link breaks (default 10)")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    args = ap.parse_args(argv)
    if not 1 <= args.runs <= 100:
        ap.error("--runs: 1..100")
    result = asyncio.run(run(args.runs))
    write_results(args.json or RESULTS / "netns_routes.json", result, render(result))
    return 1 if result["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
