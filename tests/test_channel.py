"""Per-edge channels on their own: acks, retention, and what a producer keeps."""

from __future__ import annotations

import pytest

from mso.protocol.channel import HOLD_INEXACT, AckGate, InChannel, OutChannel


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
    assert out.base == 6 and out.retained_from("snap") == 6
    out.release("snap")
    assert out.retained("snap") is None and out.base == 8 and out.kept == 2
    assert out.retained_from("snap") is None


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


def test_an_ack_with_no_positions_keeps_those_known_at_its_position() -> None:
    """A replacement acking again what a replay repeated knows no output positions yet: the
    ones the lost instance's ack brought stay, for a later restore of the consumer to number
    its output from (seed 1998 of the fault schedules: one event twice at the sink)."""
    out = OutChannel(window=100)
    out.push_many([ev(i) for i in range(10)])
    out.on_ack(4)
    out.note_positions(4, {1: 7})
    out.on_ack(4)
    out.note_positions(4, {})
    assert out.positions == {1: 7} and out.history[4] == {1: 7}
    out.on_ack(6)
    out.note_positions(6, {})  # past them: they no longer say where the output stands
    assert out.positions == {}


def test_a_consumer_awaiting_a_replay_does_not_skip_ahead_on_an_earlier_frame() -> None:
    """A replacement starts from a replica's snapshot at 3 while its producer, acked to 8,
    has frames on the way from before it got the Replay: their floor (8) would skip what the
    replay brings (seed 2748: 18 events never delivered). They wait; the replay comes first."""
    inc = InChannel(expected=3, processed=3, _acked=3, awaiting_replay=True)
    assert inc.accept(8, [ev(8), ev(9)], floor=8) == []
    assert inc.expected == 3 and inc.skipped == 0
    assert inc.accept(3, [ev(i) for i in range(3, 10)], floor=3) == [ev(i) for i in range(3, 10)]
    assert inc.accept(10, [ev(10)], floor=9) == [ev(10)] and not inc.awaiting_replay


def test_ack_gate_waits_for_positions_known_further_down() -> None:
    """A checkpoint whose output positions no ack from downstream came at is held for the next
    one that is (seed 60473); at most HOLD_INEXACT of them, then the ack goes anyway."""
    gate = AckGate()
    for n in (1, 2, 3):
        gate.record({0: n}, {1: n})
    known = {3}
    assert gate.release({1: 2}, lambda outs: outs[1] in known) is None  # 1 and 2: not known
    assert gate.release({1: 3}, lambda outs: outs[1] in known) == ({0: 3}, {1: 3})
    gate.record({0: 4}, {1: 4})
    gate.record({0: 5}, {1: 5})
    assert gate.release({1: 5}, lambda outs: outs[1] == 4) == ({0: 4}, {1: 4})  # the last known
    assert gate.release({1: 5}) == ({0: 5}, {1: 5})  # (no check: as before)
    for n in range(6, 6 + HOLD_INEXACT):
        gate.record({0: n}, {1: n})
    last = 5 + HOLD_INEXACT
    assert gate.release({1: last - 1}, lambda outs: False) is None
    assert gate.release({1: last}, lambda outs: False) == ({0: last}, {1: last})
