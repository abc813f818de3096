"""Per-edge channels on their own: acks, retention, and what a producer keeps."""

from __future__ import annotations

import pytest

from mso.protocol.channel import OutChannel


def ev(i: int) -> bytes:
    return i.to_bytes(4, "big")


def test_acked_events_are_forgotten_unless_retained() -> None:
    out = OutChannel(window=100)
    out.push_many([ev(i) for i in range(10)])
    out.on_ack(4)
    assert out.base == 4 and out.kept == 6
    assert out.unacked() == (4, [ev(i) for i in range(4, 10)])
    with pytest.raises(ValueError, match="cannot retain from 2"):
        out.retain("replica", 2)  # already forgotten: refused, never a silent gap


def test_a_retention_keeps_events_past_their_ack_until_released() -> None:
    out = OutChannel(window=100)
    out.push_many([ev(i) for i in range(10)])
    out.retain("snap", 3)  # the snapshot was taken after event 2
    out.on_ack(8)
    assert out.in_flight == 2 and out.room == 98  # retained events are not in the window
    assert out.retained("snap") == (3, [ev(i) for i in range(3, 10)])
    assert out.unacked() == (8, [ev(8), ev(9)])
    out.release("snap", upto=6)  # the replica has what came before 6
    assert out.retained("snap") == (6, [ev(i) for i in range(6, 10)])
    assert out.base == 6
    out.release("snap")
    assert out.retained("snap") is None and out.base == 8 and out.kept == 2


def test_the_oldest_retention_holds_and_an_unknown_owner_is_ignored() -> None:
    out = OutChannel(window=100)
    out.push_many([ev(i) for i in range(6)])
    out.retain("a", 1)
    out.retain("b", 4)
    out.on_ack(6)
    assert out.base == 1
    out.release("a")
    assert out.base == 4 and out.retained("b") == (4, [ev(4), ev(5)])
    out.release("nobody")
    out.push(ev(6))
    out.release("b", upto=100)  # past the end: to the end only
    assert out.retentions["b"] == 7 and out.base == 6 and out.unacked() == (6, [ev(6)])
