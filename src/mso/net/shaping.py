"""The sending side of one link: a bounded queue per class, heartbeats first; and on an
emulated link bandwidth, delay and loss.

Each class of frame has its own queue, bounded in bytes, and they leave in this order:
heartbeats, control, then data and markers (in order with each other). A relay once queued
every frame it forwarded in one unbounded control queue, ahead of its own heartbeats: 20 x 8
MiB control frames through it had three nodes declared failed. Now a beat waits for at most
the one frame already on its way, and a class whose queue is full drops what comes next
(counted, ``frames_dropped_queue``), leaving the other classes alone. A frame always fits an
empty queue, so no frame the wire allows is refused for its size alone. The frames relayed for
one neighbour may take only a share of each queue (``relayed_share``): a member streaming
frames through a relay no longer fills the queue the others' frames wait in. And the frames
relayed for all neighbours together take at most ``relayed_total`` of it, shared fairly
among the neighbours whose frames wait (each at most that over their number; a neighbour's
first frame always fits): two captured neighbours once filled a queue between them, and
still the node's own frames have the rest.

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
from dataclasses import dataclass
from typing import Protocol

from mso.net.base import DATA, HEARTBEAT, MARKER, Kind, LinkShape

# The event loop's timers have millisecond resolution (epoll), so a frame due within this slack
# leaves now instead of waiting a whole tick: bandwidth holds on average, with bursts of up to a
# millisecond's worth, and delays under a millisecond are not emulated (loopback adds ~50 µs).
TIMER_SLACK_S = 1e-3


@dataclass(frozen=True)
class QueueBounds:
    """Bytes each class may have queued on one link (a frame always fits an empty queue)."""

    heartbeat: int = 1 << 20
    control: int = 64 << 20  # a deploy announces a 4 MiB document to every node behind a link
    data: int = 32 << 20  # the channels' windows keep genuine data far below this
    # markers go past a full data queue by up to this much: a data frame dropped is resent
    # (go-back-N), a marker is not, and without it a relocation would wait for its deadline
    marker_slack: int = 1 << 20
    # a neighbour's frames this node relays may take at most this share of a class's queue
    # (its first always fits), so one member cannot fill a link it relays through
    relayed_share: float = 0.5
    # all neighbours' relayed frames together, split evenly among those with frames queued
    relayed_total: float = 0.75


class _Queue:
    """One class's frames, with their bytes, and the bytes each relayed neighbour's take."""

    def __init__(self, bound: int, share: int, total: int | None = None) -> None:
        self.bound = bound
        self.share = share  # bytes one relayed neighbour's frames may take
        self.total = bound if total is None else total  # bytes all relayed frames may take
        self.frames: deque[tuple[bytes, str | None]] = deque()
        self.bytes = 0
        self.relayed: dict[str, int] = {}
        self.relayed_bytes = 0

    def put(self, payload: bytes, slack: int = 0, via: str | None = None) -> bool:
        if self.frames and self.bytes + len(payload) > self.bound + slack:
            return False
        if via is not None:
            held = self.relayed.get(via, 0)
            if held:  # (a neighbour's first frame always fits)
                fair = self.total // (len(self.relayed) or 1)  # among those with frames here
                if held + len(payload) > min(self.share, fair):
                    return False
                if self.relayed_bytes + len(payload) > self.total:
                    return False
            self.relayed[via] = held + len(payload)
            self.relayed_bytes += len(payload)
        self.frames.append((payload, via))
        self.bytes += len(payload)
        return True

    def take(self) -> bytes:
        payload, via = self.frames.popleft()
        self.bytes -= len(payload)
        if via is not None:
            self.relayed_bytes -= len(payload)
            left = self.relayed[via] - len(payload)
            if left:
                self.relayed[via] = left
            else:
                del self.relayed[via]
        return payload


class FrameWriter(Protocol):
    """Where a link's frames go: a connection that may push back (``paused``)."""

    @property
    def paused(self) -> bool: ...

    def write_frame(self, payload: bytes) -> None: ...


class Link:
    """Three bounded queues (heartbeats, control, data: in that order) in front of a writer,
    shaped by a :class:`LinkShape`.

    ``seed`` makes emulated loss repeatable per (sender, receiver) pair; ``on_loss`` counts a
    frame the link dropped, ``on_full`` one its class's queue had no room for.
    """

    def __init__(
        self,
        writer: FrameWriter,
        shape: LinkShape,
        seed: int,
        loop: asyncio.AbstractEventLoop,
        on_loss: Callable[[], None] = lambda: None,
        bounds: QueueBounds | None = None,
        on_full: Callable[[], None] = lambda: None,
    ) -> None:
        self.writer = writer
        self.shape = shape
        self.loop = loop
        self.on_loss = on_loss
        self._rng = random.Random(seed)
        self.on_full = on_full
        b = bounds or QueueBounds()
        self._marker_slack = b.marker_slack
        share, total = b.relayed_share, b.relayed_total
        self._beats = _Queue(b.heartbeat, int(b.heartbeat * share), int(b.heartbeat * total))
        self._control = _Queue(b.control, int(b.control * share), int(b.control * total))
        self._data = _Queue(b.data, int(b.data * share), int(b.data * total))  # data, markers
        self._queues = (self._beats, self._control, self._data)  # the order they leave in
        self._next_free = 0.0
        self._in_air: deque[tuple[float, bytes]] = deque()
        self._timer: asyncio.TimerHandle | None = None

    def send(self, payload: bytes, kind: Kind, via: str | None = None) -> None:
        """Queue a frame (``via``: the neighbour it is relayed for, bounded to its share)."""
        if kind == DATA and self.shape.loss and self._rng.random() < self.shape.loss:
            self.on_loss()
            return
        queue = (
            self._beats
            if kind == HEARTBEAT
            else self._data
            if kind in (DATA, MARKER)
            else self._control
        )
        if not queue.put(payload, self._marker_slack if kind == MARKER else 0, via):
            self.on_full()
            return
        self.pump()

    @property
    def queued(self) -> tuple[int, int, int]:
        """Bytes queued per class: heartbeats, control, data."""
        return (self._beats.bytes, self._control.bytes, self._data.bytes)

    def pump(self) -> None:
        """Move queued frames onto the wire (or into the air) while the writer takes them."""
        bandwidth, delay_s = self.shape.bandwidth_mbps, self.shape.delay_ms / 1e3
        shaped = self.shape.shaped
        now = self.loop.time()
        while not self.writer.paused:
            # the first class with something queued (no generator per frame: this is per send)
            beats, control, data = self._queues
            queue = beats if beats.frames else control if control.frames else data
            if not queue.frames:
                break
            if bandwidth is not None and self._next_free > now + TIMER_SLACK_S:
                self._arm(self._next_free - TIMER_SLACK_S)
                break
            payload = queue.take()
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
