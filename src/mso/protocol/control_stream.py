"""Control streams: every control message a node sends another arrives once and in order, or
is given up by a rule. Sans-IO.

A control frame is lost when its route is missing longer than the route wait
(:mod:`mso.net.forwarding`), when a relay holding it dies, or when a connection breaks with it
queued. Most procedures ask and wait with a deadline, but some frames are said once — a move's
``Moved``, a rejoin's ``AppSync``, a claim's ``NodeDown``, a handover's ``HandoverDone`` — and
their loss left a view stale for good (the fault schedules with control frames lost,
``bench/faults.py --control-loss``). So each node numbers what it sends each peer, as TCP
numbers bytes, end to end across the overlay's hops:

- the sender keeps each frame until the receiver acknowledges it, and sends it again after a
  timeout (doubling, up to :data:`RTO_MAX_S`) while the receiver is reachable, and at once
  when a route to it appears; it gives a frame up after :data:`KEEP_S` (what it said is
  settled by then by other means: a rejoin's sync, the procedures' own deadlines), when the
  receiver is held failed or heard back in a later incarnation (the frames were for the
  process that died), or past :data:`MAX_UNACKED` frames (the oldest first);
- a frame carries ``low``, the lowest number its sender still holds: the receiver never
  waits for a frame below it;
- the receiver delivers frames in order and once, holds up to :data:`MAX_HELD` that came
  early, and acknowledges cumulatively: on a frame going back within :data:`ACK_DELAY_S`,
  else in a :class:`~mso.protocol.messages.Got` of its own.

A stream is one incarnation's (a reset or a restart starts new ones); a frame of an earlier
incarnation than the receiver has seen is dropped. A frame also names its receiver's
incarnation as its sender knows it (``to``: the latest its membership or the receiver's own
stream told it; -1 unknown, then nothing is checked): a frame sent, or sent again, before its
sender heard of the receiver's reset or restart reached the new process, which took it for its
own (fault seed 314611: a ``Switch`` sent again at a heal to a restarted target). A later
process takes such a frame in its turn and acknowledges it, as any, but does not deliver it
(the sender stops sending it; it hears of the restart as before, from the new process's
beats); the sender gives the frames kept for an earlier incarnation up whenever it hears of a
later one (a frame of the receiver's stream of that incarnation, a rejoin, or a frame sent for
it). A reset bumps the incarnation too: what was sent for the process before it was for
procedures and apps it dropped, and a reply to what it asked since is for its new incarnation
(the request's own frame told its sender). An undeploy, a word
for whichever process runs there rather than a step of a procedure with one
(:data:`FOR_ANY_INCARNATION`), goes for any. Data frames (events and their acks, which
channels number and replay themselves), markers (which travel in order with data), heartbeats,
liveness questions (worth nothing late) and the status check go as they are.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

from mso.protocol import messages as m

RTO_S = 0.25
"""A frame not acknowledged this long after it was sent is sent again (then 2x, 4x...)."""
RTO_MAX_S = 4.0
KEEP_S = 10.0
"""A frame is sent again for at most this long after it was first sent, then given up."""
ACK_DELAY_S = 0.02
"""How long an acknowledgement waits for a frame going back to ride on."""
MAX_UNACKED = 1024
"""Frames kept per receiver; past it the oldest is given up (a bound on memory)."""
MAX_HELD = 256
"""Frames that came early (a gap before them) held per sender; more are dropped (sent again)."""
MAX_PEERS = 4096
"""Peers whose receiving state is kept; past it the ones with nothing held are forgotten."""

UNSEQUENCED: frozenset[type] = frozenset(
    {
        m.Data,
        m.Ack,
        m.TapEvents,
        m.ChainDelay,
        m.Marker,
        m.Heartbeat,
        m.Suspect,
        m.Hears,
        m.Probe,
        m.ProbeReply,
        m.StatusRequest,
        m.StatusReply,
        m.PeerHello,
        m.ClientHello,
        m.Sequenced,
        m.Got,
    }
)
"""What goes as it is (see the module docstring). Probes measure the path they take, and
a deployment or remap probes again on its own deadline."""

FOR_ANY_INCARNATION: frozenset[type] = frozenset({m.StopApp})
"""Not a step of a procedure with the receiver's process but a word for whichever runs there:
an undeploy (an operator's binds every process, and is told to every node in reach again
precisely because it may have restarted). Sent with ``to`` -1, kept when its sender hears of
a later process."""


@dataclass
class _Sent:
    msg: m.Message
    first: float
    last: float
    anyone: bool  # for whichever process runs at the receiver (FOR_ANY_INCARNATION)


@dataclass
class _Out:
    """What this node sends one peer: the frames it has not had acknowledged."""

    inc: int
    to: int = -1  # the receiver's incarnation its frames are for (-1: unknown)
    next_seq: int = 0
    unacked: OrderedDict[int, _Sent] = field(default_factory=OrderedDict)
    rto: float = RTO_S
    due: float | None = None  # when to send the unacknowledged again (None: when reachable)

    @property
    def low(self) -> int:
        return next(iter(self.unacked)) if self.unacked else self.next_seq


@dataclass
class _In:
    """What this node receives from one peer: its stream's incarnation, the next number due
    and the frames that came before it."""

    inc: int
    next_seq: int = 0
    held: dict[int, m.Message | None] = field(default_factory=dict)  # None: misaddressed


class ControlStreams:
    """One node's control streams to and from every peer."""

    def __init__(self) -> None:
        self._out: dict[str, _Out] = {}
        self._in: OrderedDict[str, _In] = OrderedDict()
        self._ack_due: dict[str, float] = {}  # peer -> when its acknowledgement goes alone
        self.resent = 0  # frames sent again
        self.given_up = 0  # frames never acknowledged: timed out, bounded out, peer gone
        self.duplicates = 0  # frames that came again, dropped
        self.stale = 0  # frames of an earlier incarnation of their sender, dropped
        self.misaddressed = 0  # frames for an earlier incarnation of this node, dropped

    # -- sending ---------------------------------------------------------------------------
    def wrap(self, dst: str, msg: m.Message, inc: int, now: float, to: int = -1) -> m.Sequenced:
        """``msg`` as the next frame of this node's (incarnation ``inc``) stream to ``dst``,
        for ``dst``'s incarnation ``to`` (-1: unknown)."""
        out = self._out.get(dst)
        if out is None or out.inc != inc:  # a reset or a first frame: a new stream
            if out is not None:
                self.given_up += len(out.unacked)
            out = self._out[dst] = _Out(inc)
        self.heard_of(dst, to)
        seq = out.next_seq
        out.next_seq += 1
        sent = out.unacked[seq] = _Sent(msg, now, now, type(msg) in FOR_ANY_INCARNATION)
        if len(out.unacked) > MAX_UNACKED:
            out.unacked.popitem(last=False)
            self.given_up += 1
        if out.due is None:
            out.due = now + out.rto
        return self._frame(dst, out, seq, sent)

    def _frame(self, dst: str, out: _Out, seq: int, sent: _Sent) -> m.Sequenced:
        ack_inc, ack = self._take_ack(dst)
        to = -1 if sent.anyone else out.to
        return m.Sequenced(out.inc, seq, out.low, sent.msg, ack_inc, ack, to)

    def _take_ack(self, peer: str) -> tuple[int, int]:
        if self._ack_due.pop(peer, None) is None:
            return -1, -1
        got = self._in.get(peer)
        return (got.inc, got.next_seq - 1) if got is not None else (-1, -1)

    def on_got(self, src: str, inc: int, upto: int, now: float) -> None:
        """``src`` has every frame of our stream ``inc`` up to ``upto``."""
        out = self._out.get(src)
        if out is None or out.inc != inc or upto < 0:
            return
        acked = False
        while out.unacked:
            seq = next(iter(out.unacked))
            if seq > upto:
                break
            del out.unacked[seq]
            acked = True
        if acked:
            out.rto = RTO_S
            out.due = now + out.rto if out.unacked else None

    def heard_of(self, peer: str, inc: int) -> None:
        """``peer`` runs incarnation ``inc`` (or a later one): frames kept for an earlier one
        are given up (that process died or reset: it would drop them; those for any process
        stay), and what is sent or sent again from now on is for this one."""
        out = self._out.get(peer)
        if out is None or inc <= out.to:
            return
        if out.to >= 0:
            for seq in [q for q, sent in out.unacked.items() if not sent.anyone]:
                del out.unacked[seq]
                self.given_up += 1
            if not out.unacked:
                out.due = None
        out.to = inc

    def incarnation_of(self, peer: str) -> int:
        """The incarnation of ``peer`` this node's frames are for (-1: none known here): the
        latest of those sent for and of ``peer``'s own stream here."""
        out = self._out.get(peer)
        got = self._in.get(peer)
        return max(out.to if out is not None else -1, got.inc if got is not None else -1)

    def forget(self, peer: str) -> None:
        """``peer`` is held failed or came back as a new process: what it was not sent is
        for the process that died (a rejoin's sync tells the new one what it must know)."""
        out = self._out.get(peer)
        if out is not None and out.unacked:
            self.given_up += len(out.unacked)
            out.unacked.clear()
            out.due = None

    def reachable(self, peer: str, now: float) -> bool:
        """A route to ``peer`` appeared: what it was not acknowledged goes again now (True:
        something does)."""
        out = self._out.get(peer)
        if out is None or not out.unacked:
            return False
        out.due = now
        return True

    def reset(self) -> None:
        """This node reset (a new incarnation): it drops what it sent, as it drops its apps."""
        for out in self._out.values():
            self.given_up += len(out.unacked)
        self._out.clear()

    # -- receiving -------------------------------------------------------------------------
    def receive(self, src: str, frame: m.Sequenced, now: float, inc: int) -> list[m.Message]:
        """The messages ``frame`` makes deliverable to this node (incarnation ``inc``), in
        order (none, it, or it and those held behind it). One for an earlier incarnation of
        this node (:meth:`misaddressed_to`) is taken in its turn and acknowledged, as any,
        but not delivered."""
        if frame.ack >= 0:
            self.on_got(src, frame.ack_inc, frame.ack, now)
        body = None if self.misaddressed_to(frame, inc) else frame.body
        self.heard_of(src, frame.inc)
        got = self._in.get(src)
        if got is None or frame.inc > got.inc:  # a first frame, or a new process or reset
            got = _In(frame.inc, frame.low)
            self._in[src] = got
            self._bound_peers()
        elif frame.inc < got.inc:
            self.stale += 1
            return []
        self._in.move_to_end(src)
        self._ack_due.setdefault(src, now + ACK_DELAY_S)
        if frame.low > got.next_seq:  # the sender gave up what came before: skip it
            got.next_seq = frame.low
            for seq in [s for s in got.held if s < frame.low]:
                del got.held[seq]
        if frame.seq < got.next_seq or frame.seq in got.held:
            self.duplicates += 1
            return []
        if frame.seq > got.next_seq:
            if len(got.held) < MAX_HELD:
                got.held[frame.seq] = body
            return []
        got.held[frame.seq] = body
        ready: list[m.Message] = []
        while got.next_seq in got.held:
            taken = got.held.pop(got.next_seq)
            got.next_seq += 1
            if taken is None:
                self.misaddressed += 1
            else:
                ready.append(taken)
        return ready

    @staticmethod
    def misaddressed_to(frame: m.Sequenced, inc: int) -> bool:
        """``frame`` was sent for an earlier process of this node (incarnation ``inc``): one
        that died or reset before its sender heard of it."""
        return 0 <= frame.to < inc

    def _bound_peers(self) -> None:
        """Past MAX_PEERS, the least recently heard peer is forgotten (one holding nothing
        early first)."""
        while len(self._in) > MAX_PEERS:
            peer = next((p for p, g in self._in.items() if not g.held), next(iter(self._in)))
            del self._in[peer]
            self._ack_due.pop(peer, None)

    # -- time ------------------------------------------------------------------------------
    def due(
        self, now: float, reachable: dict[str, tuple[str, int]]
    ) -> tuple[list[tuple[str, m.Message]], float | None]:
        """What is due at ``now``: frames sent again (to reachable peers), acknowledgements
        alone; and when to look again (None: nothing waits on time)."""
        sends: list[tuple[str, m.Message]] = []
        for peer, out in self._out.items():
            if not out.unacked or out.due is None or out.due > now:
                continue
            while out.unacked:  # given up after KEEP_S
                seq, sent = next(iter(out.unacked.items()))
                if sent.first + KEEP_S > now:
                    break
                del out.unacked[seq]
                self.given_up += 1
            if not out.unacked:
                out.due = None
                continue
            if peer not in reachable:
                out.due = None  # again when a route appears (``reachable``)
                continue
            for seq, sent in out.unacked.items():
                sent.last = now
                sends.append((peer, self._frame(peer, out, seq, sent)))
                self.resent += 1
            out.rto = min(out.rto * 2, RTO_MAX_S)
            out.due = now + out.rto
        for peer, at in list(self._ack_due.items()):
            if at <= now:
                ack_inc, ack = self._take_ack(peer)
                if ack >= 0:
                    sends.append((peer, m.Got(ack_inc, ack)))
        return sends, self.next_due()

    def next_due(self) -> float | None:
        times = [o.due for o in self._out.values() if o.due is not None and o.unacked]
        times += self._ack_due.values()
        return min(times) if times else None

    def held(self) -> int:
        """Frames kept unacknowledged, to every peer (status)."""
        return sum(len(o.unacked) for o in self._out.values())

    def status(self) -> dict[str, int]:
        return {
            "unacknowledged": self.held(),
            "resent": self.resent,
            "given_up": self.given_up,
            "duplicates": self.duplicates,
            "stale": self.stale,
            "misaddressed": self.misaddressed,
        }
