"""Vertex code for bench/failure.py: a counting source, a pass-through and a gap-timing sink.

Node processes import it by its module path (``mso.benchmarks.vertices.failure:GapSink``). The
sink stamps every arrival with ``time.monotonic()`` -- CLOCK_MONOTONIC, the clock of the nodes'
and the controller's asyncio loops (``loop.time()``), all on one host -- so its gaps line up
with the controller's kill time and the nodes' failure records.
"""

from __future__ import annotations

import time
from typing import Any

import msgspec

TOP_GAPS = 5  # the largest inter-arrival gaps kept, to find the one around the kill
MISSING_CAP = 100_000  # holes remembered one by one; beyond that only counted


class Seq(msgspec.Struct, array_like=True, frozen=True):
    """One event: its number at the source."""

    seq: int


class CountingSource:
    """Numbers its events 0, 1, 2, ... (its own count, so it matches ``emitted``)."""

    def __init__(self) -> None:
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Seq:
        event = Seq(self.sent)
        self.sent += 1
        return event

    def stats(self) -> dict[str, int]:
        return {"sent": self.sent}


class PassThrough:
    """Stateless: what a replacement instance regenerates is exactly what was lost."""

    def __call__(self, event: Seq) -> Seq:
        return event


class GapSink:
    """Counts, checks order and times the gaps between arrivals (bounded memory).

    ``missing`` holds sequence numbers skipped and not (yet) filled, so ``lost`` for any prefix
    of the stream is ``missing`` plus what is beyond ``next``; a hole filled later counts as
    ``late``, an event seen twice as a repeat.
    """

    def __init__(self) -> None:
        self.count = 0
        self.next = 0
        self.repeats = 0
        self.out_of_order = 0  # arrivals ahead of their turn (they opened a hole)
        self.late = 0  # arrivals that filled a hole
        self.missing: set[int] = set()
        self.missing_overflow = 0
        self.first = 0.0
        self.first_seq = 0  # a replacement sink (after a rejoin) starts mid-stream
        self.last = 0.0
        self.gaps: list[tuple[float, float, float]] = []  # (gap, before, after), largest first

    def __call__(self, event: Seq) -> None:
        now = time.monotonic()
        if self.count:
            gap = now - self.last
            if len(self.gaps) < TOP_GAPS or gap > self.gaps[-1][0]:
                self.gaps.append((gap, self.last, now))
                self.gaps.sort(reverse=True)
                del self.gaps[TOP_GAPS:]
        else:
            self.first, self.first_seq = now, event.seq
        self.last = now
        self.count += 1
        seq = event.seq
        if seq < self.next:
            if seq in self.missing:
                self.missing.discard(seq)
                self.late += 1
            else:
                self.repeats += 1
        else:
            if seq > self.next:
                self.out_of_order += 1
                for hole in range(self.next, seq):
                    if len(self.missing) >= MISSING_CAP:
                        self.missing_overflow += seq - hole
                        break
                    self.missing.add(hole)
            self.next = seq + 1

    def stats(self) -> dict[str, Any]:
        top = self.gaps[0] if self.gaps else (0.0, 0.0, 0.0)
        return {
            "count": self.count,
            "next": self.next,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "late": self.late,
            "missing": len(self.missing) + self.missing_overflow,
            "first": self.first,
            "first_seq": self.first_seq,
            "last": self.last,
            "max_gap_ms": top[0] * 1e3,
            "gap_before": top[1],
            "gap_after": top[2],
            "gaps": [[before, after] for _, before, after in self.gaps],
        }
