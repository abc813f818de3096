"""Vertex code for the executor benchmarks (bench/heavy.py, slowsink.py, rates.py).

Node processes import it by its module path (``mso.benchmarks.vertices.executor:Burn``). It
imports nothing heavy, because the nodes import it while they deploy. Sinks stamp arrivals with
``time.monotonic()``, the clock of every node's and the controller's event loop on this host.
"""

from __future__ import annotations

import time
from typing import Any

import msgspec

from mso.benchmarks.common import SequenceCheck


class Seq(msgspec.Struct, array_like=True, frozen=True):
    """One event: its number at the source, and when the source made it."""

    seq: int
    t: float = 0.0


class Counting:
    """A rated source numbering its events 0, 1, 2, ... (``limit``: then nothing more)."""

    def __init__(self, limit: int = 0) -> None:
        self.sent = 0
        self.limit = limit

    def __call__(self, seq: int, now: float) -> Seq | None:
        if self.limit and self.sent >= self.limit:
            return None
        self.sent += 1
        return Seq(self.sent - 1, time.monotonic())

    def stats(self) -> dict[str, int]:
        return {"sent": self.sent}

    def get_state(self) -> int:
        return self.sent

    def set_state(self, state: int) -> None:
        self.sent = state


class Burn:
    """Pure-Python CPU per event: a busy loop until this thread has used ``cpu_s`` of CPU
    (``work``: a fixed number of loop rounds instead, for throughput). Keeps a count as state,
    so a relocation that lost or repeated events would show."""

    def __init__(self, cpu_s: float = 0.0, work: int = 0) -> None:
        self.cpu_s = cpu_s
        self.work = work
        self.done = 0

    def __call__(self, event: Seq) -> Seq:
        x = 0
        if self.work:
            for i in range(self.work):
                x ^= i * i
        else:
            end = time.thread_time() + self.cpu_s
            while time.thread_time() < end:
                for i in range(1000):
                    x ^= i * i
        self.done += 1
        return event

    def stats(self) -> dict[str, int]:
        return {"done": self.done}

    def get_state(self) -> int:
        return self.done

    def set_state(self, state: int) -> None:
        self.done = state


class Checker(SequenceCheck):
    """A sink that checks order and counts; ``delay_s`` per event (a sleep: a slow device or
    disk, not CPU). Its last arrival time and seq, read twice, give the rate between them."""

    def __init__(self, delay_s: float = 0.0) -> None:
        super().__init__()
        self.delay_s = delay_s
        self.missing = 0
        self.first_t = 0.0
        self.first_seq = -1
        self.last_t = 0.0
        self.last_seq = -1
        self.latency_max = 0.0

    def __call__(self, event: Seq) -> None:
        if self.delay_s:
            time.sleep(self.delay_s)
        now = time.monotonic()
        if self.count == 0:
            self.first_t, self.first_seq = now, event.seq
        self.missing += self.see(event.seq)
        self.last_t, self.last_seq = now, event.seq
        if event.t:
            self.latency_max = max(self.latency_max, now - event.t)

    def stats(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "next": self.next,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "missing": self.missing,
            "first_t": self.first_t,
            "first_seq": self.first_seq,
            "last_t": self.last_t,
            "last_seq": self.last_seq,
            "latency_max_s": self.latency_max,
        }
