"""The TCP transport on loopback: frames for a neighbour still connecting are held, and a
relay forwards frames for others hop by hop without handing them to its own receiver."""

from __future__ import annotations

import asyncio

from mso.client import overlay_key
from mso.net.base import Receiver, encode
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.protocol import messages as m

HOST = "127.0.0.1"
KEY = overlay_key("k")


def test_a_frame_crosses_a_relay() -> None:
    async def run() -> None:
        names = ["N1", "N2", "N3"]
        views = {n: EmulatorRoutes(n) for n in names}
        nets = {n: TcpTransport(n, HOST, 0, KEY, views[n]) for n in names}
        got: dict[str, list[tuple[str, m.Message]]] = {n: [] for n in names}
        arrived = asyncio.Event()

        def receiver(node: str) -> Receiver:
            def receive(src: str, msg: m.Message) -> None:
                got[node].append((src, msg))
                if node == "N3":
                    arrived.set()

            return receive

        for n in names:
            nets[n].set_receiver(receiver(n))
            await nets[n].start()
        try:

            def spec(n: str) -> list[object]:
                return [HOST, nets[n].port, None, 0.0, 0.0]

            line = {"N1": ["N2"], "N2": ["N1", "N3"], "N3": ["N2"]}
            far = {"N1": ("N3", "N2"), "N3": ("N1", "N2")}
            for n in names:
                routes: dict[str, list[object]] = {p: [p, 1] for p in line[n]}
                if n in far:
                    routes[far[n][0]] = [far[n][1], 2]
                views[n].apply(m.LinkState(1, {p: spec(p) for p in line[n]}, routes))
            # sent at once, while N1 is still connecting to N2: held for N2, then relayed
            probe = m.Probe("app", 0, 0, "N1", "N3", ["N1"], [1.0])
            nets["N1"].send("N3", *encode("N1", "N3", probe))
            await asyncio.wait_for(arrived.wait(), 10)
            assert got["N3"] == [("N1", probe)] and not got["N2"]
            assert views["N2"].counters.bytes_forwarded > 0
            assert views["N1"].counters.bytes_forwarded == 0
        finally:
            for n in names:
                await nets[n].close()

    asyncio.run(run())


def test_data_for_an_unreachable_node_is_dropped_and_control_waits() -> None:
    async def run() -> None:
        view = EmulatorRoutes("N1")
        net = TcpTransport("N1", HOST, 0, KEY, view)
        net.send("N9", *encode("N1", "N9", m.Ack("app", 0, 0, 1)))
        net.send("N9", *encode("N1", "N9", m.Probe("app", 0, 0, "N1", "N9", ["N1"], [1.0])))
        assert view.counters.frames_unroutable == 1 and len(net.waiting) == 1
        await net.close()

    asyncio.run(run())
