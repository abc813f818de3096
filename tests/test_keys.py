"""Key rotation without stopping anything, and optional ChaCha20-Poly1305 encryption of frames."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mso.client import Client, overlay_key
from mso.errors import MsoError
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.framing import FrameCodec, FramingError, WrongKey, psk_from_text
from waits import answered, listening, until

OLD, NEW, OTHER = psk_from_text("old"), psk_from_text("new"), psk_from_text("other")


def handshake(a: FrameCodec, b: FrameCodec) -> None:
    _, fb = b.feed(a.hello())
    _, fa = a.feed(b.hello())
    a.feed(fb)
    b.feed(fa)


@pytest.mark.parametrize("encrypt", [False, True])
def test_each_side_seals_with_its_first_key_and_accepts_all(encrypt: bool) -> None:
    moved, behind = FrameCodec([NEW, OLD], encrypt=encrypt), FrameCodec([OLD, NEW], encrypt=encrypt)
    handshake(moved, behind)
    assert moved.peer_key_index == 1 and behind.peer_key_index == 1  # each hears the other's
    assert behind.feed(moved.seal(b"hi"))[0] == [b"hi"]
    assert moved.feed(behind.seal(b"ho"))[0] == [b"ho"]
    a, b = FrameCodec([NEW], encrypt=encrypt), FrameCodec([OLD], encrypt=encrypt)
    with pytest.raises(WrongKey):
        handshake(a, b)


def test_encrypted_frames_hide_the_payload_and_refuse_tampering() -> None:
    a, b = FrameCodec(NEW, encrypt=True), FrameCodec(NEW, encrypt=True)
    handshake(a, b)
    secret = b"target at 52.1N 4.3E" * 3
    frame = a.seal(secret)
    assert secret not in frame and secret[:8] not in frame
    assert b.feed(frame)[0] == [secret]
    bad = bytearray(a.seal(secret))
    bad[10] ^= 1
    assert b.feed(bytes(bad))[0] == [] and b.rejected == 1
    plain = FrameCodec(NEW)  # a member that does not encrypt is told at the hello
    with pytest.raises(FramingError, match="encrypts"):
        plain.feed(a.hello())


def test_rotating_a_nodes_keys_leaves_open_connections_alone() -> None:
    async def run() -> None:
        driver = NodeDriver(NodeCore("N1"), "127.0.0.1", 0, OLD, encrypt=True)
        await driver.start()
        port = driver.transport.port
        try:
            before = await Client("127.0.0.1", port, OLD, encrypt=True).connect()
            driver.transport.set_keys([NEW, OLD])  # step 2: seal with the new, accept both
            for key in (OLD, NEW):
                c = await Client("127.0.0.1", port, key, encrypt=True).connect()
                assert isinstance(await c.call(m.StatusRequest()), m.StatusReply)
                await c.close()
            driver.transport.set_keys([NEW])  # step 3: the old key is gone
            with pytest.raises(MsoError, match="wrong overlay key"):
                await Client("127.0.0.1", port, OLD, encrypt=True).connect()
            assert isinstance(await before.call(m.StatusRequest()), m.StatusReply)
            await before.close()
        finally:
            await driver.stop()

    asyncio.run(run())


@pytest.mark.slow
def test_mso_node_rereads_its_key_file_on_sighup(tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    keys.write_text("# current first\nold\n")
    env = {k: v for k, v in os.environ.items() if k not in ("MSO_KEY", "MSO_ENCRYPT")}
    log = tmp_path / "node.log"
    with log.open("wb") as err:
        node = subprocess.Popen(
            [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", "127.0.0.1:0",
             "--key-file", str(keys), "--encrypt"],
            env=env, stdout=subprocess.DEVNULL, stderr=err,
        )  # fmt: skip

    async def status(key: bytes) -> m.Message:
        c = await Client("127.0.0.1", port, key, encrypt=True).connect(2.0)
        try:
            return await c.call(m.StatusRequest())
        finally:
            await c.close()

    async def run() -> None:
        await answered(lambda: status(overlay_key("old")), 10, "the node answering")
        keys.write_text("new\nold\n")
        node.send_signal(signal.SIGHUP)
        await answered(lambda: status(overlay_key("new")), 10, "the node taking the new file")
        assert isinstance(await status(overlay_key("new")), m.StatusReply)
        assert isinstance(await status(overlay_key("old")), m.StatusReply)  # still accepted

    try:
        port = listening(node, log)
        asyncio.run(run())
    finally:
        node.terminate()
        node.wait(10)


@pytest.mark.slow
def test_an_encrypted_overlay_with_an_operator_runs_an_app_end_to_end(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Four node processes with --encrypt and --operator-key: the emulator's own signed
    LinkStates set their links, an operator-signed deploy runs across them and relays every event
    encrypted; an unsigned relocation is refused."""
    from mso.emu.controller import Emulator
    from mso.protocol.authority import Signer
    from mso.scenario import loads_scenario
    from runtime_vertices import pipe_app

    tests = Path(__file__).resolve().parent
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(tests), path) if p))
    operator = Signer()
    line = (
        "name: l\nnodes: {N1: {}, N2: {}, N3: {}, N4: {}}\nlinks: [[N1, N2], [N2, N3], [N3, N4]]\n"
    )

    async def run() -> dict[str, object]:
        emu = Emulator(loads_scenario(line), encrypt=True, operator_keys=(operator.public_text(),))
        await emu.start()
        try:
            addr = emu.address("N2")
            host, port = addr.rsplit(":", 1)
            client = await Client(host, int(port), overlay_key(emu.key), signer=operator).connect()
            reply = await client.call(m.DeployRequest(pipe_app(100), "pipe.yaml"), timeout=30)
            await client.close()
            assert isinstance(reply, m.DeployReply) and reply.ok, reply
            unsigned = await Client(host, int(port), overlay_key(emu.key), encrypt=True).connect()
            with pytest.raises(MsoError, match="needs an operator's signature"):
                await unsigned.call(m.RelocateRequest("pipe", "mid", "upstream"))
            await unsigned.close()
            sink = lambda st: st["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]  # noqa: E731
            return await until(emu.status, lambda st: sink(st)["count"] >= 50, 10, "50 events")
        finally:
            await emu.stop()

    monkeypatch.setenv("MSO_ENCRYPT", "1")  # this test's clients encrypt too
    status = asyncio.run(run())
    got = status["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]  # type: ignore[index]
    assert got["count"] >= 50 and got["repeats"] == 0
    assert status["N2"]["traffic"]["bytes_forwarded"] > 0  # type: ignore[index]
