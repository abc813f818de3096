"""Vertex code for seeded fault runs (``mso.sim.faults``): sources that number their events,
pass-throughs, and sinks that record what they got, so an invariant checker can tell lost,
duplicated and reordered events apart.

An event names its stream: the source vertex and the virtual time its instance emitted first
(a restored source is a new instance, so a new stream). A sink instance keeps, per stream, the
sequence numbers it saw; every sink instance of a run is registered in :data:`RUNS` under the
run's token (a vertex parameter), since a node's crash takes the instance but not the record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import msgspec


class Ev(msgspec.Struct, frozen=True):
    src: str
    born: float
    seq: int
    pad: bytes = b""  # (a benchmark's event size)
    n: int = -1  # set by a Count on the way: how many events it had counted before


class Count:
    """Stateful: stamps each event with the number of events it counted before. Its output's
    ``n`` runs 0, 1, 2, ... as long as its state is never lost (chain replication), whatever
    order its input comes in; a state that restarts shows as ``n`` going back."""

    def __init__(self) -> None:
        self.n = 0

    def __call__(self, event: Ev) -> Ev:
        out = Ev(event.src, event.born, event.seq, event.pad, self.n)
        self.n += 1
        return out

    def get_state(self) -> int:
        return self.n

    def set_state(self, state: int) -> None:
        self.n = int(state)


@dataclass
class Stream:
    first: int
    last: int
    seen: set[int] = field(default_factory=set)
    duplicates: int = 0
    reordered: int = 0  # arrived after a higher sequence number

    @property
    def missing(self) -> int:
        """Sequence numbers between the first and the last seen that never arrived."""
        return self.last - self.first + 1 - len(self.seen)


@dataclass
class SinkRecord:
    """What one sink instance received: per stream (source, born), the checks' raw material;
    and of the counts a ``Count`` stamped on them, how often they went back or skipped."""

    vertex: str
    streams: dict[tuple[str, float], Stream] = field(default_factory=dict)
    last_n: int = -1
    regressions: int = 0  # a count at or below one already seen: a state went back
    skips: int = 0  # counts never seen between two that were


RUNS: dict[str, list[SinkRecord]] = {}


class Source:
    """Numbers its events 0, 1, 2, ... within this instance."""

    def __init__(self, name: str, size: int = 0) -> None:
        self.name = name
        self.born: float | None = None
        self.n = 0
        self.pad = bytes(size)

    def __call__(self, seq: int, now: float) -> Ev:
        if self.born is None:
            self.born = round(now, 9)
        ev = Ev(self.name, self.born, self.n, self.pad)
        self.n += 1
        return ev

    def stats(self) -> dict[str, float | int | None]:
        return {"born": self.born, "emitted": self.n}


class Pass:
    """Forwards what it gets: deterministic, so a replay regenerates the same outputs."""

    def __call__(self, event: Ev) -> Ev:
        return event


class Sink:
    """Records per stream what arrives, in the run's registry."""

    def __init__(self, run: str, name: str) -> None:
        self.record = SinkRecord(name)
        RUNS.setdefault(run, []).append(self.record)

    def __call__(self, event: Ev) -> None:
        key = (event.src, event.born)
        s = self.record.streams.get(key)
        if s is None:
            s = self.record.streams[key] = Stream(event.seq, event.seq)
        if event.seq in s.seen:
            s.duplicates += 1
            return
        if event.seq < s.last:
            s.reordered += 1
        s.seen.add(event.seq)
        s.first, s.last = min(s.first, event.seq), max(s.last, event.seq)
        rec = self.record
        if event.n >= 0:
            if rec.last_n >= 0 and event.n <= rec.last_n:
                rec.regressions += 1
            elif rec.last_n >= 0 and event.n > rec.last_n + 1:
                rec.skips += event.n - rec.last_n - 1
            rec.last_n = event.n

    def stats(self) -> dict[str, int]:
        return {"streams": len(self.record.streams)}
