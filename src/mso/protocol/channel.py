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

from collections import deque
from dataclasses import dataclass


@dataclass
class OutChannel:
    """Producer side of one edge instance."""

    window: int = 4096
    next_seq: int = 0
    acked: int = 0  # every seq below this is acknowledged
    waiting_since: float = 0.0  # when the oldest unacknowledged event started waiting

    def __post_init__(self) -> None:
        self._unacked: deque[bytes] = deque()

    @property
    def in_flight(self) -> int:
        return self.next_seq - self.acked

    def can_send(self) -> bool:
        return self.in_flight < self.window

    def push(self, payload: bytes, now: float = 0.0) -> int:
        """Number a new event and keep it until acknowledged; returns its sequence number."""
        seq = self.next_seq
        if seq == self.acked:
            self.waiting_since = now
        self._unacked.append(payload)
        self.next_seq += 1
        return seq

    @property
    def room(self) -> int:
        """How many more events the window admits now."""
        return self.window - (self.next_seq - self.acked)

    def push_many(self, payloads: list[bytes], now: float = 0.0) -> int:
        """Number and keep several events; returns the first one's sequence number."""
        seq = self.next_seq
        if seq == self.acked:
            self.waiting_since = now
        self._unacked.extend(payloads)
        self.next_seq += len(payloads)
        return seq

    def on_ack(self, upto: int, now: float = 0.0) -> int:
        """Release events below ``upto``; returns how many were released (0 for a stale ack)."""
        if upto > self.next_seq:
            raise ValueError(f"ack for {upto} beyond the last event sent ({self.next_seq - 1})")
        released = max(0, upto - self.acked)
        for _ in range(released):
            self._unacked.popleft()
        self.acked += released
        if released:
            self.waiting_since = now
        return released

    def overdue(self, now: float, timeout: float) -> bool:
        """Events have waited ``timeout`` with no ack progress: time to send them again."""
        return self.in_flight > 0 and now - self.waiting_since >= timeout

    def unacked(self, start: int | None = None) -> tuple[int, list[bytes]]:
        """``(first seq, events)`` still unacknowledged from ``start`` (default: all)."""
        begin = self.acked if start is None else max(start, self.acked)
        skip = begin - self.acked
        return begin, [p for i, p in enumerate(self._unacked) if i >= skip]


@dataclass
class InChannel:
    """Consumer side of one edge instance."""

    expected: int = 0  # next sequence number to deliver
    processed: int = 0  # events below this are processed (what an ack reports)
    duplicates: int = 0
    gaps: int = 0
    _acked: int = 0

    def accept(self, seq: int, events: list[bytes]) -> list[bytes]:
        """The events of a batch starting at ``seq`` that are new and in order."""
        end = seq + len(events)
        if end <= self.expected:
            self.duplicates += len(events)
            return []
        if seq > self.expected:
            self.gaps += 1  # something before was lost: wait for the producer to resend
            return []
        fresh = events[self.expected - seq :]
        self.duplicates += self.expected - seq
        self.expected = end
        return fresh

    def mark_processed(self, n: int = 1) -> None:
        self.processed += n
        if self.processed > self.expected:
            raise ValueError("processed more events than were delivered")

    def ack_due(self) -> int | None:
        """The cumulative ack to send now, or None if nothing changed since the last one."""
        if self.processed == self._acked:
            return None
        self._acked = self.processed
        return self.processed
