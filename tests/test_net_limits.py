"""Bounded resources: strangers cannot hold a node's connections or memory, and a LinkState
cannot push its version to the end of the range."""

from __future__ import annotations

import asyncio
import struct
from typing import Any

from mso.client import Client, overlay_key
from mso.net.limits import Limits
from mso.net.routes_emulator import MAX_VERSION_STEP, EmulatorRoutes
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.framing import HELLO_BYTES, MAGIC, FrameCodec
from waits import holds, patience

HOST = "127.0.0.1"
LIMITS = Limits(
    handshake_s=0.3,
    sweep_s=0.05,
    max_connections=8,
    max_per_address=4,
    max_pending_per_address=4,
)


async def read_all(reader: asyncio.StreamReader) -> bytes:
    """Everything until the node closes the connection (a reset: nothing)."""
    try:
        return await asyncio.wait_for(reader.read(), patience(5.0))
    except ConnectionError:
        return b""


def test_connections_are_limited_timed_out_and_cut_off_before_authentication() -> None:
    async def run() -> dict[str, Any]:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, overlay_key("k"), limits=LIMITS)
        await driver.start()
        port = driver.transport.port
        try:
            # 1. a hello, then a frame announcing 16 MiB: cut off at its length, nothing buffered
            r, w = await asyncio.open_connection(HOST, port)
            hello = FrameCodec(overlay_key("k")).hello()
            w.write(hello + struct.pack(">I", 16 << 20) + b"x" * 1000)
            assert len(await read_all(r)) == HELLO_BYTES  # the node's hello, then it closed
            w.close()
            # 2. four silent connections from one address fill its share; each more closes
            # the oldest of them (the pending pool, mso.net.admission)
            idle = [await asyncio.open_connection(HOST, port) for _ in range(6)]
            ends = await asyncio.gather(*(read_all(r) for r, _ in idle))
            assert [len(e) for e in ends] == [HELLO_BYTES] * 6
            for _, w in idle:
                w.close()
            # 3. a slow-loris sender trickling its hello is closed by the handshake timeout
            r, w = await asyncio.open_connection(HOST, port)
            w.write(MAGIC[:2])
            assert len(await read_all(r)) == HELLO_BYTES
            w.close()
            # the node still serves a client with the key
            client = await Client(HOST, port, overlay_key("k")).connect()
            reply = await client.call(m.StatusRequest())
            await client.close()
            assert isinstance(reply, m.StatusReply)
            return reply.nodes["N1"]
        finally:
            await driver.stop()

    st = asyncio.run(run())
    assert st["connections"]["evicted"] == 2 and st["connections"]["connections_refused"] == 0
    assert st["connections"]["handshake_timeouts"] >= 5
    assert st["traffic"]["frames_rejected"] >= 1  # the 16 MiB announcement


def test_linkstate_version_cannot_jump_to_the_end_of_its_range() -> None:
    view = EmulatorRoutes("N1")
    assert view.apply(m.LinkState(version=1, neighbours={}, routes={"N2": ["N2", 1]}))
    assert not view.apply(m.LinkState(version=2**62, neighbours={}, routes={}))
    assert view.versions_refused == 1 and view.version == 1
    assert view.apply(m.LinkState(version=2, neighbours={}, routes={}))  # genuine ones go on
    assert view.apply(m.LinkState(version=2 + MAX_VERSION_STEP, neighbours={}, routes={}))


async def member(port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, FrameCodec]:
    """An authenticated client connection (a member: it holds the overlay key)."""
    reader, writer = await asyncio.open_connection(HOST, port)
    codec = FrameCodec(overlay_key("k"))
    writer.write(codec.hello())
    while not codec.confirmed:
        writer.write(codec.feed(await reader.read(1 << 16))[1])
    writer.write(codec.seal(m.wrap("c", "N1", m.ClientHello("c"))))
    return reader, writer, codec


def test_members_cannot_fill_a_nodes_memory_with_partial_frames_or_unread_replies() -> None:
    limits = Limits(max_buffered=4 << 20, max_partial_share=1 << 20, max_client_backlog=256 << 10)

    async def run() -> dict[str, Any]:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, overlay_key("k"), limits=limits)
        await driver.start()
        port = driver.transport.port
        try:
            # four members each announce an 8 MiB frame and send 2 MiB of it
            conns = [await member(port) for _ in range(4)]
            for _, w, _ in conns:
                w.write(struct.pack(">I", 8 << 20) + b"\0" * (2 << 20))
            counters = driver.transport.connection_counters
            await holds(lambda: counters.over_buffer >= 3, 5.0, "the node reading what they sent")
            assert counters.over_buffer == 3  # the fourth fits in what is left
            assert driver.transport._held_total <= 4 << 20
            for _, w, _ in conns:
                w.close()
            # a member asking for status 20,000 times and never reading the replies
            r, w, codec = await member(port)
            w.write(
                b"".join(codec.seal(m.wrap("c", "N1", m.StatusRequest())) for _ in range(20000))
            )
            await read_all(r)  # until the node gives up on it (reset: it aborts)
            client = await Client(HOST, port, overlay_key("k")).connect()
            reply = await client.call(m.StatusRequest())
            await client.close()
            assert isinstance(reply, m.StatusReply)
            return reply.nodes["N1"]
        finally:
            await driver.stop()

    st = asyncio.run(run())
    assert st["connections"]["over_buffer"] == 4  # three of the four, and the one not reading


def test_an_incarnation_at_the_end_of_its_range_is_not_believed() -> None:
    """A member declaring N3 failed at incarnation 2^62 would keep N3 out for good: dropped and
    counted; a plausible one is taken."""

    async def run() -> dict[str, Any]:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, overlay_key("k"))
        await driver.start()
        port = driver.transport.port
        try:
            reader, writer = await asyncio.open_connection(HOST, port)
            codec = FrameCodec(overlay_key("k"))
            writer.write(codec.hello())
            while not codec.confirmed:
                writer.write(codec.feed(await reader.read(1 << 16))[1])
            for msg in [
                m.PeerHello("N2"),
                m.NodeDown("N3", "N2", 2**62),
                m.NodeUp("N4", 2**62),
                m.NodeUp("N5", 7),  # (a NodeDown about a node never heard of is refused)
                m.NodeDown("N5", "N2", 7),
            ]:
                writer.write(codec.seal(m.wrap("N2", "N1", msg)))
            await writer.drain()
            await holds(lambda: "N5" in driver.core.failed, 2.0, "the plausible claim taken")
            writer.close()
            client = await Client(HOST, port, overlay_key("k")).connect()
            reply = await client.call(m.StatusRequest())
            await client.close()
            assert isinstance(reply, m.StatusReply)
            return reply.nodes["N1"]
        finally:
            await driver.stop()

    st = asyncio.run(run())
    assert st["failed_nodes"] == ["N5"]
    assert st["traffic"]["frames_implausible"] == 2


def test_twenty_clients_that_never_read_are_closed_by_their_backlog_together() -> None:
    """Each stays under its own bound, but together they are past the node's: each holding
    a large share is closed, counted, and the node answers a reading client; what the
    clients left unread stays under the node's bound."""
    limits = Limits(max_partial_share=64 << 10, max_clients_backlog=1 << 20)

    async def run() -> dict[str, Any]:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, overlay_key("k"), limits=limits)
        await driver.start()
        port = driver.transport.port
        counters = driver.transport.connection_counters
        try:
            conns = [await member(port) for _ in range(20)]
            ask = m.wrap("c", "N1", m.StatusRequest())
            for _, w, codec in conns:  # 3,000 replies each: about 9 MiB, under 16 MiB
                w.write(b"".join(codec.seal(ask) for _ in range(3000)))
            # until the node has answered (it closes them as it does)
            await holds(lambda: counters.over_buffer >= 19, 10.0, "19 clients closed")
            backlog = sum(
                c.transport.get_write_buffer_size()
                for c in driver.transport.clients.values()
                if c.transport is not None
            )
            assert backlog <= limits.max_clients_backlog
            client = await Client(HOST, port, overlay_key("k")).connect()
            reply = await client.call(m.StatusRequest())
            await client.close()
            assert isinstance(reply, m.StatusReply)
            for _, w, _ in conns:
                w.close()
            return reply.nodes["N1"]
        finally:
            await driver.stop()

    st = asyncio.run(run())
    assert st["connections"]["over_buffer"] >= 19
