"""Vertices of the ROS 2 benchmark (bench/ros2.py); the nodes import them (``mso[ros2]``)."""

from __future__ import annotations

import time
from collections import deque
from typing import Any

MAX_AGES = 4096  # ages kept for stats(): a run of minutes at 2 Hz, bounded


class Stale:
    """A slow consumer of camera frames: ``delay_s`` a frame (0.5: a 2 Hz consumer), noting how
    old each frame is when its turn comes (now minus the camera's ``header.stamp``, the wall
    clock: the camera and the nodes share this machine's)."""

    def __init__(self, delay_s: float = 0.5) -> None:
        self.delay_s = float(delay_s)
        self.ages: deque[tuple[float, float]] = deque(maxlen=MAX_AGES)  # (when, age s)
        self.count = 0

    def __call__(self, event: Any) -> None:
        now = time.time()
        stamp = event.header.stamp
        self.ages.append((round(now, 3), round(now - (stamp.sec + stamp.nanosec / 1e9), 4)))
        self.count += 1
        time.sleep(self.delay_s)

    def stats(self) -> dict[str, Any]:
        return {"count": self.count, "ages": [list(a) for a in self.ages]}


class Arrivals:
    """A sink timing a replay against its recording: for each message, how late it arrived
    against the first one's arrival plus its recorded offset over ``rate`` (a bag replayed at
    10x: offsets / 10)."""

    def __init__(self, rate: float = 1.0) -> None:
        self.rate = float(rate)
        self.count = 0
        self.first: tuple[float, float] | None = None  # (arrival, stamp) of the first, s
        self.last = 0.0
        self.lateness: list[float] = []  # s, one a message (10,000 floats for the benchmark)

    def __call__(self, event: Any) -> None:
        now = time.time()
        stamp = event.header.stamp.sec + event.header.stamp.nanosec / 1e9
        if self.first is None:
            self.first = (now, stamp)
        self.lateness.append(now - self.first[0] - (stamp - self.first[1]) / self.rate)
        self.count += 1
        self.last = now

    def stats(self) -> dict[str, Any]:
        late = sorted(self.lateness)
        return {
            "count": self.count,
            "span_s": round(self.last - self.first[0], 3) if self.first else 0.0,
            "late_ms": {q: _ms(late, f) for q, f in (("p50", 0.5), ("p99", 0.99), ("max", 1.0))},
        }


def _ms(ordered: list[float], q: float) -> float | None:
    """The ``q`` quantile of seconds, in ms."""
    if not ordered:
        return None
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1e3, 3)
