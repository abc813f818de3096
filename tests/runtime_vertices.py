"""Vertex code for runtime tests: a counting source and a sink that checks what it gets.

Importable by node processes when the tests directory is on PYTHONPATH.
"""

from __future__ import annotations

from typing import Any

import msgspec

from mso.benchmarks.common import SequenceCheck


def pipe_app(rate: int) -> str:
    """src (N1) -> mid -> sink (N4), the app most runtime tests deploy. ``mid`` declares its
    output format, so the sink decodes ``Num`` events and really checks their order (without
    it the sink got plain dicts and counted every event as an error). ``planner: paper``: the
    tests kill, cut or move the relay ``mid`` runs on, and the paper's split puts it on one
    (the default ``bytes`` split keeps a 64-byte pipe whole on the source's node)."""
    return f"""
name: pipe
planner: paper
vertices:
  src: {{code: runtime_vertices:CountingSource, pinned: N1, rate: {rate},
        output: runtime_vertices:Num}}
  mid: {{code: runtime_vertices:Double, output: runtime_vertices:Num}}
  sink: {{code: runtime_vertices:Recorder, pinned: N4}}
edges:
  - [src, mid]
  - [mid, sink]
"""


class Num(msgspec.Struct, frozen=True):
    seq: int
    pad: bytes = b""


class CountingSource:
    """Numbers its events. ``stall_at``: the call for that event takes ``stall_s`` (a slow
    camera frame), so the events that came due meanwhile leave in one batch after it."""

    def __init__(self, size: int = 0, stall_at: int = -1, stall_s: float = 0.0) -> None:
        self.pad = b"x" * size
        self.stall_at, self.stall_s = stall_at, stall_s

    def __call__(self, seq: int, now: float) -> Num:
        if seq == self.stall_at:
            import time

            time.sleep(self.stall_s)  # the vertex's own work, not the test waiting
        return Num(seq=seq, pad=self.pad)


class Double:
    def __call__(self, event: Num) -> Num:
        return Num(seq=event.seq, pad=event.pad)


class WrongOutput:
    """Declares ``Num`` but returns a dict without ``seq``: its own mistake, to be blamed on it."""

    def __call__(self, event: Num) -> dict[str, int]:
        return {"n": event.seq}


class Recorder(SequenceCheck):
    """Checks per-producer order: every event's seq must be the previous one + 1."""

    def __call__(self, event: Num) -> None:
        self.see(event.seq)

    def stats(self) -> dict[str, int]:
        return {
            "count": self.count,
            "next": self.next,
            "out_of_order": self.out_of_order,
            "repeats": self.repeats,
        }


class Counter:
    """Stateful: numbers the events it has processed. A move that lost or repeated state (or
    events) shows at the sink as a repeat or a gap in these numbers."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Num) -> Num:
        out = Num(seq=self.count, pad=event.pad)
        self.count += 1
        return out

    def get_state(self) -> int:
        return self.count

    def set_state(self, state: int) -> None:
        self.count = state


class Broken:
    """A vertex whose constructor fails, as buggy user code does."""

    def __init__(self) -> None:
        raise RuntimeError("sensor not found")


class Flaky:
    """Fails on every third event; the node must count it and go on."""

    def __call__(self, event: Num) -> Num:
        if event.seq % 3 == 2:
            raise ValueError(f"bad reading {event.seq}")
        return event


def numbers(count: int = 100):  # type: ignore[no-untyped-def]
    """A finite generator source: its end is the end of its stream."""
    yield from (Num(seq=i) for i in range(count))


class Summing:
    """An operator that passes events on and, at the end of its inputs, one total."""

    def __init__(self) -> None:
        self.total = 0

    def __call__(self, event: Num) -> Num:
        self.total += event.seq
        return event

    def end(self) -> Num:
        return Num(seq=-1, pad=str(self.total).encode())


class Flushing:
    """A sink that buffers and flushes at the end of its stream."""

    def __init__(self) -> None:
        self.buffer: list[int] = []
        self.flushed: list[int] = []
        self.ends = 0
        self.total = b""

    def __call__(self, event: Num) -> None:
        if event.seq < 0:
            self.total = event.pad
        else:
            self.buffer.append(event.seq)

    def end(self) -> None:
        self.ends += 1
        self.flushed, self.buffer = self.flushed + self.buffer, []


class Silent:
    """A source with nothing to say (yet): its consumers have seen no event."""

    def __call__(self, seq: int, now: float) -> None:
        return None


class PidCounter(Counter):
    """A Counter that says which process runs it."""

    def stats(self) -> dict[str, int]:
        import os

        return {"pid": os.getpid(), "count": self.count}


class ExitOn:
    """Passes events on; its process ends with ``os._exit(3)`` (no cleanup, as a crashing C
    extension would) on event ``seq``, every time. With ``armed`` (a file path) it ends
    instead on the first event from ``seq`` on that it sees while that file exists, and
    removes the file: a test arms it when it is ready for the crash, whatever the stream has
    reached by then (an exit at a fixed event could come before the test's own SIGKILL)."""

    def __init__(self, seq: int, armed: str = "") -> None:
        self.seq = seq
        self.armed = armed

    def __call__(self, event: Num) -> Num:
        import os

        if not self.armed:
            if event.seq == self.seq:
                os._exit(3)
        elif event.seq >= self.seq and os.path.exists(self.armed):
            os.remove(self.armed)
            os._exit(3)
        return event

    def stats(self) -> dict[str, int]:
        import os

        return {"pid": os.getpid()}


class SqliteLog:
    """A sink that appends a row per event to the SQLite file it is given (``mso profile``
    must measure it without touching that file)."""

    def __init__(self, db: str) -> None:
        self.db = db
        self.conn: Any = None

    def open(self) -> None:
        import sqlite3

        self.conn = sqlite3.connect(self.db)
        self.conn.execute("CREATE TABLE IF NOT EXISTS log (seq INTEGER)")

    def __call__(self, event: Num) -> None:
        self.conn.execute("INSERT INTO log VALUES (?)", (event.seq,))
        self.conn.commit()

    def close(self) -> None:
        self.conn.close()


class EnvLog:
    """A sink that writes where the environment says, and declares ``dry_run`` so profiling
    can point it at a scratch directory instead."""

    def __init__(self) -> None:
        import os

        self.path = os.environ["MSO_TEST_ENVLOG"]

    def dry_run(self, scratch: str) -> None:
        self.path = f"{scratch}/envlog.txt"

    def __call__(self, event: Num) -> None:
        with open(self.path, "a") as f:
            f.write(f"{event.seq}\n")


SEEN: dict[str, list[int]] = {}  # run -> every seq any SeenSink instance of it received


class SeenSink:
    """Records every seq it gets in :data:`SEEN` under its ``run`` param, across instances
    (a restored or reset sink keeps adding to the same list): a test reads loss, duplicates
    and order over the whole run."""

    def __init__(self, run: str = "") -> None:
        self.seen = SEEN.setdefault(run, [])

    def __call__(self, event: Num) -> None:
        self.seen.append(event.seq)


class FileSeen:
    """A sink that appends each event's seq to the file it is given, one a line, flushed:
    a test reads loss, duplicates and order over every instance (a restored one appends)."""

    def __init__(self, path: str) -> None:
        self.out = open(path, "a")  # noqa: SIM115 (open for the instance's life)

    def __call__(self, event: Num) -> None:
        self.out.write(f"{event.seq}\n")
        self.out.flush()
