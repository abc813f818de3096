"""The handshake's key confirmation leaks nothing an offline guesser can use (issue 27, item 6).

A node used to answer a wrong key with its own key confirmation: an outsider who connected got a
tag under the overlay key and both nonces, and could test guesses of the key against it offline
(182,000 guesses a second; a passphrase key fell in 0.8 s). Now the side that accepted the
connection proves the key only after the connecting side has, a wrong key gets a plain close
(counted), and the direction keys depend on an ephemeral X25519 secret an eavesdropper lacks.
"""

from __future__ import annotations

import asyncio
import hashlib
import struct

import pytest

from mso.client import Client, overlay_key
from mso.errors import MsoError
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.framing import (
    HELLO_BYTES,
    TAG_BYTES,
    FrameCodec,
    WrongKey,
    derive_key,
    psk_from_text,
)

HOST = "127.0.0.1"
KEY, GUESS = psk_from_text("the overlay's passphrase"), psk_from_text("a guess")


def test_the_responder_says_nothing_keyed_before_the_initiator_proved_the_key() -> None:
    node, stranger = FrameCodec(KEY, responder=True), FrameCodec(GUESS)
    _, flush = node.feed(stranger.hello())
    assert flush == b""  # the node's hello (keyless) is all it has sent
    _, confirmation = stranger.feed(node.hello())
    assert len(confirmation) == 4 + TAG_BYTES
    with pytest.raises(WrongKey):
        node.feed(confirmation)
    assert not node.ready and node.seal(b"anything") == b""  # nothing sealed, nothing sent
    # with the key, the node answers with its own confirmation, and only then
    node, member = FrameCodec(KEY, responder=True), FrameCodec(KEY)
    assert node.feed(member.hello()) == ([], b"")
    _, confirmation = member.feed(node.hello())
    _, answer = node.feed(confirmation)
    assert len(answer) == 4 + TAG_BYTES and member.feed(answer) == ([], b"")
    assert node.confirmed and member.confirmed


def test_an_eavesdropper_with_the_right_key_cannot_check_it_against_a_confirmation() -> None:
    """Everything on the wire (both hellos, the confirmation) and even the right key do not
    reproduce the tag: the direction key needs the X25519 secret of the two ephemeral keys."""
    node, member = FrameCodec(KEY, responder=True), FrameCodec(KEY)
    node.feed(member.hello())
    _, confirmation = member.feed(node.hello())
    tag = confirmation[4:]
    for shared in (b"", b"\0" * 32):  # what a listener could put in place of the secret
        key = derive_key(KEY, member.hello(), node.hello(), shared)
        guess = hashlib.blake2b(struct.pack(">Q", 0), key=key, digest_size=TAG_BYTES).digest()
        assert guess != tag


def test_a_stranger_with_a_wrong_key_gets_a_plain_close_counted_over_tcp() -> None:
    async def run() -> None:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, KEY)
        await driver.start()
        port = driver.transport.port
        try:
            for attempt in range(3):  # as a guesser would: hello, a confirmation, read all
                guesser = FrameCodec(psk_from_text(f"guess {attempt}"))
                r, w = await asyncio.open_connection(HOST, port)
                w.write(guesser.hello())
                node_hello = await asyncio.wait_for(r.readexactly(HELLO_BYTES), 5.0)
                _, confirmation = guesser.feed(node_hello)
                w.write(confirmation)
                rest = await asyncio.wait_for(r.read(), 5.0)
                assert rest == b""  # closed: no confirmation of the node's to guess against
                w.close()
            with pytest.raises(MsoError, match="wrong overlay key"):
                await Client(HOST, port, GUESS).connect()
            counters = driver.transport.connection_counters
            assert counters.wrong_key == 4
            client = await Client(HOST, port, KEY).connect()  # the key still works
            assert isinstance(await client.call(m.StatusRequest()), m.StatusReply)
            await client.close()
        finally:
            await driver.stop()

    asyncio.run(run())


def test_text_keys_are_stretched_so_each_guess_costs_scrypt() -> None:
    assert psk_from_text("k") == hashlib.scrypt(
        b"k", salt=b"mso-overlay-key", n=1 << 14, r=8, p=1, maxmem=64 << 20, dklen=32
    )
    assert overlay_key("k") == psk_from_text("k") != psk_from_text("k ")
