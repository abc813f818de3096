"""Authenticated frames: only holders of the overlay key are heard; replays and forgeries fail."""

from __future__ import annotations

import pytest

from mso.protocol import messages as m
from mso.protocol.framing import (
    MAX_REJECTED_IN_A_ROW,
    FrameCodec,
    FramingError,
    WrongKey,
    psk_from_text,
)

KEY = psk_from_text("test-key")


def pair(key_a: bytes = KEY, key_b: bytes = KEY) -> tuple[FrameCodec, FrameCodec]:
    a, b = FrameCodec(key_a), FrameCodec(key_b)
    _, flush_b = b.feed(a.hello())
    _, flush_a = a.feed(b.hello())
    assert len(flush_a) == len(flush_b) == 4 + 16  # the empty key confirmation frames
    assert a.feed(flush_b)[0] == [] and b.feed(flush_a)[0] == []
    assert a.confirmed and b.confirmed
    return a, b


def test_round_trip_and_early_frames_are_queued_until_hello() -> None:
    a, b = FrameCodec(KEY), FrameCodec(KEY)
    assert a.seal(b"early") == b""  # not sent before the peer's nonce is known
    b.feed(a.hello())
    payloads, flush = a.feed(b.hello())
    assert payloads == []
    got, _ = b.feed(flush)
    assert got == [b"early"]
    assert b.feed(a.seal(b"x" * 5000))[0] == [b"x" * 5000]


def test_frames_split_across_reads() -> None:
    a, b = pair()
    frame = a.seal(b"hello world")
    out = []
    for i in range(len(frame)):
        out += b.feed(frame[i : i + 1])[0]
    assert out == [b"hello world"]


def test_replayed_frame_is_rejected_and_stream_goes_on() -> None:
    a, b = pair()
    frame = a.seal(b"one")
    assert b.feed(frame)[0] == [b"one"]
    assert b.feed(frame)[0] == []  # same bytes again: counter mismatch
    assert b.rejected == 1
    assert b.feed(a.seal(b"two"))[0] == [b"two"]


def test_frame_from_another_connection_is_rejected() -> None:
    a1, b1 = pair()
    _a2, b2 = pair()
    assert b2.feed(a1.seal(b"not for you"))[0] == []
    assert b2.rejected == 1
    assert b1.accepted == 0


def test_wrong_key_fails_the_key_confirmation() -> None:
    a, b = FrameCodec(psk_from_text("intruder")), FrameCodec(KEY)
    _, flush_b = b.feed(a.hello())
    _, flush_a = a.feed(b.hello() + a.seal(b"let me in"))
    with pytest.raises(WrongKey):
        b.feed(flush_a)
    with pytest.raises(WrongKey):
        a.feed(flush_b)
    assert not b.confirmed and b.accepted == 0


def test_nothing_but_a_key_confirmation_before_it() -> None:
    a, b = FrameCodec(KEY), FrameCodec(KEY)
    b.feed(a.hello())
    a.feed(b.hello())
    # a stranger announcing a big frame before confirming is cut off at its 4-byte length
    with pytest.raises(FramingError, match="key confirmation"):
        b.feed(b"\x00\xff\xff\xff")


def test_tampered_payload_is_rejected() -> None:
    a, b = pair()
    frame = bytearray(a.seal(b"pay 10"))
    frame[-1] ^= 1
    assert b.feed(bytes(frame))[0] == []
    assert b.rejected == 1


def test_garbage_stream_is_a_framing_error() -> None:
    b = FrameCodec(KEY)
    with pytest.raises(FramingError):
        b.feed(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")


def test_oversized_frame_is_a_framing_error() -> None:
    a, b = FrameCodec(KEY, max_frame=100), FrameCodec(KEY, max_frame=100)
    b.feed(a.hello())
    b.feed(a.feed(b.hello())[1])
    with pytest.raises(FramingError):
        b.feed(a.seal(b"x" * 1000))


def test_messages_are_validated_on_decode() -> None:
    ok = m.wrap("N1", "N2", m.Ack("app", 1, 0, 5))
    env = m.unwrap(ok)
    assert env.kind == m.DATA and m.decode(env.body) == m.Ack("app", 1, 0, 5)
    bad = m.wrap("N1", "N2", m.ClientHello("x")).replace(b"client", b"unknwn")
    with pytest.raises(Exception, match="Invalid value"):
        m.decode(m.unwrap(bad).body)


def test_a_stream_whose_frames_keep_failing_is_given_up() -> None:
    """One frame altered on the way leaves the counters apart: every later frame fails. After
    MAX_REJECTED_IN_A_ROW of them the stream is closed instead of dropping frames for ever."""
    a, b = pair()
    bad = bytearray(a.seal(b"altered"))
    bad[-1] ^= 1
    b.feed(bytes(bad))
    with pytest.raises(FramingError, match="in a row"):
        for _ in range(MAX_REJECTED_IN_A_ROW):
            b.feed(a.seal(b"later"))
    assert b.rejected == MAX_REJECTED_IN_A_ROW and b.accepted == 0
