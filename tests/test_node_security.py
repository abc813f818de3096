"""A running node drops and counts unauthenticated, replayed and malformed frames, and lives on."""

from __future__ import annotations

import asyncio
from typing import Any

from mso.client import Client, NodeUnreachable, overlay_key
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.framing import HELLO_BYTES, FrameCodec, psk_from_text

HOST, PORT = "127.0.0.1", 0


async def start_node() -> tuple[NodeDriver, int]:
    driver = NodeDriver(NodeCore("N1"), HOST, 0, overlay_key("secret"))
    await driver.start()
    assert driver._server is not None
    port = driver._server.sockets[0].getsockname()[1]
    return driver, port


async def status(port: int) -> dict[str, Any]:
    client = await Client(HOST, port, overlay_key("secret")).connect()
    try:
        reply = await client.call(m.StatusRequest())
        assert isinstance(reply, m.StatusReply)
        return reply.nodes["N1"]
    finally:
        await client.close()


async def raw_session(port: int, key: bytes, payloads: list[bytes]) -> bytes:
    """Handshake with ``key`` and send ``payloads`` as frames; return every byte written."""
    reader, writer = await asyncio.open_connection(HOST, port)
    codec = FrameCodec(key)
    sent = codec.hello()
    writer.write(sent)
    _, confirm = codec.feed(await reader.readexactly(HELLO_BYTES))
    sent += confirm
    writer.write(confirm)
    for p in payloads:
        frame = codec.seal(p)
        sent += frame
        writer.write(frame)
    await writer.drain()
    await asyncio.sleep(0.1)
    writer.close()
    return sent


def test_bad_frames_are_dropped_counted_and_the_node_lives_on() -> None:
    async def run() -> dict[str, Any]:
        driver, port = await start_node()
        try:
            hello = m.wrap("client", "N1", m.ClientHello("x"))
            request = m.wrap("client", "N1", m.DeployRequest("name: evil\nvertices: {A: {}}\n"))
            # 1. not mso at all: the connection is closed
            r, w = await asyncio.open_connection(HOST, port)
            w.write(b"GET / HTTP/1.1\r\n\r\n" + b"\x00" * 64)
            await w.drain()
            rest = await asyncio.wait_for(r.read(), 2.0)  # the node's hello, then EOF
            assert len(rest) == HELLO_BYTES
            w.close()
            # 2. the wrong overlay key: every frame rejected, nothing deployed
            await raw_session(port, psk_from_text("wrong"), [hello, request])
            # 3. a replay of an authentic session on a new connection
            first = await raw_session(port, overlay_key("secret"), [hello])
            r, w = await asyncio.open_connection(HOST, port)
            await r.readexactly(HELLO_BYTES)
            w.write(first + first[HELLO_BYTES:])
            await w.drain()
            await asyncio.sleep(0.1)
            w.close()
            # 4. authentic but malformed bodies
            await raw_session(
                port,
                overlay_key("secret"),
                [hello, b"\xc1garbage", m.wrap("c", "N1", m.ClientHello("x"))[:-3]],
            )
            await asyncio.sleep(0.1)
            return await status(port)
        finally:
            await driver.stop()

    st = asyncio.run(run())
    traffic = st["traffic"]
    assert traffic["frames_rejected"] >= 3  # wrong key (2) + replay (>= 1) + the garbage stream
    assert traffic["frames_malformed"] >= 2
    assert st["apps"] == {}  # nothing from an unauthenticated peer was acted on
    assert st["node"] == "N1"  # and the node still answers


def test_a_late_reply_is_never_read_as_the_next_calls_answer() -> None:
    """A call that times out leaves its reply on the way; on a kept connection the next call
    would read it as its own answer. The client opens the connection anew instead."""

    async def main() -> None:
        driver, port = await start_node()
        try:
            loop = asyncio.get_running_loop()
            # a peer the node routes to but that never answers: a status fan-out waits for it
            # until its deadline (1 s) and then answers late
            driver._apply(driver.core.set_routes({"N2": ("N2", 1)}, loop.time()))
            client = await Client(HOST, port, overlay_key("secret")).connect()
            try:
                late = m.StatusRequest(req=0, everywhere=True)
                try:
                    await client.call(late, timeout=0.2)
                    raise AssertionError("the fan-out should outlast the call's timeout")
                except NodeUnreachable:
                    pass
                while driver.core.procedures:  # the fan-out's late answer has gone out
                    await asyncio.sleep(0.01)
                reply = await client.call(m.RelocateRequest("none", "v"), timeout=5.0)
                assert isinstance(reply, m.RelocateReply), reply  # its own answer
                assert not reply.ok and "no running app" in reply.error
            finally:
                await client.close()
        finally:
            await driver.stop()

    asyncio.run(main())


def test_a_body_nested_100000_deep_is_refused_and_counted() -> None:
    """msgspec gives up on deep nesting with RecursionError, which used to escape the
    connection and drop it uncounted: now such a frame is dropped as malformed, counted, and
    the same connection is still served."""
    import msgspec

    deep = b"\x91" * 100_000 + b"\xc0"
    enc = msgspec.msgpack.Encoder()

    def envelope(body: bytes) -> bytes:  # an envelope whose raw body is ``body``
        head = enc.encode(["client", "N1", 32, 0, msgspec.Raw(b"\xc0")])  # a bare envelope
        return head[:-1] + body

    in_envelope = envelope(deep)  # skipped as the envelope's raw body
    in_message = envelope(enc.encode(m.StatusReply(1, nodes={"x": 0}))[:-1] + deep)

    async def run() -> tuple[dict[str, Any], dict[str, Any]]:
        driver, port = await start_node()
        try:
            before = (await status(port))["traffic"]
            reader, writer = await asyncio.open_connection(HOST, port)
            codec = FrameCodec(overlay_key("secret"))
            writer.write(codec.hello())
            _, confirm = codec.feed(await reader.readexactly(HELLO_BYTES))
            writer.write(confirm)
            frames = [m.wrap("client", "N1", m.ClientHello("x")), in_envelope, in_message]
            for p in [*frames, m.wrap("client", "N1", m.StatusRequest(req=7))]:
                writer.write(codec.seal(p))
            await writer.drain()
            while True:  # the same connection answers after the deep frames
                payloads, _ = codec.feed(await asyncio.wait_for(reader.read(65536), 5.0))
                replies = [m.decode(m.unwrap(p).body) for p in payloads]
                got = [r for r in replies if isinstance(r, m.StatusReply) and r.req == 7]
                if got:
                    writer.close()
                    return before, got[0].nodes["N1"]["traffic"]
        finally:
            await driver.stop()

    before, after = asyncio.run(asyncio.wait_for(run(), 30))
    assert after["frames_malformed"] - before["frames_malformed"] == 2
    assert after["frames_failed"] == before["frames_failed"]
