"""Holding control frames while routes converge: the one implementation every driver uses.

After a link breaks or a node fails, the nodes on a path learn the new routes a moment apart
(babeld takes 1.6-3 s; the emulator pushes routes after ``--convergence``). A probe sent by the
first node to learn would otherwise die at the next, still stale, hop and wait for a 1 s step
retry. So a control or marker frame with no usable next hop waits up to :data:`ROUTE_WAIT_S`
for the routes to change, then is given up. Data frames (events, acks) are never held: the
channels' acks and go-back-N replay recover them, and holding them would only grow memory.
(Heartbeats wait: the one a newly reachable node is sent tells it this node's incarnation.)
What waits is bounded by count and by bytes.

:class:`RouteWait` is sans-IO: it never reads a clock (``now`` is passed in) and never sends
(``release`` is given a send function), so the asyncio driver and the virtual-time simulator
hold frames by the very same rules, and the tests can drive it without sleeping.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from typing import Generic, NamedTuple, TypeVar

from mso.net.base import DATA, Kind

ROUTE_WAIT_S = 1.0
"""How long a control or marker frame waits for a route before it is given up."""
MAX_AWAITING = 1_000
"""At most this many frames wait at once; more are given up (a bound on memory)."""
MAX_AWAITING_BYTES = 32 << 20
"""And at most this many bytes of them (with a ``size`` function): 1,000 frames of 16 MiB
would be 16 GB."""

T = TypeVar("T")


class Waiting(NamedTuple, Generic[T]):
    deadline: float
    dst: str
    item: T
    kind: Kind


class RouteWait(Generic[T]):
    """Frames (any ``T``: bytes, a message, a tuple) waiting for a next hop toward ``dst``.

    Every frame it refuses or gives up on is counted in :attr:`dropped` and passed to
    ``on_drop``. Deadlines are ``now + wait_s`` at the time a frame is held, so with a
    monotonic ``now`` the oldest frame always expires first.
    """

    def __init__(
        self,
        wait_s: float | None = None,
        limit: int = MAX_AWAITING,
        on_drop: Callable[[T], None] | None = None,
        size: Callable[[T], int] | None = None,
        limit_bytes: int = MAX_AWAITING_BYTES,
    ) -> None:
        # the module's constant is read here, not at definition, so tests can shorten it
        self.wait_s = ROUTE_WAIT_S if wait_s is None else wait_s
        self.limit = limit
        self.on_drop = on_drop
        self.dropped = 0
        self._waiting: deque[Waiting[T]] = deque()
        self.size = size or (lambda item: 0)
        self.limit_bytes = limit_bytes
        self.bytes = 0

    def __len__(self) -> int:
        return len(self._waiting)

    def __iter__(self) -> Iterator[Waiting[T]]:
        return iter(self._waiting)

    def _drop(self, item: T) -> None:
        self.dropped += 1
        if self.on_drop is not None:
            self.on_drop(item)

    def expire(self, now: float) -> int:
        """Give up every frame whose deadline has passed; returns how many."""
        n = 0
        while self._waiting and self._waiting[0].deadline < now:
            item = self._waiting.popleft().item
            self.bytes -= self.size(item)
            self._drop(item)
            n += 1
        return n

    def hold(self, dst: str, item: T, kind: Kind, now: float) -> bool:
        """Keep a frame that found no next hop; False (and dropped) for a data frame or when
        :attr:`limit` frames or :attr:`limit_bytes` bytes already wait."""
        self.expire(now)
        size = self.size(item)
        full = len(self._waiting) >= self.limit or self.bytes + size > self.limit_bytes
        if kind == DATA or full:
            self._drop(item)
            return False
        self._waiting.append(Waiting(now + self.wait_s, dst, item, kind))
        self.bytes += size
        return True

    def release(self, now: float, send: Callable[[str, T, Kind], bool]) -> int:
        """The routes changed: offer every waiting frame to ``send(dst, item, kind)``, which
        returns False when there is still no next hop (the frame keeps waiting). Expired frames
        are given up. Returns how many frames left."""
        waiting, self._waiting = self._waiting, deque()
        sent = 0
        for w in waiting:
            if w.deadline < now:
                self.bytes -= self.size(w.item)
                self._drop(w.item)
            elif send(w.dst, w.item, w.kind):
                self.bytes -= self.size(w.item)
                sent += 1
            else:
                self._waiting.append(w)
        return sent

    def next_deadline(self) -> float | None:
        """When the oldest frame expires (for a driver that wants to expire on a timer)."""
        return self._waiting[0].deadline if self._waiting else None
