"""Vertex code whose module takes long to import, as one using scipy does on a small CPU: the
sleep *is* the import cost under test, not synchronisation."""

from __future__ import annotations

import time

import msgspec

time.sleep(2.0)


class Num(msgspec.Struct, frozen=True):
    seq: int


class Source:
    def __call__(self, seq: int, now: float) -> Num:
        return Num(seq)


class Sink:
    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Num) -> None:
        self.count += 1

    def stats(self) -> dict[str, int]:
        return {"count": self.count}
