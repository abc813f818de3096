"""The sending side of one emulated link: bandwidth, delay, loss, control before data.

Shaping happens in the sender, as the user-space emulator's links have no kernel queue of their
own: frames are serialised at the link's bandwidth (a token-bucket-like ``next free`` time),
then held for the link's delay, then written. Loss drops data frames only: control frames carry
the procedures, which have no replay, and markers must arrive in their place among the data.
"""

from __future__ import annotations

import asyncio
import random
from collections import deque
from collections.abc import Callable
from typing import Protocol

from mso.net.base import CONTROL, DATA, Kind, LinkShape

# The event loop's timers have millisecond resolution (epoll), so a frame due within this slack
# leaves now instead of waiting a whole tick: bandwidth holds on average, with bursts of up to a
# millisecond's worth, and delays under a millisecond are not emulated (loopback adds ~50 µs).
TIMER_SLACK_S = 1e-3


class FrameWriter(Protocol):
    """Where a link's frames go: a connection that may push back (``paused``)."""

    @property
    def paused(self) -> bool: ...

    def write_frame(self, payload: bytes) -> None: ...


class Link:
    """Two queues (control leaves first) in front of a writer, shaped by a :class:`LinkShape`.

    ``seed`` makes emulated loss repeatable per (sender, receiver) pair; ``on_loss`` counts a
    frame the link dropped.
    """

    def __init__(
        self,
        writer: FrameWriter,
        shape: LinkShape,
        seed: int,
        loop: asyncio.AbstractEventLoop,
        on_loss: Callable[[], None] = lambda: None,
    ) -> None:
        self.writer = writer
        self.shape = shape
        self.loop = loop
        self.on_loss = on_loss
        self._rng = random.Random(seed)
        self._control: deque[bytes] = deque()
        self._data: deque[bytes] = deque()  # data and markers, in order
        self._next_free = 0.0
        self._in_air: deque[tuple[float, bytes]] = deque()
        self._timer: asyncio.TimerHandle | None = None

    def send(self, payload: bytes, kind: Kind) -> None:
        if kind == DATA and self.shape.loss and self._rng.random() < self.shape.loss:
            self.on_loss()
            return
        (self._control if kind == CONTROL else self._data).append(payload)
        self.pump()

    def pump(self) -> None:
        """Move queued frames onto the wire (or into the air) while the writer takes them."""
        bandwidth, delay_s = self.shape.bandwidth_mbps, self.shape.delay_ms / 1e3
        shaped = self.shape.shaped
        now = self.loop.time()
        while (self._control or self._data) and not self.writer.paused:
            if bandwidth is not None and self._next_free > now + TIMER_SLACK_S:
                self._arm(self._next_free - TIMER_SLACK_S)
                break
            payload = (self._control or self._data).popleft()
            if not shaped:
                self.writer.write_frame(payload)
                continue
            if bandwidth is not None:
                start = max(now, self._next_free)
                self._next_free = start + len(payload) * 8 / (bandwidth * 1e6)
                arrive = self._next_free + delay_s
            else:
                arrive = now + delay_s
            self._in_air.append((arrive, payload))
        self._deliver_due()

    def _deliver_due(self) -> None:
        now = self.loop.time()
        while self._in_air and self._in_air[0][0] <= now + TIMER_SLACK_S:
            self.writer.write_frame(self._in_air.popleft()[1])
        if self._in_air:
            self._arm(self._in_air[0][0] - TIMER_SLACK_S)

    def _arm(self, at: float) -> None:
        if self._timer is not None and self._timer.when() <= at:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self.loop.call_at(at, self._fire)

    def _fire(self) -> None:
        self._timer = None
        self.pump()

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
