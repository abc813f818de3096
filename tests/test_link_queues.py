"""Per-class bounded link queues over TCP loopback (issue 27, item 4): a stream of large
control frames relayed through a node does not delay its heartbeats to a neighbour past the
liveness window; the relay's control queue stays bounded, and bulk frames labelled heartbeats
(to overtake everything) are refused at the relay."""

from __future__ import annotations

import asyncio
import itertools

from mso.client import overlay_key
from mso.net.base import CONTROL, HEARTBEAT, Receiver, encode
from mso.net.forwarding import RouteWait
from mso.net.limits import Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.shaping import QueueBounds
from mso.net.tcp import TcpTransport
from mso.protocol import messages as m
from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S

HOST = "127.0.0.1"
KEY = overlay_key("k")
# the whole control queue for the one member streaming (its share of it: test_security_relay)
LIMITS = Limits(
    queues=QueueBounds(control=2 << 20, relayed_share=1.0, relayed_total=1.0),  # A may fill it
    max_beat_frame=16 * 1024,
)
BULK = 256 * 1024  # one control frame of the stream
SEEN = 8  # control frames the neighbour must receive while the beats are timed


def test_relayed_bulk_control_never_delays_a_neighbours_heartbeats() -> None:
    async def run() -> None:
        names = ["A", "R", "B"]  # a line: A (the member streaming) - R (the relay) - B
        views = {n: EmulatorRoutes(n) for n in names}
        nets = {n: TcpTransport(n, HOST, 0, KEY, views[n], LIMITS) for n in names}
        beats: list[float] = []
        bulk: list[str] = []
        enough = asyncio.Event()
        loop = asyncio.get_running_loop()

        def receiver(node: str) -> Receiver:
            def receive(src: str, msg: m.Message) -> None:
                if node != "B":
                    return
                if isinstance(msg, m.Heartbeat):
                    beats.append(loop.time())
                else:
                    bulk.append(src)
                    if len(bulk) >= SEEN:
                        enough.set()

            return receive

        for n in names:
            nets[n].set_receiver(receiver(n))
            await nets[n].start()

        async def beat() -> None:  # R's heartbeats to its neighbour B, every 50 ms
            while True:
                nets["R"].send("B", *encode("R", "B", m.Heartbeat("R", 1)))
                await asyncio.sleep(0.05)  # the heartbeat period, not a synchronisation

        beating = loop.create_task(beat())
        try:
            # R's link to B carries 20 Mbit/s: one 256 KiB frame takes 0.1 s on it
            def spec(n: str, bandwidth: float | None = None) -> list[object]:
                return [HOST, nets[n].port, bandwidth, 0.0, 0.0]

            views["A"].apply(m.LinkState(1, {"R": spec("R")}, {"R": ["R", 1], "B": ["R", 2]}))
            views["B"].apply(m.LinkState(1, {"R": spec("R")}, {"R": ["R", 1], "A": ["R", 2]}))
            views["R"].apply(
                m.LinkState(
                    1, {"A": spec("A"), "B": spec("B", 20.0)}, {"A": ["A", 1], "B": ["B", 1]}
                )
            )
            while len(beats) < 3:  # the links are up and R's beats reach B
                await asyncio.sleep(0.05)
            start = loop.time()
            big = m.ChainPlaced("x", 0, {"k": "x" * BULK})
            forged = m.unwrap(encode("A", "B", big)[0])
            forged.kind = HEARTBEAT  # bulk posing as heartbeats, to overtake everything
            for _ in range(5):
                nets["A"].send("B", m.rewrap(forged), CONTROL)
            for _ in range(40):  # 10 MiB of control for B: 4 s of R's link to B
                nets["A"].send("B", *encode("A", "B", big))
            await asyncio.wait_for(enough.wait(), 10)
            during = [t for t in beats if t >= start - 0.1] + [loop.time()]
            gaps = [b - a for a, b in itertools.pairwise(during)]
            assert max(gaps) < DEAD_AFTER_S, gaps  # B would never declare R failed
            relay = views["R"].counters
            assert relay.frames_bad_kind == 5  # the forged beats stopped at the relay
            assert relay.frames_dropped_queue > 0  # the control queue is bounded ...
            link = nets["R"].peers["B"].link
            assert link is not None
            assert link.queued[1] <= (2 << 20) + BULK  # ... by bytes, per class
        finally:
            beating.cancel()
            for n in names:
                await nets[n].close()

    asyncio.run(run())


def test_frames_waiting_for_a_route_are_bounded_by_bytes() -> None:
    """1,000 frames of 16 MiB could once wait for a route at once (16 GB): bytes bound them."""
    wait: RouteWait[bytes] = RouteWait(size=len, limit_bytes=32 << 20)
    frame = b"x" * (16 << 20)
    held = [wait.hold("N9", frame, CONTROL, 0.0) for _ in range(5)]
    assert held == [True, True, False, False, False] and wait.dropped == 3
    assert wait.release(0.5, lambda dst, item, kind: True) == 2 and wait.bytes == 0
    assert wait.hold("N9", frame, CONTROL, 0.6)  # room again once they left


def test_a_marker_is_never_dropped_by_a_full_data_queue() -> None:
    """A data frame a full queue drops is sent again (go-back-N); a relocation's marker is
    not, so it goes past the bound (by a small slack) and the move still hands over."""
    import asyncio

    from mso.net.base import DATA, MARKER, LinkShape
    from mso.net.shaping import Link, QueueBounds

    class Stuck:
        paused = True  # the connection pushes back: nothing leaves the queues

        def write_frame(self, payload: bytes) -> None:
            raise AssertionError("nothing should be written")

    full: list[int] = []
    loop = asyncio.new_event_loop()
    try:
        bounds = QueueBounds(data=1000, marker_slack=200)
        link = Link(Stuck(), LinkShape(), 1, loop, bounds=bounds, on_full=lambda: full.append(1))
        for _ in range(10):
            link.send(b"d" * 100, DATA)
        assert link.queued[2] == 1000 and not full
        link.send(b"d" * 100, DATA)  # a data frame past the bound: dropped, counted
        assert full == [1]
        link.send(b"m" * 50, MARKER)  # a marker is not
        assert full == [1] and link.queued[2] == 1050
        for _ in range(4):
            link.send(b"m" * 50, MARKER)
        assert full == [1, 1] and link.queued[2] == 1200  # the slack is bounded too
    finally:
        loop.close()
