"""Store and forward at a producer: what its edges do while their consumer is out of reach.

A component of the data plane (:mod:`mso.protocol.dataplane`). An edge whose consumer's node
is held failed or has no route keeps numbering and keeping its events (within the bounds and
policies of :mod:`mso.protocol.delivery`, spilling to the node's store past memory), sends
nothing there, and drains its backlog a window at a time once the consumer is back or restored
elsewhere. Also here: go-back-N retransmission, and a source's edge channels across this node's
reset. Sans-IO.
"""

from __future__ import annotations

from typing import Protocol

from mso.protocol import delivery
from mso.protocol import messages as m
from mso.protocol.channel import GEN_NOTE, REPLICA_OWNER, OutChannel
from mso.protocol.context import NodeContext
from mso.protocol.effects import Send, SetTimer
from mso.protocol.events import Retransmit
from mso.protocol.spill import placement_notes
from mso.protocol.state import AppState

RETRANSMIT_S = 0.25
ASK_EVERY_S = 1.0  # a guessed channel asks its consumer where it stands at most this often
# go-back-N doubles its wait after each resend without progress, up to this (OutChannel.overdue)
RETRANSMIT_MAX_S = 2.0
HANDOVER_PART_BYTES = 1 << 20  # events a move's Handover carries itself, and each part ahead
MAX_BATCH_BYTES = 64 * 1024  # a Data frame is sent once its events reach about this size
# a backlog (after an outage, or handed over unsent) drains with at most about this much
# unacknowledged: the rest goes as acks come back. Without it a heal sent a window (4,096
# events: 200 MB of 50 KB ones) in one turn, and on the emulator the two ends of a 10-minute
# cut, each busy with it past the detector's window, declared each other: the sink's node
# reset, its sink was restored and the whole window went again: 58 times in 105 s.
MAX_IN_FLIGHT_BYTES = 4 * 1024 * 1024


class Plane(Protocol):
    """What store and forward uses of the data plane."""

    outbox: dict[tuple[str, int], tuple[int, list[bytes], float]]
    armed: set[str]  # apps whose retransmit timer is set

    def unacked(self, dep: AppState) -> bool: ...

    def out(self, dep: AppState, edge: int) -> OutChannel: ...

    def deliver(
        self,
        dep: AppState,
        edge: int,
        seq: int,
        events: list[bytes],
        ts: float = 0.0,
        floor: int = 0,
        gens: dict[int, int] | None = None,
    ) -> None: ...

    def stamp_gens(self, dep: AppState, edge: int) -> dict[int, int]: ...

    def release(self, dep: AppState, vid: str) -> None: ...

    def unblock(self, dep: AppState, edge: int) -> None: ...


class StoreAndForward:
    """The producer's side of an outage (see the module docstring)."""

    def __init__(self, ctx: NodeContext, dp: Plane) -> None:
        self.ctx = ctx
        self.dp = dp
        # (app, epoch, edge) -> a source's channel kept across this node's reset, until the
        # source is restored here (bounded: one per edge of the apps it ran)
        self.carried: dict[tuple[str, int, int], OutChannel] = {}

    def carry(self, dep: AppState) -> None:
        """This node resets: its sources' edge channels outlive it (see ``carry_over``)."""
        for vid, h in dep.instances.items():
            if h.kind == "source":
                for e in dep.out_edges.get(vid, []):
                    if e in dep.out:
                        self.carried[(dep.app.name, dep.epoch, e)] = dep.out[e]

    def carry_over(self, dep: AppState, edge: int, start: int) -> OutChannel | None:
        """A source restored here after this node reset: the channel its edge had before the
        reset, if it still holds ``start`` (where the consumer stands; below its ack when the
        consumer is being restored too and said nothing: acks are chained, so what it acked is
        safe downstream): what the source made while cut off is still delivered, and it
        numbers on from there, never from 0 (seed 1998: its positions with it)."""
        ch = self.carried.pop((dep.app.name, dep.epoch, edge), None)
        if ch is None or start > ch.next_seq:
            return None
        if ch.positions and ch.positions_at == ch.acked < start:
            # the consumer stands past the last ack, whose positions are known (its next ack
            # lost): kept from that ack, as a restarted daemon's edge is (OutChannel.recover),
            # so that the Resume's start and positions name one point: a replacement of the
            # consumer numbers the replay as the lost one did, a live one drops what it has
            start = ch.acked
        start = max(start, ch.acked)
        ch.on_ack(start, self.ctx.now)
        ch.sent = start  # the rest goes (again), a window at a time
        return ch

    def channel(self, dep: AppState, edge: int, start: int = 0) -> OutChannel:
        """A new producer end of ``edge`` numbering from ``start``; past its window and memory
        bound it spills to the node's store (what an earlier end here left there is gone)."""
        key = self.key(dep, edge)
        self.ctx.spill.drop(key)
        ch = OutChannel(self.ctx.window, start, start, self.ctx.now, store=self.ctx.spill, key=key)
        ch.persist = dep.layout.kinds[dep.app.edges[edge].src] == "source"
        if ch.persist:
            self.ctx.spill.save_position(key, start)
            self.ctx.spill.forget_notes(key + GEN_NOTE)  # (numbered as the deployment's)
        return ch

    def handover_events(self, out: OutChannel) -> tuple[list[bytes], list[tuple[int, list[bytes]]]]:
        """An output's unacknowledged events for a move's handover: all in the handover when
        they fit ``HANDOVER_PART_BYTES``, else none there and ``(first seq, events)`` parts of
        about that size to send ahead of it (a backlog kept for a consumer out of reach may be
        far beyond one frame)."""
        per_event = max(1, out.kept_bytes // max(1, out.kept))
        if out.in_flight * per_event <= HANDOVER_PART_BYTES:
            return out.unacked()[1], []
        step, pos, parts = max(1, HANDOVER_PART_BYTES // per_event), out.acked, []
        while pos < out.next_seq:
            first, events = out.events_from(pos, min(step, out.next_seq - pos))
            if not events:
                break
            parts.append((first, events))
            pos = first + len(events)
        return [], parts

    def key(self, dep: AppState, edge: int) -> str:
        """The name of ``edge``'s events and position in the node's spill store."""
        return f"{dep.app.name}/{dep.epoch}/{edge}"

    def recover(self, dep: AppState, edge: int, start: int) -> OutChannel | None:
        """A source restored here after this node's daemon restarted: its edge numbers on from
        the position the old process saved, and what it held for an unreachable consumer (in
        the store) is delivered; None if nothing was saved (another node's source before)."""
        store, key = self.ctx.spill, self.key(dep, edge)
        retain = REPLICA_OWNER if dep.replicas.get(dep.app.edges[edge].dst) else None
        return OutChannel.recover(store, key, start, self.ctx.window, self.ctx.now, retain)

    def forget(self, dep: AppState) -> None:
        """The app is gone from this node: its edges' events and positions too."""
        for edge in range(len(dep.app.edges)):
            self.ctx.spill.drop(self.key(dep, edge))
            self.ctx.spill.forget_notes(self.key(dep, edge) + GEN_NOTE)
        self.ctx.spill.forget_notes(placement_notes(dep.app.name))  # (placement.remember)

    def held(self, dep: AppState, edge: int) -> bool:
        """The consumer of ``edge`` is out of reach (failed, or no route to it), or placed on
        unconfirmed hearsay (:meth:`AppState.unconfirmed`: a captured member's first sync
        would have its events sent to it): its events wait here until it is back, restored
        elsewhere or confirmed (store and forward). So do a guessed numbering's, wherever the
        consumer runs, until it says where it stands (:meth:`ask_where`)."""
        consumer = dep.app.edges[edge].dst
        dst = dep.placed[consumer]
        out = dep.out.get(edge)
        if out is not None and out.unsure:
            # (a consumer here too: restored before it, past its consumers' marks, it dropped
            # the guess's first 12 events as had; restart seed 102602)
            return True
        if dst == self.ctx.id:
            return False
        return dst in self.ctx.failed or dst not in self.ctx.routes or dep.unconfirmed(consumer)

    def ask_where(self, dep: AppState, edge: int, out: OutChannel, now: float) -> None:
        """A guessed channel whose consumer is in reach: ask it where it stands, as a
        restore's ``Rewire`` does (its answer, a ``Resume``, renumbers the channel from there:
        :meth:`mso.protocol.procedures.restore.Restorer.on_resume`). A consumer that survived
        out of reach of the restore has events this numbering would repeat."""
        dst = dep.placed[dep.app.edges[edge].dst]
        away = dst != self.ctx.id and (dst in self.ctx.failed or dst not in self.ctx.routes)
        if now - out.asked_at < ASK_EVERY_S or away:
            return
        out.asked_at = now
        self.ctx.send(dst, m.Rewire(dep.app.name, edge, self.ctx.id, 0, False))

    def edge_room(self, dep: AppState, edge: int) -> int:
        """Events the producer of ``edge`` may make now (the window, or the store's bound)."""
        held = self.held(dep, edge)
        return delivery.room(self.dp.out(dep, edge), dep.app.edges[edge], held)

    def hold(self, dep: AppState, edge: int, out: OutChannel) -> None:
        """Events wait on ``edge``: apply its bound, history and lifespan, then send what a
        reachable consumer's window admits."""
        held = self.held(dep, edge)
        out.out_of_reach |= held
        if held and out.persist:  # what a source's edge holds survives a restart
            out.make_durable()
        if delivery.enforce(out, dep.app.edges[edge], held, self.ctx.now):
            self.gave_up(dep, edge)
        self.drain(dep, edge)

    def gave_up(self, dep: AppState, edge: int) -> None:
        """Events of ``edge`` were given up as if acknowledged: pass that on upstream (chained
        acks) and wake a producer held by the bound."""
        producer = dep.app.edges[edge].src
        if producer in dep.instances:
            self.dp.release(dep, producer)
        self.dp.unblock(dep, edge)

    def drain(self, dep: AppState, edge: int) -> None:
        """Send what ``edge`` holds unsent, as far as its window and ``MAX_IN_FLIGHT_BYTES``
        admit, in frames of about ``MAX_BATCH_BYTES`` (after an outage, or events handed over
        unsent); each ack drains on."""
        out = dep.out.get(edge)
        if out is None or self.held(dep, edge):
            return
        if out.out_of_reach:
            self.back_in_reach(out)
        if out.sent >= out.next_seq:
            return
        app, dst = dep.app.name, dep.placed[dep.app.edges[edge].dst]
        batch = self.dp.outbox.pop((app, edge), None)  # what was sent before goes first
        if batch is not None:
            data = m.Data(app, edge, dep.epoch, *batch, floor=out.acked)
            data.gens = self.dp.stamp_gens(dep, edge)
            self.ctx.emit(Send(dst, data))
        size = max(1, out.kept_bytes // max(1, out.kept))  # an event's, on average
        per_frame = max(1, MAX_BATCH_BYTES // size)
        room = max(1, MAX_IN_FLIGHT_BYTES // size) - (out.sent - out.acked)
        ts = out.stamp(out.sent)
        while room > 0:
            first, events = out.unsent(min(per_frame, room))
            if not events:
                return
            room -= len(events)
            self.transmit(dep, edge, first, events, ts, out.acked)

    def spill_ready(self, key: str) -> None:
        """The node's store has read ahead events of ``key`` (an edge's name in it, see
        :meth:`key`) that a drain waited for: drain on."""
        app, epoch, edge = key.rsplit("/", 2)
        dep = self.ctx.apps.get(app)
        if dep is not None and dep.running and str(dep.epoch) == epoch and edge.isdigit():
            self.drain(dep, int(edge))

    def back_in_reach(self, out: OutChannel) -> None:
        """The consumer is in reach again after an outage. What was sent before it went out
        of reach and is not acknowledged may have been lost with the link (and a consumer
        drops what follows a gap), so it all goes again, in order from the ack, once: the
        retransmission clock starts now. (It ran on through the outage, so the first tick
        after a heal found the backlog just drained overdue and sent it again whole, then
        again at every tick while the link still carried the first copies: on the emulator,
        469 events of 50 KB sent again after a 10 s cut, 130 of them dropped as duplicates.)
        What goes twice is at most what was in flight when the consumer went out of reach."""
        out.out_of_reach = False
        out.sent = out.acked
        out.waiting_since = self.ctx.now

    def transmit(
        self, dep: AppState, edge: int, first: int, events: list[bytes], ts: float, floor: int
    ) -> None:
        """Events ``first``... of ``edge`` to its consumer, now (here: delivered at once)."""
        dst = dep.placed[dep.app.edges[edge].dst]
        gens = self.dp.stamp_gens(dep, edge)
        if dst == self.ctx.id:
            self.dp.deliver(dep, edge, first, events, ts, floor, gens)
        else:
            data = m.Data(dep.app.name, edge, dep.epoch, first, events, ts, floor, gens=gens)
            self.ctx.emit(Send(dst, data))

    def retransmit(self, app: str, now: float) -> None:
        """Go-back-N: resend what has waited a whole period without any ack progress (a
        window at most; a best-effort edge gives it up instead), the period doubling while
        nothing progresses (up to RETRANSMIT_MAX_S). Then the periodic part of
        store and forward: bounds and lifespans applied, backlogs drained to consumers back
        in reach, producers the bound held woken."""
        dep = self.ctx.apps.get(app)
        if dep is None or not dep.running:
            self.dp.armed.discard(app)
            return
        for edge, ch in list(dep.out.items()):
            e = dep.app.edges[edge]
            held = self.held(dep, edge)
            if delivery.enforce(ch, e, held, now):
                self.gave_up(dep, edge)
            if held:  # kept until the consumer is back or restored elsewhere
                if ch.unsure:
                    self.ask_where(dep, edge, ch, now)
                ch.out_of_reach = True
                if ch.persist:
                    ch.make_durable()
                self.dp.unblock(dep, edge)  # (it may make events into the store now)
                continue
            if ch.out_of_reach:
                self.back_in_reach(ch)
            if ch.overdue(now, RETRANSMIT_S, RETRANSMIT_MAX_S) and ch.sent > ch.acked:
                if e.qos == "best_effort":
                    ch.given_up += ch.drop_front(ch.sent, now)
                    self.gave_up(dep, edge)
                else:  # ``first`` is the acked position: nothing below it will come again
                    n = min(ch.sent - ch.acked, ch.window)
                    first, events = ch.events_from(ch.acked, n, ready=True)
                    ch.sent_again(events)
                    if len(events) < n:  # the rest is still read: the drain sends it
                        ch.sent = first + len(events)
                    per_frame = max(1, MAX_BATCH_BYTES // max(1, ch.kept_bytes // ch.kept))
                    for i in range(0, len(events), per_frame):
                        chunk = events[i : i + per_frame]
                        self.transmit(dep, edge, first + i, chunk, ch.stamp(first), first)
                ch.retried(now)
            self.drain(dep, edge)
            if dep.app.edges[edge].src in dep.blocked_sources:
                self.dp.unblock(dep, edge)
        if self.dp.unacked(dep):  # armed only while something waits for an ack (or a source
            self.dp.armed.add(app)  # for room)
            self.ctx.emit(SetTimer(Retransmit(app), now + RETRANSMIT_S))
        else:
            self.dp.armed.discard(app)
