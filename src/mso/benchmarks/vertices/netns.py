"""Vertex code for bench/netns_bytes.py and netns_routes.py: a source of fixed-size events, a
counting sink, and a gap-timing sink. Node processes import it by its module path
(``mso.benchmarks.vertices.netns:BlobSource``)."""

from __future__ import annotations

import msgspec

from mso.benchmarks.common import SequenceCheck


class Blob(msgspec.Struct, array_like=True, frozen=True):
    seq: int
    pad: bytes


class BlobSource:
    def __init__(self, size: int = 1200) -> None:
        self.pad = b"x" * size
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Blob:
        self.sent += 1
        return Blob(self.sent - 1, self.pad)


class CountingSink:
    def __init__(self) -> None:
        self.count = 0
        self.bytes = 0

    def __call__(self, event: Blob) -> None:
        self.count += 1
        self.bytes += len(event.pad)

    def stats(self) -> dict[str, int]:
        return {"count": self.count, "bytes": self.bytes}


class Beat(msgspec.Struct, array_like=True, frozen=True):
    seq: int


class BeatSource:
    def __init__(self) -> None:
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Beat:
        self.sent += 1
        return Beat(self.sent - 1)


class GapTimer(SequenceCheck):
    """Times every inter-arrival gap over ``min_gap_s`` (CLOCK_MONOTONIC, the clock of the
    controller's loop): ``(start, end)`` of each, the last 100; and counts order violations."""

    def __init__(self, min_gap_s: float = 0.05) -> None:
        super().__init__()
        self.min_gap_s = min_gap_s
        self.last: float | None = None
        self.gaps: list[tuple[float, float]] = []

    def __call__(self, event: Beat) -> None:
        import time

        now = time.monotonic()
        if self.last is not None and now - self.last > self.min_gap_s:
            self.gaps.append((self.last, now))
            del self.gaps[:-100]
        self.last = now
        self.see(event.seq)

    def stats(self) -> dict[str, object]:
        return {
            "count": self.count,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "gaps": [list(g) for g in self.gaps],
        }
