"""The vertex code of Table 1's measurement app (``beats``, see :mod:`mso.benchmarks.table1`):
a numbered source that a file pauses, a stateless forwarder, a relay whose counter must move with
it, and a sink that checks order and relay state and keeps the wall time of recent arrivals.
Node processes import it by ``mso.benchmarks.vertices.table1:GapSink`` ...; kept apart from the
benchmark so a node's import pulls in no emulator or client code.
"""

from __future__ import annotations

import os
import time
from collections import deque
from typing import Any

import msgspec

from mso.benchmarks.common import SequenceCheck


class Beat(msgspec.Struct, array_like=True, frozen=True):
    """One event of the measurement app: its number, and the relay's count when it passed."""

    seq: int
    sent_at: float
    relay: int = -1


class BeatSource:
    """Numbers its events from 0; emits nothing while ``pause_file`` exists."""

    def __init__(self, pause_file: str = "") -> None:
        self.pause_file = pause_file
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Beat | None:
        if self.pause_file and os.path.exists(self.pause_file):
            return None
        event = Beat(self.sent, time.time())
        self.sent += 1
        return event

    def stats(self) -> dict[str, int]:
        return {"sent": self.sent}


class Forward:
    def __call__(self, event: Beat) -> Beat:
        return event


class Relay:
    """Stateful: stamps how many events it has processed. Its state must move with it."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Beat) -> Beat:
        out = Beat(event.seq, event.sent_at, self.count)
        self.count += 1
        return out

    def get_state(self) -> int:
        return self.count

    def set_state(self, state: int) -> None:
        self.count = int(state)


class GapSink(SequenceCheck):
    """Checks order and relay state; keeps the wall time of the last ``history`` arrivals."""

    def __init__(self, history: int = 600) -> None:
        super().__init__()
        self.relay_mismatch = 0
        self.first = 0.0
        self.last = 0.0
        self.max_gap = 0.0
        self.arrivals: deque[float] = deque(maxlen=history)

    def __call__(self, event: Beat) -> None:
        now = time.time()
        if self.count:
            self.max_gap = max(self.max_gap, now - self.last)
        else:
            self.first = now
        self.last = now
        self.arrivals.append(now)
        self.see(event.seq)
        if event.relay != event.seq:
            self.relay_mismatch += 1

    def stats(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "next": self.next,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "relay_mismatch": self.relay_mismatch,
            "first": self.first,
            "last": self.last,
            "max_gap_ms": self.max_gap * 1e3,
            "arrivals": list(self.arrivals),
        }
