"""What an edge does with the events it holds: its store-and-forward bound, overflow policy
and QoS (``mso.model.qos``), as pure functions of one channel. Sans-IO.

A producer keeps every event its consumer has not acknowledged. While the consumer is out of
reach (or the backlog of a past outage drains), that buffer may grow past the window, up to the
edge's ``buffer_bytes`` and ``buffer_age_s``; past them its ``overflow`` policy applies:

- ``buffer`` (default): the producer is held (backpressure) until acks free room;
- ``drop_oldest``: the oldest events are given up to make room;
- ``keep_latest``: everything but the newest event is given up.

Events given up are counted on the channel (``dropped``, ``superseded``, ``expired``) and the
consumer skips them by the frame's floor: never a silent gap. ``keep_last: N`` bounds what
waits at either end to the newest N (older ones are *superseded*); ``lifespan_ms`` gives up
events older than that (from when they entered their chain); ``best_effort`` neither buffers
for an unreachable consumer nor sends anything twice.
"""

from __future__ import annotations

from mso.model.app import Edge
from mso.protocol.channel import OutChannel

UNBOUNDED_RUN = 4096  # events a producer may make at once when its edge never holds it


def room(out: OutChannel, edge: Edge, held: bool) -> int:
    """How many more events the producer may make now. A reachable consumer with no backlog:
    the window (backpressure as ever). Out of reach, or draining a backlog: the store's bound,
    for the ``buffer`` policy; the other policies give events up instead of holding it."""
    if not held and out.next_seq - out.acked <= out.window:
        return out.room
    if edge.qos == "best_effort" or edge.keep_last is not None or edge.overflow != "buffer":
        return UNBOUNDED_RUN
    if out.kept == 0:
        return UNBOUNDED_RUN
    left = edge.buffer_bytes - out.kept_bytes
    per_event = max(1, out.kept_bytes // out.kept)
    if left <= 0:
        return 0
    return max(0, min(UNBOUNDED_RUN, left // per_event))


def over_age(out: OutChannel, edge: Edge, now: float) -> bool:
    return out.in_flight > 0 and out.age(now) > edge.buffer_age_s


def enforce(out: OutChannel, edge: Edge, held: bool, now: float) -> int:
    """Apply the edge's bound, history and lifespan to what it holds unacknowledged; returns
    how many events were given up (the caller releases and unblocks)."""
    given = 0
    if edge.lifespan_ms is not None and out.in_flight:
        oldest_ok = now - edge.lifespan_ms / 1e3
        upto = out.next_seq  # stamps: runs of events numbered at one time, oldest first
        for first, at in out.stamps:
            if at >= oldest_ok:
                upto = first
                break
        if upto > out.acked:
            n = out.drop_front(upto, now)
            out.expired += n
            given += n
    if not held:
        return given
    if edge.qos == "best_effort":  # no store and forward: gone, counted
        n = out.drop_front(out.next_seq, now)
        out.dropped += n
        return given + n
    if edge.keep_last is not None and out.in_flight > edge.keep_last:
        n = out.drop_front(out.next_seq - edge.keep_last, now)
        out.superseded += n
        given += n
    over = out.kept_bytes > edge.buffer_bytes or over_age(out, edge, now)
    if not over or edge.overflow == "buffer":
        return given
    if edge.overflow == "keep_latest":
        n = out.drop_front(out.next_seq - 1, now)
    else:  # drop_oldest: as few as bring it back under both bounds
        n = 0
        while out.in_flight > 1 and (
            out.kept_bytes > edge.buffer_bytes or over_age(out, edge, now)
        ):
            n += out.drop_front(out.acked + 1, now)
    out.dropped += n
    return given + n
