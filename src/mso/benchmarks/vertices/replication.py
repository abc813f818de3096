"""Vertex code for bench/replication.py: a stateful counter and a sink that checks its output.

The counter numbers the events it has processed (its state); the sink expects 0, 1, 2, ...
from it, as a run without failure gives, so a reset of the state, a repeat or a loss shows
there. The sink stamps arrivals with the module's clock (:func:`set_clock`: the simulator
passes its virtual one) and keeps the largest gap between them: the outage a failure caused.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import msgspec

_clock: Callable[[], float] = time.monotonic


def set_clock(clock: Callable[[], float]) -> None:
    """The clock new sinks stamp arrivals with."""
    global _clock
    _clock = clock


class Num(msgspec.Struct, array_like=True, frozen=True):
    n: int


class Source:
    def __call__(self, seq: int, now: float) -> Num:
        return Num(seq)


class Counter:
    """Stateful: its output is the number of events it processed before."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Num) -> Num:
        out = Num(self.count)
        self.count += 1
        return out

    def get_state(self) -> int:
        return self.count

    def set_state(self, state: int) -> None:
        self.count = int(state)


class CheckSink:
    """Counts what arrives, checks it is 0, 1, 2, ... and times the largest gap."""

    def __init__(self) -> None:
        self.clock = _clock
        self.count = 0
        self.next = 0
        self.repeats = 0  # a number again (the state went back: reset, or an event twice)
        self.skipped = 0  # numbers never seen (events counted but their output lost)
        self.resets = 0  # times the numbers went back (the state restarted)
        self._back = False
        self.last = 0.0
        self.gap = (0.0, 0.0, 0.0)  # (largest gap, before, after)

    def __call__(self, event: Num) -> None:
        now = self.clock()
        if self.count and now - self.last > self.gap[0]:
            self.gap = (now - self.last, self.last, now)
        self.last = now
        self.count += 1
        if event.n < self.next:
            self.repeats += 1
            self.resets += not self._back
            self._back = True
        else:
            self._back = False
            self.skipped += event.n - self.next
            self.next = event.n + 1

    def stats(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "next": self.next,
            "repeats": self.repeats,
            "skipped": self.skipped,
            "resets": self.resets,
            "gap_ms": round(self.gap[0] * 1e3, 3),
            "gap_before": self.gap[1],
            "gap_after": self.gap[2],
        }
