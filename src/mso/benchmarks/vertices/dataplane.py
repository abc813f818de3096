"""Vertex code for bench/dataplane.py and bench/memory.py.

Node processes import it by its module path (``mso.benchmarks.vertices.dataplane:StampSource``),
allowed by default like all of ``mso.benchmarks``. The bare-TCP baseline of
bench/dataplane.py uses the very same event type and sink, so both sides do the same per-event
work.

An event is ``[t, pad]`` (a msgspec array-like Struct): ``t`` is ``time.perf_counter()`` at the
source (CLOCK_MONOTONIC on Linux, so comparable across processes) and ``pad`` fills the encoded
event to exactly the requested size (``pad_len``).
"""

from __future__ import annotations

import math
import time
from array import array
from typing import Any

import msgspec


class Stamped(msgspec.Struct, array_like=True):
    t: float
    pad: bytes


def pad_len(size: int) -> int:
    """Pad length making ``msgpack(Stamped(t, pad))`` exactly ``size`` bytes.

    fixarray (1) + float64 (9) + bin8 header (2) or bin16 header (3) + pad.
    """
    n = size - 12
    if n > 255:
        n = size - 13
    if n < 0 or len(msgspec.msgpack.encode(Stamped(0.0, bytes(n)))) != size:
        raise ValueError(f"cannot make an event of exactly {size} bytes")
    return n


class StampSource:
    """Emits stamped events of ``size`` encoded bytes (as fast as it is called)."""

    def __init__(self, size: int = 38) -> None:
        self.pad = bytes(pad_len(size))

    def __call__(self, seq: int, now: float) -> Stamped:
        return Stamped(time.perf_counter(), self.pad)


def _percentile(s: list[float], q: float) -> float:
    if not s:
        return math.nan
    pos = (len(s) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


class LatencySink:
    """Per-event latency and throughput over a window that opens ``warmup_s`` after the first
    event and lasts ``window_s``. Latencies of every ``stride``-th event in the window are kept
    (at most ``cap``: a bounded reservoir); ``stats()`` summarises them once the window closed.
    """

    def __init__(
        self, warmup_s: float = 1.0, window_s: float = 2.0, stride: int = 7, cap: int = 200_000
    ) -> None:
        self.warmup_s = warmup_s
        self.window_s = window_s
        self.stride = max(1, int(stride))
        self.cap = int(cap)
        self.count = 0
        self.opens = math.inf
        self.closes = math.inf
        self.win_count = 0
        self.win_first = 0.0
        self.win_last = 0.0
        self.lat: array[float] = array("d")
        self._summary: dict[str, Any] | None = None

    def __call__(self, event: Stamped) -> None:
        now = time.perf_counter()
        self.count += 1
        if now < self.opens:
            if self.count == 1:
                self.opens = now + self.warmup_s
                self.closes = self.opens + self.window_s
            return
        if now >= self.closes:
            return
        n = self.win_count = self.win_count + 1
        if n == 1:
            self.win_first = now
        self.win_last = now
        if n % self.stride == 0 and len(self.lat) < self.cap:
            self.lat.append(now - event.t)

    def done(self) -> bool:
        return time.perf_counter() >= self.closes

    def stats(self) -> dict[str, Any]:
        if not self.done():
            return {"count": self.count, "done": False}
        if self._summary is None:
            s = sorted(self.lat)
            span = self.win_last - self.win_first
            self._summary = {
                "done": True,
                "window_events": self.win_count,
                "window_s": span,
                "events_per_s": (self.win_count - 1) / span if span > 0 else 0.0,
                "latency_n": len(s),
                "latency_mean_us": (sum(s) / len(s) * 1e6) if s else math.nan,
                "latency_p50_us": _percentile(s, 50) * 1e6,
                "latency_p99_us": _percentile(s, 99) * 1e6,
                "latency_max_us": (s[-1] * 1e6) if s else math.nan,
            }
        return {"count": self.count, **self._summary}


class IdleSource:
    """A low-rate source for bench/memory.py: a small stamped event."""

    def __init__(self, size: int = 38) -> None:
        self.pad = bytes(pad_len(size))

    def __call__(self, seq: int, now: float) -> Stamped:
        return Stamped(time.perf_counter(), self.pad)


class CountSink:
    """A sink for bench/memory.py that only counts."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Stamped) -> None:
        self.count += 1

    def stats(self) -> dict[str, int]:
        return {"count": self.count}
