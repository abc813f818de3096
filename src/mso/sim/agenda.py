"""The simulator's agenda: events in time order, those due at one moment in the order they
were put in -- the order of a heap of ``(at, sequence number, ...)`` entries, without its
comparisons.

At scale nearly every event falls on a moment shared with hundreds of others: every node
starts at 0 with the same beat and monitor periods, so its ticks (and their beats' arrivals)
coincide with every other node's, and of 23,000 events a simulated second at 1,000 nodes all
but 2% came at the same time as the one before. A heap orders them by comparing tuples whose
times tie, about 12 levels deep per pop (6% of a 1,000-node run); here a heap holds only the
distinct moments, each with a queue of its events.
"""

from __future__ import annotations

import heapq
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class Agenda(Generic[T]):
    """Items due at times: :meth:`pop` gives the earliest, ties in the order put in
    (first in, first out), whatever time is put in meanwhile (one earlier than the last
    popped comes next, as from a heap)."""

    __slots__ = ("_due", "_times")

    def __init__(self) -> None:
        self._times: list[float] = []  # a heap of the moments that have items due
        self._due: dict[float, deque[T]] = {}  # moment -> its items, in the order put in

    def __len__(self) -> int:
        return sum(map(len, self._due.values()))

    def __bool__(self) -> bool:
        return bool(self._times)

    def push(self, at: float, item: T) -> None:
        due = self._due.get(at)
        if due is None:
            self._due[at] = deque((item,))
            heapq.heappush(self._times, at)
        else:
            due.append(item)

    def next_at(self) -> float | None:
        """When the earliest item is due (None: nothing is)."""
        return self._times[0] if self._times else None

    def pop(self, until: float) -> tuple[float, T] | None:
        """The earliest item and its time, if due at ``until`` or before (else None)."""
        times = self._times
        if not times or times[0] > until:
            return None
        at = times[0]
        due = self._due[at]
        item = due.popleft()
        if not due:
            heapq.heappop(times)
            del self._due[at]
        return at, item
