"""Per-edge channels: sequence numbers, cumulative acks, a replay buffer and a send window.

Sans-IO. The producer's node keeps an :class:`OutChannel` per edge instance and the consumer's
node an :class:`InChannel`. Events are numbered from 0; the consumer acknowledges cumulatively
once events are processed, and the producer keeps every unacknowledged event so it can send them
again: after a loss (go-back-N on a retransmission timer), into a relocated instance, or into a
remapped one after a node failure. The window bounds that buffer; a full window is backpressure:
the producer stops until acks arrive. The consumer drops duplicates and anything past a gap, so
each event is delivered once and in order.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any

from mso.protocol.spill import SpillStore

# a source's edge saves a bound on its numbers this far ahead, not every number: a restart
# numbers on from the bound (the consumer skips the unused ones by the floor), and the store
# is written once per POSITION_LEASE events instead of on every push
POSITION_LEASE = 1024
# the retention a replicated consumer's producer keeps: the events after the consumer's newest
# replicated snapshot (mso.protocol.procedures.replication)
REPLICA_OWNER = "replica"
# a source's edge keeps the generation of its numbering as a note under its key and this
GEN_NOTE = "/gen/"


@dataclass
class OutChannel:
    """Producer side of one edge instance.

    It keeps every event from ``base`` on: the unacknowledged ones (from ``acked``), and before
    them any that a *retention* still holds. A retention (:meth:`retain`) keeps the events
    from a sequence number on, acknowledged or not, until its owner releases it: chain
    replication retains the events after a snapshot until the replica has acknowledged it, so
    a replacement can start from the replica plus their replay. Retained events do not count
    against the window (the consumer has them); they are bounded by their owner, and local to
    this channel: a relocation hands over the unacknowledged events only.

    Store and forward: events numbered but not sent yet (from ``sent``) wait while the consumer
    is out of reach, and go out, a window at a time, once it is back. Past the window and
    ``mem_limit`` bytes in memory, the newest events spill to ``store`` (the driver's durable
    log) and come back into memory as acks make room. The data plane applies the edge's bound
    and overflow policy (:mod:`mso.protocol.dataplane`); the counts of what it gave up are here.
    """

    window: int = 4096
    next_seq: int = 0
    acked: int = 0  # every seq below this is acknowledged
    waiting_since: float = 0.0  # when the oldest unacknowledged event started waiting
    # the consumer's output positions reported with the last ack (see AckGate)
    positions: dict[int, int] = field(default_factory=dict)
    store: SpillStore | None = None  # where events past the window and mem_limit spill
    key: str = ""  # this edge instance's name in the store
    mem_limit: int = 8 << 20  # bytes in memory past the window before events spill
    persist: bool = False  # a source's edge: a bound on its numbers is kept in the store
    # numbered from a guess: a replacement whose consumer was lost too and no ack said where
    # the edge stood; its numbers are not the lost consumer's (until a consumer acks one)
    guessed: bool = False
    # a guessed channel's consumer said where it stands, or took this numbering (a replacement
    # that asked): until then its events wait here (StoreAndForward.held), since a consumer
    # that survived out of reach would take them for what it has (fault seed 40939)
    confirmed: bool = False
    # the consumer's instance this channel fed went with its node (held failed): a restore
    # of it rewires this channel, or one that did not (it resumed a twin of this producer,
    # restored across a cut) left the consumer numbered in that twin's terms; until either
    # says where it stands, the events wait here (fault seed 118461)
    consumer_lost: bool = False
    asked_at: float = -1e18  # when the consumer was last asked where it stands
    # a merge's replacement: the first number it made itself, a new interleaving (-1: none)
    remade: int = -1
    # every event from this number on is new: made since its instance's restore by a source,
    # or of such events only (-1: not so). Positions of the edge past it that an earlier
    # instance made name other events (Restorer.activate, fault seed 266014)
    new_from: int = -1
    # a guess's start in its vertex's one input (-1: none): the input position its first
    # number (``origin``) was made from. Once a consumer takes the guess, the producer of that
    # input is told (an ack there with this position: Restorer._tell_taken), as it is of a
    # start that is known; a replacement of the vertex then numbers the replay as this one did
    made_from: int = -1
    # the generation of this edge's numbering: 0 is the deployment's; a numbering made anew
    # (from a guess, no ack's positions and no consumer's word) takes a fresh one, and the
    # channels, acks' positions and saved positions that follow it carry it: a consumer started
    # past marks of another numbering tells the two apart (Restorer.anchor, seed 105902)
    gen: int = 0
    # the generations of ``positions`` (those not 0)
    gens: dict[int, int] = field(default_factory=dict)

    HISTORY = 64  # acks whose positions are kept, to look one up at an exact position

    @property
    def unsure(self) -> bool:
        """Its numbers may not be its consumer's (a guess not confirmed, or a consumer lost
        since): its events wait until the consumer says where it stands."""
        return (self.guessed and not self.confirmed) or self.consumer_lost

    def __post_init__(self) -> None:
        self._unacked: deque[bytes] = deque()  # events from ``base`` on, in memory
        self.base = self.acked
        self.origin = self.next_seq  # the first number this channel made (or was handed)
        self.top = self.next_seq  # every event below this has been sent at least once
        self.sent = self.next_seq  # events from here on have not been sent yet
        self.mem_bytes = 0
        self.leased = 0  # the bound saved in the store (``persist``): no number reaches it
        self.spilled = 0  # the newest events, in the store
        self.stamps: deque[tuple[int, float]] = deque()  # (first seq, when it was numbered)
        self.retentions: dict[Hashable, int] = {}  # owner -> first seq it retains
        # what the edge's policies gave up, counted (reported in status, never silent)
        self.dropped = 0  # past the bound (overflow policy), or best effort out of reach
        self.superseded = 0  # keep_last: older events replaced by newer ones
        self.expired = 0  # lifespan: too old to deliver
        self.given_up = 0  # best effort: lost on the way, not sent again
        # events sent more than once (go-back-N, a replay into a replacement), and their
        # bytes: the radio a loss, an outage or a restore cost on this edge
        self.resent = 0
        self.resent_bytes = 0
        # its consumer was out of reach since the last send: what went out before may be
        # lost with the link (see StoreAndForward.back_in_reach)
        self.out_of_reach = False
        # ack position -> the positions that came with it: a vertex releasing a checkpoint
        # at exactly such a position passes them on upstream (transitive, see AckGate)
        self.history: dict[int, dict[int, int]] = {}
        self.history_gens: dict[int, dict[int, int]] = {}  # their generations (not 0)
        self.positions_at = self.acked  # the ack ``positions`` came with
        # go-back-N's backoff: times sent again since the clock last restarted otherwise
        self.retries = 0
        self._retried_at: float | None = None

    @property
    def sent(self) -> int:
        """Events from here on have not been sent yet (or are to be sent again: go-back)."""
        return self._sent

    @sent.setter
    def sent(self, value: int) -> None:
        self._sent = value
        self.top = max(self.top, value)

    def number_as(self, gen: int) -> None:
        """Take numbering ``gen`` (see ``gen``); a source's edge keeps it in the store, so
        that after a restart of this node's daemon it numbers on in the same one."""
        self.gen = gen
        if self.persist and self.store is not None:
            self.store.note(self.key + GEN_NOTE, "", gen)

    def note_positions(
        self, upto: int, positions: dict[int, int], gens: Mapping[int, int] | None = None
    ) -> None:
        """An ack up to ``upto`` came with the consumer's ``positions``. An ack with none (a
        consumer that does not know them yet, e.g. a replacement acking again what its
        producer's replay repeated) leaves those known at that position: a later restore of
        the consumer numbers its output from them (seed 1998)."""
        gens = {e: g for e, g in (gens or {}).items() if g and e in positions}
        if upto >= self.acked and (positions or upto > self.positions_at):
            self.positions, self.positions_at, self.gens = positions, upto, gens
            self._save_positions()
        if positions or upto not in self.history:
            self.history[upto] = positions
            self.history_gens[upto] = gens
        while len(self.history) > self.HISTORY:
            oldest = next(iter(self.history))
            del self.history[oldest]
            self.history_gens.pop(oldest, None)

    def _save_positions(self) -> None:
        """A source's edge holding its events in the store keeps the positions of its last
        ack there too: after a restart of this node's daemon, its consumer's replacement
        numbers what the replay makes as the lost one did (seed 1088)."""
        if self.persist and self.store is not None and self.spilled:
            self.store.save_positions(self.key, self.positions_at, self.positions, self.gens)

    @property
    def in_flight(self) -> int:
        return self.next_seq - self.acked

    def can_send(self) -> bool:
        return self.in_flight < self.window

    def push(self, payload: bytes, now: float = 0.0) -> int:
        """Number a new event and keep it until acknowledged; returns its sequence number."""
        return self.push_many([payload], now)

    @property
    def room(self) -> int:
        """How many more events the window admits now."""
        return self.window - (self.next_seq - self.acked)

    def push_many(self, payloads: list[bytes], now: float = 0.0) -> int:
        """Number and keep several events; returns the first one's sequence number."""
        seq = self.next_seq
        if seq == self.acked:
            self.waiting_since = now
        size = sum(map(len, payloads))
        if self.store is not None and (
            self.spilled
            or (seq - self.base >= self.window and self.mem_bytes + size > self.mem_limit)
        ):
            if self.persist:  # a source's edge: all in memory, or all in the store
                self.make_durable()
            self.store.append(self.key, seq, payloads)
            self.spilled += len(payloads)
        else:
            self._unacked.extend(payloads)
            self.mem_bytes += size
        if not self.stamps or now > self.stamps[-1][1] + 1e-3:
            self.stamps.append((seq, now))
        self.next_seq += len(payloads)
        if self.persist and self.store is not None and self.next_seq > self.leased:
            self.leased = self.next_seq + POSITION_LEASE
            self.store.save_position(self.key, self.leased)
        return seq

    def make_durable(self) -> None:
        """Move what is kept in memory into the store, and keep new events there too, so
        everything held survives a restart of this node's daemon (a held edge: its consumer
        is out of reach)."""
        if self.store is None or not self._unacked:
            return
        self.store.append(self.key, self.base, list(self._unacked))  # (before what it holds)
        self.spilled += len(self._unacked)
        self._unacked.clear()
        self.mem_bytes = 0
        self._save_positions()

    @classmethod
    def recover(
        cls,
        store: SpillStore,
        key: str,
        start: int,
        window: int,
        now: float,
        retain: Hashable | None = None,
    ) -> OutChannel | None:
        """A source's edge after this node's daemon restarted, numbering on. If it held its
        events in the store (its consumer was out of reach), they are all there, up to its
        last number: it keeps those from ``start`` (where the consumer stands) on. Else it
        numbers on from the saved bound, and the consumer skips by the frame's floor what
        it never got (the events in memory then, gone with the process; numbers never used).
        Held events its consumer had acknowledged (kept for a retention: ``retain`` names
        it again, else they are forgotten) come back acknowledged, with the output positions
        that ack brought; so do those past it when the consumer stands beyond it (its next
        ack lost), so that positions are known where the edge says it starts. None if
        nothing was saved under ``key``."""
        bound = store.position(key)
        if bound is None:
            return None
        span = store.span(key)
        saved = store.saved_positions(key)
        if span is not None and saved is not None and span[0] <= saved[0] < start <= span[1]:
            # the consumer acknowledged past the last ack whose positions were saved (that
            # ack lost with the link or the process): kept from the saved one, a replay to a
            # replacement of the consumer numbers what it makes as the lost one did; the
            # consumer drops what it has (seed 106785: numbered from its own consumer's
            # position instead, a forwarder's replacement sent 12 events twice)
            start = saved[0]
        if span is not None:  # held: everything it had, from ``span[0]`` on
            first, top = max(start, span[0]), max(start, span[1])
        else:
            first = top = max(start, bound)
        ch = cls(window, first, first, now, store=store, key=key, persist=True)
        store.trim(key, first)
        ch.next_seq = top
        ch.spilled = top - first
        ch.sent = first
        ch.stamps.append((first, now))
        ch.leased = max(top, bound)
        store.save_position(key, ch.leased)
        ch.gen = store.notes(key + GEN_NOTE).get("", 0)  # (the numbering it numbers on in)
        if saved is not None and first <= saved[0] <= top:  # its last ack, if it is kept
            at, ch.positions = saved
            ch.gens = store.saved_gens(key)
            ch.acked = ch.sent = ch.positions_at = at  # (what is kept before: retained)
            if retain is not None:
                ch.retentions[retain] = first
            else:
                ch._trim()
        return ch

    def on_ack(self, upto: int, now: float = 0.0) -> int:
        """Release events below ``upto``; returns how many were released (0 for a stale ack)."""
        if upto > self.next_seq:
            raise ValueError(f"ack for {upto} beyond the last event sent ({self.next_seq - 1})")
        released = max(0, upto - self.acked)
        self.acked += released
        if released:
            self.waiting_since = now
            self.guessed = False
            self._trim()
        return released

    def _trim(self) -> None:
        """Forget the events below both the ack and every retention."""
        keep = min(min(self.retentions.values(), default=self.acked), self.acked)
        n = keep - self.base
        if n <= 0:
            return
        in_memory = min(n, len(self._unacked))
        for _ in range(in_memory):
            self.mem_bytes -= len(self._unacked.popleft())
        self.spilled -= n - in_memory
        self.base = keep
        self.sent = max(self.sent, keep)
        while len(self.stamps) > 1 and self.stamps[1][0] <= keep:
            self.stamps.popleft()
        if self.store is not None and (self.spilled or n > in_memory):
            self.store.trim(self.key, keep + len(self._unacked))
            if not self.persist:  # (a source's edge reads what it spilled from the store
                self._refill()  # until it has drained: a restart loses no event in between)

    def _refill(self) -> None:
        """Bring the oldest spilled events back into memory while there is room."""
        assert self.store is not None
        while self.spilled and self.mem_bytes < self.mem_limit:
            first = self.base + len(self._unacked)
            back = self.store.ready(self.key, first, min(self.spilled, 256))
            if not back:
                break
            self._unacked.extend(back)
            self.mem_bytes += sum(map(len, back))
            self.spilled -= len(back)
            self.store.trim(self.key, first + len(back))

    def drop_front(self, upto: int, now: float) -> int:
        """Give up the events below ``upto`` as if acknowledged (an overflow policy or a
        lifespan did); the consumer skips them by the floor of the next frame. Returns how
        many were given up."""
        return self.on_ack(min(max(upto, self.acked), self.next_seq), now)

    @property
    def spill_bytes(self) -> int:
        return self.store.size(self.key) if self.spilled and self.store is not None else 0

    @property
    def kept_bytes(self) -> int:
        return self.mem_bytes + self.spill_bytes

    def age(self, now: float) -> float:
        """How long the oldest event kept has waited."""
        return now - self.stamps[0][1] if self.stamps and self.kept else 0.0

    def stamp(self, seq: int) -> float:
        """When ``seq`` was numbered (to the millisecond; the oldest kept if before)."""
        t = self.stamps[0][1] if self.stamps else 0.0
        for first, at in self.stamps:
            if first > seq:
                break
            t = at
        return t

    def overdue(self, now: float, timeout: float, cap: float | None = None) -> bool:
        """Events have waited with no ack progress long enough to send them again:
        ``timeout``, doubled for each time they were sent again since (up to ``cap``). Any
        restart of the clock (an ack's progress, a consumer back in reach, a replay asked
        for) starts the doubling over: a link that loses everything is not sent a window
        four times a second, and once acks progress a new loss is answered soon again."""
        if self.waiting_since != self._retried_at:
            self.retries = 0
        wait = timeout * 2 ** min(self.retries, 16)
        return self.in_flight > 0 and now - self.waiting_since >= min(wait, cap or wait)

    def retried(self, now: float) -> None:
        """What was overdue has been sent again (or given up): the clock starts again, and
        the next wait is twice as long (see :meth:`overdue`)."""
        self.waiting_since = self._retried_at = now
        self.retries += 1

    def unacked(self, start: int | None = None) -> tuple[int, list[bytes]]:
        """``(first seq, events)`` still unacknowledged from ``start`` (default: all)."""
        return self.events_from(self.acked if start is None else max(start, self.acked))

    def events_from(
        self, start: int, count: int | None = None, ready: bool = False
    ) -> tuple[int, list[bytes]]:
        """``(first seq, events)`` kept from ``start`` on (no earlier than ``base``), at most
        ``count`` of them; ``ready``: only the first of them the store has at hand (a drain:
        the rest is read off the loop, and sent when it is in)."""
        begin = max(start, self.base)
        end = self.next_seq if count is None else min(self.next_seq, begin + count)
        in_memory = self.base + len(self._unacked)
        out = (
            list(
                itertools.islice(self._unacked, begin - self.base, min(end, in_memory) - self.base)
            )
            if begin < in_memory
            else []
        )
        if end > in_memory and self.store is not None:
            frm = max(begin, in_memory)
            read = self.store.ready if ready else self.store.read
            out += read(self.key, frm, end - frm)
        return begin, out

    def unsent(self, limit: int) -> tuple[int, list[bytes]]:
        """The next events to send, within the window and at most ``limit``; they count as
        sent from now on."""
        end = min(self.next_seq, self.acked + self.window, self.sent + limit)
        first, events = self.events_from(self.sent, max(0, end - self.sent), ready=True)
        self.sent_again(events[: max(0, self.top - first)])
        self.sent = max(self.sent, first + len(events))
        return first, events

    def sent_again(self, events: list[bytes]) -> None:
        """Count ``events`` as sent once more (see ``resent``)."""
        self.resent += len(events)
        self.resent_bytes += sum(map(len, events))

    # -- retention: keep events past their ack until released ---------------------------------
    def retain(self, owner: Hashable, start: int) -> None:
        """Keep every event from ``start`` on, acknowledged or not, until ``owner`` releases
        it (:meth:`release`). ``start`` must still be kept (``base`` <= start <= next_seq):
        retain before acknowledging, e.g. at the snapshot's position. Retaining again moves the
        owner's retention (forward or back, within what is kept)."""
        if not self.base <= start <= self.next_seq:
            raise ValueError(
                f"cannot retain from {start}: events {self.base}..{self.next_seq - 1} are kept"
            )
        self.retentions[owner] = start
        self._trim()

    def release(self, owner: Hashable, upto: int | None = None) -> None:
        """``owner`` no longer needs the events below ``upto`` (None: any of them)."""
        if owner not in self.retentions:
            return
        if upto is None:
            del self.retentions[owner]
        else:
            self.retentions[owner] = max(self.retentions[owner], min(upto, self.next_seq))
        self._trim()

    def rewind(self, to: int) -> None:
        """Count the events from ``to`` on as unacknowledged again (they must still be kept):
        a replacement that starts from a replica's snapshot gets them resent until it
        acknowledges them itself."""
        if not self.base <= to <= self.acked:
            raise ValueError(f"cannot rewind to {to}: events {self.base}..{self.acked} are kept")
        self.acked = to

    def retained(self, owner: Hashable) -> tuple[int, list[bytes]] | None:
        """``(first seq, events)`` that ``owner`` retains (to replay them), or None."""
        start = self.retained_from(owner)
        return None if start is None else self.events_from(start)

    def retained_from(self, owner: Hashable) -> int | None:
        """The first sequence number ``owner`` retains, or None (no events read: what it
        retains may be far beyond memory, in the store)."""
        start = self.retentions.get(owner)
        return None if start is None else max(start, self.base)

    @property
    def kept(self) -> int:
        """Events held now: unacknowledged and retained."""
        return self.next_seq - self.base


@dataclass
class InChannel:
    """Consumer side of one edge instance."""

    expected: int = 0  # next sequence number to deliver
    processed: int = 0  # events below this are processed
    duplicates: int = 0
    gaps: int = 0
    _acked: int = 0
    # how far an ack may go: None = as far as processed (a sink); else set by the AckGate
    released: int | None = None
    positions: dict[int, int] = field(default_factory=dict)  # sent with the acks
    reack: bool = False  # a duplicate arrived: the producer missed an ack, send it again
    skipped: int = 0  # events the producer gave up before they arrived (see ``skip_to``)
    # QoS at the consumer (mso.protocol.delivery): events never fed, and the deadline
    superseded: int = 0  # keep_last: newer ones came before they were fed
    expired: int = 0  # lifespan: too old when their turn came
    deadline_missed: int = 0  # arrivals later than deadline_ms after the one before
    last_at: float | None = None  # when the last new event arrived
    # a replay from ``expected`` was asked for (a replacement started from a replica's
    # snapshot behind its producer's ack): frames sent before it (further on, with a floor
    # at that ack) are not a reason to skip ahead, and wait for the replay to come first
    awaiting_replay: bool = False
    # of a merge's output: the provenance of the last event it has from each of the merge's
    # inputs (mso.protocol.provenance); None when it cannot know (the channel was rebuilt
    # from positions, without them)
    marks: dict[int, tuple[int, int]] | None = None
    # started past its consumers' marks, not at a position it held (a fork's or merge's
    # replacement whose producer was lost too): until an event comes, a producer that numbers
    # from its acks' positions may start it there instead (Restorer.anchor)
    unheld: bool = False
    # where it was started past its consumers' marks (-1: not so): a guess, which a producer
    # that numbers anew overrides while nothing of it was taken (Restorer.anchor)
    past_marks: int = -1
    taken: bool = False  # an event of this numbering was taken (Restorer._follow)
    # the generation of the numbering it follows (OutChannel.gen), and of ``positions``
    gen: int = 0
    gens: dict[int, int] = field(default_factory=dict)
    # the generations of the numberings ``marks`` name (not 0), as its producer's frames say
    markgens: dict[int, int] = field(default_factory=dict)

    @classmethod
    def starting_at(
        cls,
        pos: int,
        gated: bool,
        marks: dict[int, tuple[int, int]] | None = None,
        gen: int = 0,
    ) -> InChannel:
        """A channel whose next event is ``pos`` of numbering ``gen``, everything before it
        taken and acknowledged (``gated``: its consumer has outputs, so acks are chained)."""
        return cls(
            expected=pos,
            processed=pos,
            _acked=pos,
            released=pos if gated else None,
            marks=marks,
            gen=gen,
        )

    def __post_init__(self) -> None:
        # (position, count): once ``processed`` reaches position, count events were skipped
        self._skips: deque[tuple[int, int]] = deque()

    def skip_to(self, floor: int) -> None:
        """The producer will never send anything below ``floor`` again (a parked chain
        dropped those events and counted them acknowledged): stop waiting for them. They count
        as processed once everything delivered before them is."""
        if floor <= self.expected:
            return
        n = floor - self.expected
        self.skipped += n
        if self.processed == self.expected:
            self.processed = floor
        else:
            self._skips.append((self.expected, n))
        self.expected = floor

    def accept(self, seq: int, events: list[bytes], floor: int = 0) -> list[bytes]:
        """The events of a batch starting at ``seq`` that are new and in order; ``floor`` is
        the producer's lowest position it can still send (see :meth:`skip_to`)."""
        if self.awaiting_replay:
            if seq > self.expected:  # sent before the producer went back (seed 2748)
                self.gaps += 1
                return []
            self.awaiting_replay = False
        self.unheld = False
        self.skip_to(floor)
        end = seq + len(events)
        if end <= self.expected:
            self.duplicates += len(events)
            self.reack = True
            return []
        if seq > self.expected:
            self.gaps += 1  # something before was lost: wait for the producer to resend
            return []
        fresh = events[self.expected - seq :]
        self.duplicates += self.expected - seq
        self.expected = end
        self.taken = True
        return fresh

    def mark_processed(self, n: int = 1) -> None:
        self.processed += n
        while self._skips and self._skips[0][0] == self.processed:
            self.processed += self._skips.popleft()[1]
        if self.processed > self.expected:
            raise ValueError("processed more events than were delivered")

    def ack_due(self) -> int | None:
        """The cumulative ack to send now, or None if nothing changed since the last one."""
        upto = self.processed if self.released is None else min(self.processed, self.released)
        if upto <= self._acked and not self.reack:
            return None
        self.reack = False
        self._acked = max(self._acked, upto)
        return self._acked


HOLD_INEXACT = 8  # checkpoints an ack may wait behind for positions known further down


@dataclass
class AckGate:
    """Chained acknowledgement for one vertex with outputs.

    A vertex acknowledges its inputs only once what it derived from them has been acknowledged
    downstream, so an event stays in its producer's replay buffer until it has left every node
    whose failure could lose it (upstream backup). Each processed batch leaves a checkpoint: the
    input positions it reached and the output positions it had produced by then; a checkpoint
    is released once every output has been acknowledged up to its positions. The ack upstream
    carries those output positions, plus, where an ack from downstream came at exactly such a
    position, the positions further down that came with it: a restore of several adjacent
    vertices then numbers each replacement's output as the lost instance did.
    """

    checkpoints: deque[tuple[dict[int, int], dict[int, int]]] = field(default_factory=deque)

    def record(self, inputs: dict[int, int], outputs: dict[int, int]) -> None:
        """After a batch: ``inputs`` edge -> processed, ``outputs`` edge -> next seq."""
        if self.checkpoints and self.checkpoints[-1][1] == outputs:
            self.checkpoints[-1][0].update(inputs)  # nothing new went out: widen the last one
        else:
            self.checkpoints.append((dict(inputs), dict(outputs)))

    def release(
        self,
        acked: Mapping[int, int],
        exact: Callable[[dict[int, int]], bool] | None = None,
    ) -> tuple[dict[int, int], dict[int, int]] | None:
        """Pop every checkpoint whose outputs are acknowledged (``acked``: edge -> acked up
        to); returns the input positions now safe to acknowledge and the output positions they
        correspond to, or None if none is.

        ``exact`` says whether the positions further down are known at a checkpoint's output
        positions (an ack from downstream came at exactly them). The ack goes up to the last
        checkpoint where they are, and waits for one behind at most :data:`HOLD_INEXACT`
        checkpoints: an ack whose positions miss an edge further down let a restore of the
        vertices below number that edge from its consumer's position, one event on (a lost
        ack, the next acking two batches at once: fault seed 60473)."""
        popped: list[tuple[dict[int, int], dict[int, int]]] = []
        while self.checkpoints:
            ins, outs = self.checkpoints[0]
            if any(acked.get(e, 0) < pos for e, pos in outs.items()):
                break
            popped.append(self.checkpoints.popleft())
        if not popped:
            return None
        upto = len(popped)
        if exact is not None and not exact(popped[-1][1]):
            upto = next((k for k in range(upto - 1, 0, -1) if exact(popped[k - 1][1])), 0)
            if upto == 0 and len(popped) >= HOLD_INEXACT:
                upto = len(popped)  # (a bound: acks never wait for long)
        self.checkpoints.extendleft(reversed(popped[upto:]))
        if upto == 0:
            return None
        inputs: dict[int, int] = {}
        for ins, _ in popped[:upto]:
            for e, pos in ins.items():
                inputs[e] = max(inputs.get(e, 0), pos)
        return inputs, popped[upto - 1][1]

    def to_wire(self) -> list[Any]:
        return [[ins, outs] for ins, outs in self.checkpoints]

    @classmethod
    def from_wire(cls, data: list[Any]) -> AckGate:
        gate = cls()
        for ins, outs in data:
            gate.checkpoints.append(
                (
                    {int(k): int(v) for k, v in ins.items()},
                    {int(k): int(v) for k, v in outs.items()},
                )
            )
        return gate
