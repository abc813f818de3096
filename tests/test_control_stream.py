"""Control streams (mso.protocol.control_stream): every control message a node sends a peer
arrives once and in order, or is given up by a rule; and a core sends its control messages on
them (fault seeds 400, 497, 734, 851 with control frames lost at random: a lost Moved, Prepare,
NodeDown or HandoverDone left a view stale for good)."""

from __future__ import annotations

import msgspec
import pytest

from mso.node.core import NodeCore
from mso.protocol import control_stream as cs
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.control_stream import ControlStreams
from mso.protocol.events import StreamTick
from mso.protocol.procedures.relocation.new_host import NewHost
from mso.sim.faults import Settings, run

REACHABLE = {"B": ("B", 1), "A": ("A", 1)}


def moved(version: int) -> m.Moved:
    return m.Moved("app", "v", "N9", -1, version)


def test_frames_arrive_once_and_in_order_whatever_order_they_come_in() -> None:
    a, b = ControlStreams(), ControlStreams()
    frames = [a.wrap("B", moved(k), 0, 0.0) for k in range(4)]
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    got: list[m.Message] = []
    for f in (frames[2], frames[0], frames[3], frames[0], frames[1], frames[2]):
        got += b.receive("A", f, 0.01, 0)
    assert got == [moved(0), moved(1), moved(2), moved(3)]
    assert b.duplicates == 2


def test_what_is_not_acknowledged_is_sent_again_with_a_doubling_timeout() -> None:
    a, b = ControlStreams(), ControlStreams()
    a.wrap("B", moved(0), 0, 0.0)  # lost
    sends, then = a.due(cs.RTO_S - 0.01, REACHABLE)
    assert sends == [] and then == cs.RTO_S
    sends, then = a.due(cs.RTO_S, REACHABLE)
    ((dst, frame),) = sends
    assert dst == "B" and isinstance(frame, m.Sequenced) and frame.body == moved(0)
    assert then == cs.RTO_S + 2 * cs.RTO_S  # backed off
    assert b.receive("A", frame, 0.3, 0) == [moved(0)]
    # its acknowledgement waits ACK_DELAY_S for a frame going back, then goes alone
    (ack,), _ = b.due(0.3 + cs.ACK_DELAY_S, REACHABLE)
    assert ack == ("A", m.Got(0, 0))
    a.on_got("B", 0, 0, 0.4)
    assert a.held() == 0 and a.next_due() is None


def test_an_acknowledgement_rides_on_a_frame_going_back() -> None:
    a, b = ControlStreams(), ControlStreams()
    assert b.receive("A", a.wrap("B", moved(0), 0, 0.0), 0.0, 0) == [moved(0)]
    back = b.wrap("A", moved(1), 0, 0.005)
    assert (back.ack_inc, back.ack) == (0, 0)
    a.receive("B", back, 0.01, 0)
    assert a.held() == 0
    sends, _ = b.due(1.0, REACHABLE)  # nothing left to acknowledge alone
    assert not [s for s in sends if isinstance(s[1], m.Got)]


def test_nothing_is_sent_again_to_an_unreachable_peer_until_a_route_appears() -> None:
    a = ControlStreams()
    a.wrap("B", moved(0), 0, 0.0)
    sends, then = a.due(1.0, {})
    assert sends == [] and then is None  # waits for the route, not on a timer
    assert a.reachable("B", 2.0) and a.next_due() == 2.0
    sends, _ = a.due(2.0, REACHABLE)
    assert [f.body for _, f in sends if isinstance(f, m.Sequenced)] == [moved(0)]


def test_a_frame_is_given_up_after_keep_s_and_the_receiver_skips_past_it() -> None:
    a, b = ControlStreams(), ControlStreams()
    a.wrap("B", moved(0), 0, 0.0)  # never arrives
    a.due(cs.KEEP_S, REACHABLE)
    assert a.given_up == 1 and a.held() == 0
    later = a.wrap("B", moved(1), 0, cs.KEEP_S + 1)
    assert later.low == 1  # nothing below 1 will come
    assert b.receive("A", later, cs.KEEP_S + 1, 0) == [moved(1)]


def test_a_peer_held_failed_or_restarted_is_not_sent_what_its_last_process_missed() -> None:
    a = ControlStreams()
    a.wrap("B", moved(0), 0, 0.0)
    a.forget("B")
    assert a.held() == 0 and a.given_up == 1
    assert a.wrap("B", moved(1), 0, 0.1).low == 1


def test_a_new_incarnation_starts_a_new_stream_and_the_old_ones_frames_are_dropped() -> None:
    old, new, b = ControlStreams(), ControlStreams(), ControlStreams()
    first = old.wrap("B", moved(0), 0, 0.0)
    late = old.wrap("B", moved(1), 0, 0.0)
    assert b.receive("A", first, 0.0, 0) == [moved(0)]
    assert b.receive("A", new.wrap("B", moved(2), 1, 0.1), 0.1, 0) == [moved(2)]  # seq 0 again
    assert b.receive("A", late, 0.2, 0) == [] and b.stale == 1
    # a reset (a new incarnation of the same process) starts its streams anew too
    again = old.wrap("B", moved(3), 1, 0.3)
    assert (again.inc, again.seq, again.low) == (1, 0, 0) and old.given_up == 2


def test_a_frame_for_an_earlier_incarnation_of_its_receiver_is_not_delivered() -> None:
    """A frame names its receiver's incarnation as its sender knows it: a later process (a
    restart or a reset) takes it in its turn and acknowledges it, but does not deliver it;
    an unknown one (-1) is not checked."""
    a, b = ControlStreams(), ControlStreams()
    old = a.wrap("B", moved(0), 0, 0.0, to=3)
    later = a.wrap("B", m.StopApp("app"), 0, 0.0, to=3)  # (for any process)
    assert (old.to, later.to) == (3, -1)
    assert b.receive("A", later, 0.1, 4) == []  # in order: behind the frame it will drop
    assert b.receive("A", old, 0.1, 4) == [m.StopApp("app")] and b.misaddressed == 1
    (ack,), _ = b.due(0.2, REACHABLE)
    assert ack == ("A", m.Got(0, 1))  # the sender stops sending them
    for to, inc in ((-1, 4), (4, 4), (5, 4)):  # unknown, the current one, one ahead
        frame = ControlStreams().wrap("B", moved(to), 0, 0.2, to=to)
        assert ControlStreams().receive("A", frame, 0.2, inc) == [moved(to)]
    # a frame of the wire before ``to`` decodes as for an unknown incarnation
    before = msgspec.msgpack.encode(msgspec.msgpack.decode(m.encode(old))[:-1])
    assert m.decode(before) == msgspec.structs.replace(old, to=-1)


def test_a_sender_gives_up_its_frames_for_a_receiver_s_earlier_incarnation() -> None:
    """Heard of in a later incarnation (by its membership, or by a frame of its own stream),
    a receiver is sent nothing of what was for the process before: it would drop it."""
    a = ControlStreams()
    a.wrap("B", moved(0), 0, 0.0, to=3)
    a.wrap("B", moved(1), 0, 0.0)  # (-1: as known)
    assert a.held() == 2 and a.incarnation_of("B") == 3
    later = a.wrap("B", moved(2), 0, 0.1, to=4)
    assert a.given_up == 2 and a.held() == 1 and (later.to, later.low) == (4, 2)
    (frame,) = [f for _, f in a.due(1.0, REACHABLE)[0] if isinstance(f, m.Sequenced)]
    assert (frame.body, frame.to) == (moved(2), 4)  # sent again for the process it was for
    a.wrap("C", moved(3), 0, 0.2, to=0)  # lost; then C is heard in its incarnation 1:
    assert a.receive("C", ControlStreams().wrap("A", moved(4), 1, 0.3), 0.3, 0) == [moved(4)]
    assert a.given_up == 3 and a.held() == 1 and a.incarnation_of("C") == 1


def test_an_undeploy_is_for_whichever_process_runs_at_the_receiver() -> None:
    """An undeploy (told to every node in reach again, because it may have restarted) is sent
    for any incarnation, and kept when a later one is heard of (tests/test_captured_robot.py:
    a restarted node hears the undeploy)."""
    a = ControlStreams()
    stop = m.StopApp("app")
    frames = [a.wrap("B", msg, 0, 0.0, to=3) for msg in (moved(0), stop, moved(1))]
    assert [f.to for f in frames] == [3, -1, 3]
    a.heard_of("B", 4)
    assert a.given_up == 2 and a.held() == 1
    (resent,) = [f for _, f in a.due(1.0, REACHABLE)[0] if isinstance(f, m.Sequenced)]
    assert (resent.body, resent.to, resent.low) == (stop, -1, 1)
    b = ControlStreams()  # B's new process takes it
    assert b.receive("A", resent, 1.0, 4) == [stop] and b.misaddressed == 0


def test_a_restarted_node_drops_a_frame_for_its_last_process() -> None:
    """Acknowledged, not delivered: the sender stops sending it; once it hears of the restart
    (the new process's beat) what it sends is for the new process (fault seed 314611: a
    Switch sent again at a heal reached a restarted target, whose new process took it)."""
    n1 = NodeCore("N1")
    n1.set_routes({"N2": ("N2", 1)}, 0.0)
    n1.receive("N2", NodeCore("N2").membership.beat(), 0.0)
    n1.send("N2", moved(0))
    (frame,) = [e.msg for e in n1._run(0.0) if isinstance(e, fx.Send)]
    assert isinstance(frame, m.Sequenced) and frame.to == 0
    n2 = NodeCore("N2", incarnation=1)  # N2 restarted
    n2.set_routes({"N1": ("N1", 1)}, 0.0)
    n2.receive("N1", frame, 0.5)
    assert n2.streams.misaddressed == 1 and not n2._work
    acks = [
        e.msg for e in n2.on_timer(StreamTick(), 0.5 + cs.ACK_DELAY_S) if isinstance(e, fx.Send)
    ]
    assert acks == [m.Got(frame.inc, frame.seq)]
    n1.receive("N2", acks[0], 0.6)
    assert n1.streams.held() == 0
    n1.receive("N2", n2.membership.beat(), 0.6)
    assert n1.incarnation_of("N2", -1) == 1
    n1.send("N2", moved(1))
    (frame,) = [e.msg for e in n1._run(0.7) if isinstance(e, fx.Send) and e.said == moved(1)]
    assert isinstance(frame, m.Sequenced) and frame.to == 1
    assert n2.streams.receive("N1", frame, 0.8, n2.incarnation) == [moved(1)]


def test_a_restarted_target_takes_no_switch_for_its_last_process(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Control loss seed 314611 with the relocation's own guard off (a Switch to a node that
    holds no instance prepared for the move is refused, ``NewHost.prepared_for``): the
    stream's frames name their receiver's incarnation, so the restarted target's new process
    drops its last process's Switch sent again at the heal, and the vertex is not handed over
    to nothing."""
    monkeypatch.setattr(NewHost, "prepared_for", lambda self, app, vertex, rid: True)
    cfg = Settings(start_s=1.0, faults_s=3.0, quiet_s=4.0, rate=10.0, restarts=True,
                   planner="paper", control_loss=0.01)  # fmt: skip
    result = run(314611, cfg)
    assert not result.violations, result.violations


def test_what_a_stream_holds_is_bounded() -> None:
    a, b = ControlStreams(), ControlStreams()
    for k in range(cs.MAX_UNACKED + 5):
        a.wrap("B", moved(k), 0, 0.0)
    assert a.held() == cs.MAX_UNACKED and a.given_up == 5
    c = ControlStreams()
    frames = [c.wrap("B", moved(k), 0, 0.0) for k in range(cs.MAX_HELD + 10)]
    for f in frames[1:]:  # the first is missing: the rest wait behind it, up to MAX_HELD
        assert b.receive("C", f, 0.0, 0) == []
    assert b.receive("C", frames[0], 0.0, 0) == [moved(k) for k in range(cs.MAX_HELD + 1)]


def test_a_core_sends_control_messages_on_its_streams_and_delivers_them_in_order() -> None:
    """The core wraps what it sends (data and beats go as they are), unwraps what it gets in
    order, and sends again on its StreamTick what was not acknowledged."""
    n1 = NodeCore("N1")
    n1.set_routes({"N2": ("N2", 1)}, 0.0)
    n1.send("N2", moved(0))
    n1.send("N2", m.Ack("app", 0, 0, 1))
    out = n1._run(0.0)
    (frame,) = [e.msg for e in out if isinstance(e, fx.Send) and type(e.msg) is m.Sequenced]
    assert frame.body == moved(0)
    assert [e.said for e in out if isinstance(e, fx.Send)] == [moved(0), m.Ack("app", 0, 0, 1)]
    (tick,) = [e for e in out if isinstance(e, fx.SetTimer)]
    assert tick.key == StreamTick() and tick.at == cs.RTO_S
    again = [e.msg for e in n1.on_timer(StreamTick(), cs.RTO_S) if isinstance(e, fx.Send)]
    assert again and all(type(f) is m.Sequenced and f.seq == frame.seq for f in again)
    n1.receive("N2", m.Got(frame.inc, frame.seq), 0.3)
    assert n1.streams.held() == 0
    counted = n1.status(0.3)["control_streams"]
    assert counted["unacknowledged"] == 0 and counted["resent"] == len(again)


def test_control_frames_lost_at_random_leave_no_view_stale() -> None:
    """Seeds 400, 497, 734 and 851 of the fault schedules, each control frame lost with
    probability 0.01 (``bench/faults.py --control-loss 0.01``): every one broke an invariant
    before control streams (a placement the nodes disagreed on, a vertex placed where it does
    not run, a sink stalled)."""
    cfg = Settings(start_s=1.0, faults_s=3.0, quiet_s=4.0, rate=10.0, restarts=True,
                   planner="paper", control_loss=0.01)  # fmt: skip
    for seed in (400, 497, 734, 851):
        result = run(seed, cfg)
        assert not result.violations, (seed, result.violations)


def test_the_peers_a_receiver_keeps_state_for_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Past MAX_PEERS the least recently heard sender is forgotten, one with frames held
    early last: the bound holds whatever the senders do."""

    monkeypatch.setattr(cs, "MAX_PEERS", 2)
    b = ControlStreams()
    early = ControlStreams()
    early.wrap("B", moved(0), 0, 0.0)  # lost: the next waits at B
    assert b.receive("E", early.wrap("B", moved(1), 0, 0.0), 0.0, 0) == []
    for peer in ("F", "G"):
        assert b.receive(peer, ControlStreams().wrap("B", moved(2), 0, 0.0), 0.1, 0) == [moved(2)]
    assert list(b._in) == ["E", "G"]  # F, heard before G and holding nothing, went first
    assert b.receive("H", ControlStreams().wrap("B", moved(3), 0, 0.0), 0.2, 0) == [moved(3)]
    assert len(b._in) == 2 and "H" in b._in
