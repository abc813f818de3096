"""Operator authority: a member holding only the overlay key changes nothing; commands signed
with an operator key (or by the node's own emulator, for its LinkStates) are carried out."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.client import Client, Refused, overlay_key
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer, strip_grant
from mso.protocol.framing import HELLO_BYTES, FrameCodec

HOST = "127.0.0.1"
KEY = overlay_key("members")
APP = (
    "name: one\n"
    "vertices:\n"
    "  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 20, "
    "output: runtime_vertices:Num}\n"
    "  sink: {code: runtime_vertices:Recorder, pinned: N1}\n"
    "edges:\n"
    "  - [src, sink]\n"
)
OPERATOR = Signer()
EMULATOR = Signer()
ROGUE = Signer()


def test_commands_signed_for_this_connection_only() -> None:
    auth = Authority.configure([OPERATOR.public_text()])
    nonce, other = b"n" * 16, b"o" * 16
    stop = m.StopApp("one")
    assert auth.command(nonce, OPERATOR.command(nonce, stop)) == stop
    assert auth.command(nonce, m.StatusRequest()) == m.StatusRequest()  # reading needs nothing
    for bad, why in [
        (stop, "needs an operator's signature"),
        (OPERATOR.command(other, stop), "bad signature"),  # replayed from another connection
        (ROGUE.command(nonce, stop), "has no authority"),
        (m.Authorized(body=b"\xc1", key=OPERATOR.id, sig=b""), "does not decode"),
    ]:
        verdict = auth.command(nonce, bad)
        assert isinstance(verdict, str) and why in verdict
    assert auth.refused == 4
    # a node that needs no signature takes a signed command as it is (an operator signing
    # everything can still talk to an open node)
    open_node = Authority()
    assert open_node.command(nonce, ROGUE.command(other, stop)) == stop


def test_documents_carry_a_grant_that_survives_relay_but_not_edits() -> None:
    auth = Authority.configure([OPERATOR.public_text()])
    granted = OPERATOR.grant(APP, 1)
    assert auth.document(granted) == "" and strip_grant(granted) == APP
    assert "no operator grant" in auth.document(APP)
    assert "not an operator's" in auth.document(ROGUE.grant(APP, 1))
    tampered = granted.replace("rate: 20", "rate: 99")
    assert "does not match" in auth.document(tampered)
    # the grant is a comment after the document: line numbers of errors do not move
    assert granted.startswith(APP)


async def start(auth: Authority) -> tuple[NodeDriver, int]:
    driver = NodeDriver(NodeCore("N1"), HOST, 0, KEY, authority=auth)
    await driver.start()
    return driver, driver.transport.port


async def as_neighbour(port: int) -> tuple[asyncio.StreamWriter, FrameCodec]:
    """A connection to the node at ``port`` past the key confirmation (a neighbour's, before
    its hello): the writer and the codec that seals its frames."""
    reader, writer = await asyncio.open_connection(HOST, port)
    codec = FrameCodec(KEY)
    writer.write(codec.hello())
    _, confirm = codec.feed(await reader.readexactly(HELLO_BYTES))
    writer.write(confirm)
    return writer, codec


async def status(port: int) -> dict[str, Any]:
    client = await Client(HOST, port, KEY).connect()
    try:
        reply = await client.call(m.StatusRequest())
        assert isinstance(reply, m.StatusReply)
        return reply.nodes["N1"]
    finally:
        await client.close()


async def refused(port: int, msg: m.Message, signer: Signer | None = None) -> str:
    client = await Client(HOST, port, KEY, signer=signer).connect()
    try:
        with pytest.raises(Refused) as info:
            await client.call(msg, timeout=5)
        return str(info.value)
    finally:
        await client.close()


def test_a_member_without_operator_authority_changes_nothing() -> None:
    auth = Authority.configure([OPERATOR.public_text()], EMULATOR.public_text())

    async def run() -> None:
        driver, port = await start(auth)
        try:
            link = m.LinkState(version=5, neighbours={}, routes={"N9": ["N9", 1]})
            for msg in [
                m.DeployRequest(APP, "one.yaml"),
                m.StopApp("one"),
                m.RelocateRequest("one", "sink", target="N2"),
                m.RemapRequest("one", [], everything=True),
                m.Shutdown(),
                link,
            ]:
                assert "needs an operator's signature" in await refused(port, msg)
                assert "has no authority" in await refused(port, msg, ROGUE)
            # a deploy signed by the operator, but its document altered on the way: refused
            forged = m.DeployRequest(OPERATOR.grant(APP, 1).replace("rate: 20", "rate: 1"))
            client = await Client(HOST, port, KEY).connect()
            nonce = client._codec.peer_nonce
            assert nonce is not None
            with pytest.raises(Refused, match="does not match"):
                await client.call(OPERATOR.command(nonce, forged))
            await client.close()
            st = await status(port)
            assert st["apps"] == {} and not driver.stopped.is_set()
            assert driver.view.routes() == {}  # the LinkState was not taken
            assert st["authority"]["refused"] == 13

            # the operator deploys; a member still cannot undeploy; the operator can
            client = await Client(HOST, port, KEY, signer=OPERATOR).connect()
            reply = await client.call(m.DeployRequest(APP, "one.yaml"))
            assert isinstance(reply, m.DeployReply) and reply.ok, reply
            await refused(port, m.StopApp("one"))
            assert "one" in (await status(port))["apps"]
            await client.call(m.StopApp("one"))
            await client.close()
            assert (await status(port))["apps"] == {}

            # only the emulator that started the node sets its links
            client = await Client(HOST, port, KEY, signer=EMULATOR).connect()
            await client.send(link)
            await client.send(m.Shutdown())
            await asyncio.wait_for(driver.stopped.wait(), 5)
            assert set(driver.view.routes()) == {"N9"}
        finally:
            if not driver.stopped.is_set():
                await driver.stop()

    asyncio.run(run())


def test_an_announced_app_without_a_grant_is_never_loaded() -> None:
    """A captured robot (a member) announces an app of its own to a neighbour: dropped."""
    auth = Authority.configure([OPERATOR.public_text()])

    async def run() -> dict[str, Any]:
        driver, port = await start(auth)
        try:
            writer, codec = await as_neighbour(port)
            for msg in [
                m.PeerHello("N2"),
                m.AppAnnounce(app="one", origin="N2", document=APP),
                m.AppAnnounce(app="two", origin="N2", document=ROGUE.grant(APP, 1)),
            ]:
                writer.write(codec.seal(m.wrap("N2", "N1", msg)))
            await writer.drain()
            for _ in range(100):  # until both were looked at
                if driver.authority.refused >= 2:
                    break
                await asyncio.sleep(0.02)
            writer.close()
            return await status(port)
        finally:
            await driver.stop()

    st = asyncio.run(run())
    assert st["apps"] == {} and st["authority"]["refused"] == 2


def test_an_app_without_a_grant_in_a_control_streams_frame_is_refused_and_the_stream_goes_on() -> (
    None
):
    """The same two announcements, each in a frame of N2's control stream, then a third frame:
    the transport judges a frame by what it carries (both refused, nothing loaded), and passes
    each refusal on as a ``Refused`` body, so N2's stream is not stuck behind them."""
    auth = Authority.configure([OPERATOR.public_text()])

    async def run() -> tuple[dict[str, Any], int]:
        driver, port = await start(auth)
        try:
            writer, codec = await as_neighbour(port)
            writer.write(codec.seal(m.wrap("N2", "N1", m.PeerHello("N2"))))
            said: list[m.Message] = [
                m.AppAnnounce(app="one", origin="N2", document=APP),
                m.AppAnnounce(app="two", origin="N2", document=ROGUE.grant(APP, 1)),
                m.Moved("one", "v", "N2", -1, 1),
            ]
            for seq, msg in enumerate(said):
                frame = m.Sequenced(inc=1, seq=seq, low=0, body=msg)
                writer.write(codec.seal(m.wrap("N2", "N1", frame)))
            await writer.drain()
            streams = driver.core.streams
            for _ in range(100):  # until all three were taken
                got = streams._in.get("N2")
                if got is not None and got.next_seq == 3:
                    break
                await asyncio.sleep(0.02)
            writer.close()
            got = streams._in.get("N2")
            return await status(port), (got.next_seq if got is not None else -1)
        finally:
            await driver.stop()

    st, taken = asyncio.run(run())
    assert st["apps"] == {} and st["authority"]["refused"] == 2
    assert taken == 3  # the refused two did not stall the third


def test_keygen_and_signed_cli(tmp_path: Path) -> None:
    out = tmp_path / "op.key"
    result = CliRunner().invoke(main, ["keygen", str(out)])
    assert result.exit_code == 0, result.output
    assert out.stat().st_mode & 0o777 == 0o600
    signer = Signer.load(str(out))
    auth = Authority.configure([str(out.with_name("op.key.pub"))])
    assert signer.id in auth.operators
    again = CliRunner().invoke(main, ["keygen", str(out)])  # never overwrites a key
    assert again.exit_code == 2 and "File exists" in again.stderr


def test_python_api_signs_with_an_operator_key_file(tmp_path: Path) -> None:
    from mso.api import AsyncOverlay
    from mso.errors import MsoError

    key_file = tmp_path / "op.key"
    key_file.write_text(OPERATOR.private_text() + "\n")
    app = tmp_path / "one.yaml"
    app.write_text(APP)

    async def run() -> None:
        driver, port = await start(Authority.configure([OPERATOR.public_text()]))
        try:
            addr = f"{HOST}:{port}"
            with pytest.raises(MsoError, match="needs an operator's signature"):
                await AsyncOverlay(addr, key="members").deploy(app)
            reply = await AsyncOverlay(addr, key="members", sign=str(key_file)).deploy(app)
            assert reply.ok and "one" in (await status(port))["apps"]
        finally:
            await driver.stop()

    asyncio.run(run())
