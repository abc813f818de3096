"""Vertex code for bench/peer_dora.py: the source -> relay -> sink pipeline measured side by side
with dora-rs.

An event is ``[seq, t, pad]`` (a msgspec array-like Struct): ``seq`` numbers it at the source,
``t`` is ``time.perf_counter()`` there (CLOCK_MONOTONIC on Linux, so comparable across the node
processes of one host) and ``pad`` fills the encoded event to exactly the requested size. Both
numbers are float64 so the size does not depend on them. The dora-rs side of the benchmark
carries the same three fields in the same number of bytes and its sink does the same work.
"""

from __future__ import annotations

import math
import time
from typing import Any

import msgspec

from mso.benchmarks.common import SequenceCheck, percentile

HEAD = 21  # fixarray (1) + two float64 (9 + 9) + bin8 header (2)
TOP_GAPS = 8  # the largest gaps between arrivals kept (the one after a move or kill is among)


class Probe(msgspec.Struct, array_like=True):
    seq: float
    t: float
    pad: bytes


def probe_pad(size: int) -> int:
    """Pad length making ``msgpack(Probe(seq, t, pad))`` exactly ``size`` bytes."""
    n = size - HEAD
    if n > 255:
        n -= 1  # bin16 header
    if n < 0 or len(msgspec.msgpack.encode(Probe(0.0, 0.0, bytes(n)))) != size:
        raise ValueError(f"cannot make an event of exactly {size} bytes (at least {HEAD})")
    return n


class ProbeSource:
    """Numbers and stamps events of ``size`` encoded bytes."""

    def __init__(self, size: int = 38) -> None:
        self.pad = bytes(probe_pad(size))
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Probe:
        event = Probe(float(self.sent), time.perf_counter(), self.pad)
        self.sent += 1
        return event


class Relay:
    """Passes each event on untouched (the middle of the pipeline)."""

    def __call__(self, event: Probe) -> Probe:
        return event


class ProbeSink(SequenceCheck):
    """Latency of every event in a window that opens ``warmup_s`` after the first arrival and
    lasts ``window_s`` (at most ``cap`` kept); and, all along, the holes in the numbering and
    the largest gaps between arrivals with when each ended (``time.monotonic()``, the
    controller's clock), so the one after a move or a kill can be found."""

    def __init__(self, warmup_s: float = 1.0, window_s: float = 10.0, cap: int = 100_000) -> None:
        super().__init__()
        self.warmup_s = warmup_s
        self.window_s = window_s
        self.cap = int(cap)
        self.opens = math.inf
        self.closes = math.inf
        self.lat: list[float] = []
        self.missing = 0
        self.first = 0.0  # time.monotonic() of the first arrival
        self.last = 0.0
        self.gaps: list[tuple[float, float]] = []  # the TOP_GAPS largest: (gap, when it ended)

    def __call__(self, event: Probe) -> None:
        now = time.perf_counter()
        mono = time.monotonic()
        if self.count == 0:
            self.first = mono
            self.opens = now + self.warmup_s
            self.closes = self.opens + self.window_s
        elif len(self.gaps) < TOP_GAPS or mono - self.last > self.gaps[-1][0]:
            self.gaps.append((mono - self.last, mono))
            self.gaps.sort(reverse=True)
            del self.gaps[TOP_GAPS:]
        self.last = mono
        self.missing += self.see(int(event.seq))
        if self.opens <= now < self.closes and len(self.lat) < self.cap:
            self.lat.append(now - event.t)

    def stats(self) -> dict[str, Any]:
        done = time.perf_counter() >= self.closes
        out: dict[str, Any] = {
            "count": self.count,
            "next": self.next,
            "missing": self.missing,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "first": self.first,
            "gaps": [[gap * 1e3, ended] for gap, ended in self.gaps],
            "done": done,
        }
        if done and self.lat:
            out.update(
                window_events=len(self.lat),
                p50_us=percentile(self.lat, 50) * 1e6,
                p99_us=percentile(self.lat, 99) * 1e6,
            )
        return out
