"""Vertex code for bench/netns_bytes.py: a source of fixed-size events and a counting sink.
Node processes import it by module name; the benchmark puts bench/ on their PYTHONPATH and
allows the module (``MSO_ALLOW_CODE``)."""

from __future__ import annotations

import msgspec


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
