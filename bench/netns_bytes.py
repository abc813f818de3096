"""Byte accounting on the netns backend: what mso counts against what the kernel counted.

On the line N1 - N2 - N3 (netns testbed, babeld, 100 Mbit/s tbf), a source pinned to N1 sends
fixed-size events to a sink pinned to N3; the kernel of N2 forwards them (mso relays nothing).
Over an idle window (no app: babeld, announcements, heartbeats) and then a window with the app
flowing, the benchmark reads mso's socket counters (``bytes_out``/``bytes_in`` of every node)
and the kernel's ``eth0`` counters (bytes and packets) of every node, and compares:

* the flow as mso accounts it: N1's and N3's ``bytes_out`` (the events and the acks going back),
  less the idle rate;
* the bytes N2's kernel forwarded: its eth0 ``tx_bytes`` less the idle rate (the relay's own
  traffic and the background), raw and without the 66 bytes of Ethernet, IP and TCP headers
  (with timestamps) that each forwarded packet carries, counted from ``tx_packets``;
* N1's kernel ``tx_bytes`` against its ``bytes_out``, the same way.

Usage: .venv/bin/python bench/netns_bytes.py [--rate 500] [--size 1200] [--seconds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.emu.netns.emulator import NetnsEmulator, check_available
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.netns"  # the vertex code the nodes import
LINE = """
name: line3
link_defaults: {bandwidth_mbps: 100}
nodes: {N1: {}, N2: {}, N3: {}}
links: [[N1, N2], [N2, N3]]
"""
HEADER_BYTES = 66  # Ethernet 14 + IPv4 20 + TCP 20 + timestamps 12
NODES = ("N1", "N2", "N3")


def app(rate: float, size: int) -> str:
    return f"""
name: bytes
vertices:
  src: {{code: {VERTICES}:BlobSource, pinned: N1, rate: {rate}, params: {{size: {size}}},
        output: {VERTICES}:Blob}}
  sink: {{code: {VERTICES}:CountingSink, pinned: N3}}
edges: [[src, sink]]
"""


async def read(emu: NetnsEmulator) -> dict[str, dict[str, int]]:
    """Every node's mso socket counters and kernel eth0 counters, read back to back."""
    status = await emu.status("N2")
    out = {}
    for n in NODES:
        k = emu.counters(n)
        t = status[n]["traffic"]
        out[n] = {"mso_out": t["bytes_out"], "mso_in": t["bytes_in"]} | k
    return out


def delta(a: dict[str, dict[str, int]], b: dict[str, dict[str, int]]) -> dict[str, Any]:
    return {n: {k: b[n][k] - a[n][k] for k in a[n]} for n in a}


async def run(rate: float, size: int, seconds: float) -> dict[str, Any]:
    check_available()
    t_start = time.monotonic()
    emu = NetnsEmulator(loads_scenario(LINE), manage=False)
    loop = asyncio.get_running_loop()
    try:
        await emu.start()
        await asyncio.sleep(1.0)
        t0, c0 = loop.time(), await read(emu)
        await asyncio.sleep(seconds)  # the idle window
        t1, c1 = loop.time(), await read(emu)
        await emu.deploy(app(rate, size), "bytes.yaml", "N1", check=True)
        await asyncio.sleep(1.0)
        t2, c2 = loop.time(), await read(emu)
        await asyncio.sleep(seconds)  # the flowing window
        t3, c3 = loop.time(), await read(emu)
        sink = (await emu.status("N3"))["N3"]["apps"]["bytes"]["vertices"]["sink"]["stats"]
    finally:
        await emu.stop()
    idle, flow = delta(c0, c1), delta(c2, c3)
    scale = (t3 - t2) / (t1 - t0)

    def net(node: str, key: str) -> float:
        """What the app added: the flowing window less the idle rate."""
        return flow[node][key] - idle[node][key] * scale

    mso_flow = net("N1", "mso_out") + net("N3", "mso_out")
    fwd_raw = net("N2", "tx_bytes")
    fwd_packets = net("N2", "tx_packets")
    fwd_payload = fwd_raw - HEADER_BYTES * fwd_packets
    n1_raw = net("N1", "tx_bytes")
    n1_payload = n1_raw - HEADER_BYTES * net("N1", "tx_packets")
    n1_mso = net("N1", "mso_out")
    return {
        "benchmark": "netns_bytes",
        "rate": rate,
        "size": size,
        "window_s": t3 - t2,
        "idle": idle,
        "flow": flow,
        "sink": sink,
        "mso_flow_bytes": mso_flow,
        "relay_kernel_tx_bytes": fwd_raw,
        "relay_kernel_tx_packets": fwd_packets,
        "relay_kernel_payload_bytes": fwd_payload,
        "relay_raw_over_mso": fwd_raw / mso_flow if mso_flow else None,
        "relay_payload_over_mso": fwd_payload / mso_flow if mso_flow else None,
        "source_kernel_tx_bytes": n1_raw,
        "source_mso_out_bytes": n1_mso,
        "source_raw_over_mso": n1_raw / n1_mso if n1_mso else None,
        "source_payload_over_mso": n1_payload / n1_mso if n1_mso else None,
        "seconds": time.monotonic() - t_start,
    } | provenance()


def render(r: dict[str, Any]) -> str:
    def pct(x: float | None) -> str:
        return "-" if x is None else f"{(x - 1) * 100:+.1f}%"

    ratio = r["relay_payload_over_mso"]
    within = ratio is not None and abs(ratio - 1) <= 0.05
    return (
        f"Byte accounting on the netns backend: {r['rate']:g} events/s of {r['size']} B from N1 "
        f"to N3 over {r['window_s']:.1f} s, the kernel of N2 forwarding (idle rates "
        f"subtracted):\n\n"
        "| figure | bytes | vs mso |\n|---|---:|---:|\n"
        f"| mso: N1 + N3 bytes_out (events, acks) | {r['mso_flow_bytes']:,.0f} | - |\n"
        f"| kernel: N2 eth0 tx | {r['relay_kernel_tx_bytes']:,.0f} "
        f"| {pct(r['relay_raw_over_mso'])} |\n"
        f"| kernel: N2 eth0 tx less {HEADER_BYTES} B a packet "
        f"({r['relay_kernel_tx_packets']:,.0f} packets) | {r['relay_kernel_payload_bytes']:,.0f} "
        f"| {pct(r['relay_payload_over_mso'])} |\n"
        f"| mso: N1 bytes_out | {r['source_mso_out_bytes']:,.0f} | - |\n"
        f"| kernel: N1 eth0 tx | {r['source_kernel_tx_bytes']:,.0f} "
        f"| {pct(r['source_raw_over_mso'])} |\n\n"
        f"- forwarded bytes, headers removed, within 5% of mso's count: "
        f"{'yes' if within else 'NO'}; sink got {r['sink']}\n"
        f"- load average: {r['machine']['load_average']} (a shared 2-vCPU VM)\n"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--size", type=int, default=1200)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    result = asyncio.run(run(args.rate, args.size, args.seconds))
    write_results(args.json or RESULTS / "netns_bytes.json", result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
