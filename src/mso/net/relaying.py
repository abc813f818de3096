"""What a relay takes from one neighbour to pass on: a frame rate per class.

A frame a node forwards is checked like one of its own (its kind, a beat's size: :mod:`mso.net.tcp`)
and queued by class on the next link, where one neighbour's relayed frames may take only a share
of each queue (:mod:`mso.net.shaping`). A member could still keep a relay busy with a stream of
small control frames it addresses through it (50,000 invented ``NodeDown``\\s once froze an
overlay), so each neighbour also has a budget of relayed frames per class: a token bucket of
``rate`` frames a second holding up to ``burst_s`` seconds' worth. A frame past it is dropped
and counted (``frames_dropped_rate``). Data and markers have no such budget: the channels'
windows bound genuine data, and their queue share bounds the rest.

Sans-IO: ``now`` is passed in.
"""

from __future__ import annotations

from mso.net.base import CONTROL, HEARTBEAT

MAX_NEIGHBOURS = 4096  # budgets kept (the oldest forgotten first; a neighbour's outlives its
# connection, so that reconnecting does not refill it)


class RelayBudget:
    """Token buckets of relayed frames per (neighbour, class)."""

    def __init__(self, control_per_s: float, beats_per_s: float, burst_s: float = 2.0) -> None:
        self.rates = {CONTROL: control_per_s, HEARTBEAT: beats_per_s}
        self.burst_s = burst_s
        self._buckets: dict[tuple[str, int], tuple[float, float]] = {}  # -> (tokens, as of)

    def allow(self, neighbour: str, kind: int, now: float, cost: float = 1.0) -> bool:
        """Whether one more frame of ``kind`` from ``neighbour`` may be relayed now (``cost``:
        how many frames' worth it takes, at most a whole burst, so that any frame passes in
        time)."""
        rate = self.rates.get(kind)
        if rate is None:
            return True
        burst = rate * self.burst_s
        cost = min(cost, burst)
        tokens, at = self._buckets.get((neighbour, kind), (burst, now))
        tokens = min(burst, tokens + (now - at) * rate)
        if tokens < cost:
            self._buckets[(neighbour, kind)] = (tokens, now)
            return False
        if len(self._buckets) >= MAX_NEIGHBOURS and (neighbour, kind) not in self._buckets:
            del self._buckets[next(iter(self._buckets))]
        self._buckets[(neighbour, kind)] = (tokens - cost, now)
        return True
