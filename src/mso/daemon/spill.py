"""The daemon's durable spill store: one SQLite file under the node's state directory
(``mso node --state-dir``) holding, per edge instance, the events its producer could not
deliver yet and, per source edge, the next sequence number (so a restarted daemon numbers on).

It implements :class:`mso.protocol.spill.SpillStore`; the protocol calls it synchronously (it
stays sans-IO: the store is injected). Writes go through SQLite's write-ahead log without a
sync per commit (``synchronous=NORMAL``): a crash of the process loses nothing committed, a
power loss at most the last commits. Rows are deleted as acks trim them, and the freed pages go
back to the file system once an edge has drained (incremental vacuum), so the file is about the
size of what is held. A file that is not SQLite, is damaged, or is another program's gives a
clear error when the node starts, never a crash later.

Every call is made on the node's event loop, so none may take long: giving back a drained
300 MB in one go took 3.6-5.7 s, past the failure detector (the emulated 10-minute cut's reset).
So the pages go back a bounded step at a time (:meth:`SqliteSpill.tidy`, ~1 MiB), and the
write-ahead log's checkpoints (a copy and an fsync) run on a thread of their own
(:func:`keep_tidy`, which the daemon runs beside its node). Reads of a backlog (4 MB a window
of 50 KB events: 18 ms, to 100 ms under load) run on a reader thread of their own
(:meth:`SqliteSpill.read_apart`): a drain takes what was read ahead (:meth:`SqliteSpill.ready`,
no SQLite work on the loop), and the thread's results come back to the loop as a call, which
tells the node to drain on.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import itertools
import os
import queue
import sqlite3
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mso.errors import MsoError

FILE = "spill.sqlite3"
FORMAT = "mso-spill"
VERSION = "1"
# the positions table also holds, under ``key + ACKED`` (and ``+ edge``), the output positions
# the last ack of a held source edge brought (``save_positions``)
ACKED = "@"
GEN = "g"  # under ``key + ACKED + GEN + edge``: the generation of that edge's numbering, if not 0
_DELETE_ACK_POSITIONS = "DELETE FROM positions WHERE substr(key, 1, ?) = ?"
# notes (SpillStore.note): named integers under a prefix, in the positions table too
_NOTES = "SELECT key, value FROM positions WHERE substr(key, 1, ?) = ?"
_DELETE_NOTES = "DELETE FROM positions WHERE substr(key, 1, ?) = ?"
# pages (4 KiB) one tidy step gives back to the file system: a few ms (bench: 300 MB in 288
# steps, p50 0.7 ms, p99 9-13 ms, wall time on a loaded 2-core machine)
VACUUM_PAGES = 256
# how often keep_tidy checkpoints what was written; the log's own checkpoint (on the loop, in
# whichever commit crosses it) finishes what keep_tidy left and lets the log start over: 16 MiB
TIDY_S = 0.5
AUTOCHECKPOINT_PAGES = 4096
# a writer waits this long for a checkpoint on keep_tidy's thread (ms; they take a few)
BUSY_MS = 5000
# the reader thread reads an edge's backlog this far ahead of what was sent (events, bytes),
# and an edge keeps at most CACHE_BYTES of what it read (what was sent and not acked, for a
# go-back): about a drain's MAX_IN_FLIGHT_BYTES (mso.protocol.forward) each
READ_AHEAD_EVENTS = 4096
READ_AHEAD_BYTES = 4 << 20
CACHE_BYTES = 3 * READ_AHEAD_BYTES
_SELECT_FROM = "SELECT seq, data FROM events WHERE key = ? AND seq >= ? ORDER BY seq LIMIT ?"


@dataclass
class _Ahead:
    """What the reader thread read of one edge: events ``lo``, ``lo + 1``, ... in order."""

    gen: int  # a dropped key's reads in flight are not the new key's
    lo: int = 0
    events: deque[bytes] = field(default_factory=deque)
    size: int = 0
    asked: bool = False  # a read is on the reader thread
    dry: bool = False  # the last read found nothing more: ask again after an append

    @property
    def end(self) -> int:
        return self.lo + len(self.events)

    def clear(self, lo: int) -> None:
        self.events.clear()
        self.lo, self.size, self.dry = lo, 0, False

    def pop_below(self, seq: int) -> None:
        while self.events and self.lo < seq:
            self.size -= len(self.events.popleft())
            self.lo += 1


class SqliteSpill:
    """A :class:`~mso.protocol.spill.SpillStore` in ``state_dir/spill.sqlite3``."""

    def __init__(self, state_dir: Path) -> None:
        self.path = state_dir / FILE
        self._checkpointer: sqlite3.Connection | None = None  # keep_tidy's thread's
        self._checkpointing = threading.Lock()
        # read_apart: the reader thread, its jobs, and what it read ahead per edge
        self._reader: threading.Thread | None = None
        self._jobs: queue.SimpleQueue[tuple[str, int, int] | None] = queue.SimpleQueue()
        self._ahead: dict[str, _Ahead] = {}
        self._gens = itertools.count()
        self._hand_back: Callable[[Callable[[], None]], object] = lambda call: call()
        self._on_ready: Callable[[str], None] = lambda key: None
        self.reads_apart = 0  # reads done on the reader thread (bench, tests)
        try:
            state_dir.mkdir(parents=True, exist_ok=True)
            self._lock = (state_dir / (FILE + ".lock")).open("a+")
        except OSError as exc:
            raise MsoError(f"--state-dir {state_dir}: cannot use it ({exc.strerror})") from exc
        try:  # one node per state directory: two would number the same edges twice
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            self._lock.close()
            raise MsoError(
                f"--state-dir {state_dir}: in use by another mso node (each needs its own)"
            ) from exc
        try:
            self._db = self._open()
        except sqlite3.DatabaseError as exc:
            self.close()
            raise MsoError(
                f"{self.path}: not a usable mso spill store ({exc}); move it away to start "
                "afresh (its held events are then lost) or give another --state-dir"
            ) from exc
        self._bytes: dict[str, int] = dict(
            self._db.execute("SELECT key, SUM(LENGTH(data)) FROM events GROUP BY key").fetchall()
        )
        self.owed = False  # an edge drained: free pages to give back (tidy)
        self.wrote = False  # written since the last checkpoint (keep_tidy)

    def _open(self) -> sqlite3.Connection:
        new = not self.path.exists() or self.path.stat().st_size == 0
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            if new:
                db.execute("PRAGMA auto_vacuum = INCREMENTAL")  # before the first table
                db.execute("PRAGMA journal_mode = WAL")
                db.executescript(
                    "BEGIN;"
                    "CREATE TABLE meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);"
                    "CREATE TABLE events (key TEXT NOT NULL, seq INTEGER NOT NULL,"
                    " data BLOB NOT NULL, PRIMARY KEY (key, seq)) WITHOUT ROWID;"
                    "CREATE TABLE positions (key TEXT PRIMARY KEY, value INTEGER NOT NULL);"
                    f"INSERT INTO meta VALUES ('format', '{FORMAT}'), ('version', '{VERSION}');"
                    "COMMIT;"
                )
            else:
                self._check(db)
                db.execute("PRAGMA journal_mode = WAL")
            db.execute("PRAGMA synchronous = NORMAL")
            db.execute(f"PRAGMA busy_timeout = {BUSY_MS}")
        except BaseException:
            db.close()
            raise
        with contextlib.suppress(OSError):
            os.chmod(self.path, 0o600)  # events are the app's data: this user's only
        return db

    def _check(self, db: sqlite3.Connection) -> None:
        """Damaged, or another program's file: said here, before anything runs."""
        ok = db.execute("PRAGMA quick_check").fetchone()
        if ok is None or ok[0] != "ok":
            raise sqlite3.DatabaseError(f"damaged: {ok[0] if ok else 'no answer'}")
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not {"meta", "events", "positions"} <= tables:
            found = ", ".join(sorted(tables)) or "none"
            raise sqlite3.DatabaseError(f"a SQLite file, but not {FORMAT} (tables: {found})")
        meta = dict(db.execute("SELECT name, value FROM meta").fetchall())
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise sqlite3.DatabaseError(
                f"format {meta.get('format')!r} version {meta.get('version')!r}, "
                f"expected {FORMAT!r} version {VERSION!r}"
            )
        bad = db.execute(
            "SELECT COUNT(*) FROM events WHERE typeof(seq) != 'integer' OR typeof(data) != 'blob'"
        ).fetchone()[0]
        if bad:
            raise sqlite3.DatabaseError(f"{bad} events of the wrong type")

    def close(self) -> None:
        self.stop_reading()
        with self._checkpointing:
            if self._checkpointer is not None:
                self._checkpointer.close()
                self._checkpointer = None
        if hasattr(self, "_db"):
            self._db.close()
        self._lock.close()

    # -- SpillStore ------------------------------------------------------------------------
    def append(self, key: str, seq: int, events: list[bytes]) -> None:
        rows = [(key, seq + i, e) for i, e in enumerate(events)]
        with self._db:
            self._db.execute("BEGIN")
            self._db.executemany("INSERT OR REPLACE INTO events VALUES (?, ?, ?)", rows)
        self._bytes[key] = self._bytes.get(key, 0) + sum(map(len, events))
        self.wrote = True
        a = self._ahead.get(key)
        if a is not None:
            a.dry = False
            if seq < a.end and seq + len(events) > a.lo:  # (rewritten: what was read is not it)
                self._ahead[key] = _Ahead(next(self._gens), lo=a.lo)

    def read(self, key: str, start: int, count: int) -> list[bytes]:
        if count <= 0 or not self._bytes.get(key):
            return []
        rows = self._db.execute(
            "SELECT data FROM events WHERE key = ? AND seq >= ? ORDER BY seq LIMIT ?",
            (key, start, count),
        ).fetchall()
        return [bytes(r[0]) for r in rows]

    def trim(self, key: str, below: int) -> None:
        if not self._bytes.get(key):
            return
        with self._db:
            self._db.execute("BEGIN")
            (gone,) = self._db.execute(
                "SELECT COALESCE(SUM(LENGTH(data)), 0) FROM events WHERE key = ? AND seq < ?",
                (key, below),
            ).fetchone()
            self._db.execute("DELETE FROM events WHERE key = ? AND seq < ?", (key, below))
        self._bytes[key] -= gone
        self.wrote = True
        a = self._ahead.get(key)
        if a is not None:
            a.pop_below(below)
            if a.lo < below:
                a.clear(below)
        if self._bytes[key] <= 0:
            del self._bytes[key]
            self._vacuum()

    def drop(self, key: str) -> None:
        with self._db:
            self._db.execute("BEGIN")
            self._db.execute("DELETE FROM events WHERE key = ?", (key,))
            self._db.execute("DELETE FROM positions WHERE key = ?", (key,))
            self._db.execute(_DELETE_ACK_POSITIONS, (len(key) + 1, key + ACKED))
        self.wrote = True
        self._ahead.pop(key, None)
        if self._bytes.pop(key, 0):
            self._vacuum()

    def ready(self, key: str, start: int, count: int) -> list[bytes]:
        """Up to ``count`` events of ``key`` from ``start`` on that the reader thread has read
        (all of them, read here, when it does not run): no SQLite work on the loop. Reading
        on is asked for in the same call, and the node is told when it is in."""
        if self._reader is None:
            return self.read(key, start, count)
        if count <= 0 or not self._bytes.get(key):
            return []
        a = self._ahead.get(key)
        if a is None:
            a = self._ahead[key] = _Ahead(next(self._gens), lo=start)
        elif not a.lo <= start <= a.end:  # elsewhere (a go-back past what is kept): anew
            a.clear(start)
            a.gen = next(self._gens)
            a.asked = False
        skip = start - a.lo
        out = list(itertools.islice(a.events, skip, skip + count))
        if a.size > CACHE_BYTES:  # what was sent before ``start`` goes first
            a.pop_below(start)
        ahead = a.end - start - len(out)
        if (
            not a.asked
            and not a.dry
            and ahead * (a.size // max(1, len(a.events))) < READ_AHEAD_BYTES
        ):
            a.asked = True
            self._jobs.put((key, a.gen, a.end))
        return out

    def read_apart(
        self,
        hand_back: Callable[[Callable[[], None]], object],
        on_ready: Callable[[str], None],
    ) -> None:
        """From now on :meth:`ready` reads on a thread of its own: ``hand_back`` runs a call
        on the loop's thread (``loop.call_soon_threadsafe``), where what was read is taken in
        and ``on_ready(key)`` tells the node events of ``key`` are there to send."""
        if self._reader is not None:
            return
        self._hand_back, self._on_ready = hand_back, on_ready
        self._reader = threading.Thread(target=self._reading, name="mso-spill-reader", daemon=True)
        self._reader.start()

    def stop_reading(self) -> None:
        """The reader thread ends (what it read is forgotten; :meth:`ready` reads here)."""
        if self._reader is not None:
            self._jobs.put(None)
            self._reader.join()
            self._reader = None
            self._ahead.clear()

    def _reading(self) -> None:
        """The reader thread: each job, read ahead and hand back; its own connection (the
        write-ahead log lets it read while the loop writes)."""
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            while (job := self._jobs.get()) is not None:
                key, gen, start = job
                events: list[bytes] = []
                size = 0
                # (closed at once: an open read would hold the log's checkpoints back)
                with contextlib.closing(
                    db.execute(_SELECT_FROM, (key, start, READ_AHEAD_EVENTS))
                ) as rows:
                    for seq, data in rows:
                        if seq != start + len(events) or size >= READ_AHEAD_BYTES:
                            break  # (trimmed meanwhile: what follows is not from ``start``)
                        events.append(bytes(data))
                        size += len(data)
                self.reads_apart += 1
                with contextlib.suppress(RuntimeError):  # the loop closed: nobody to tell
                    self._hand_back(functools.partial(self._read_ahead, key, gen, start, events))
        finally:
            db.close()

    def _read_ahead(self, key: str, gen: int, start: int, events: list[bytes]) -> None:
        """On the loop: what the reader thread read, kept if the edge still wants it there."""
        a = self._ahead.get(key)
        if a is None or a.gen != gen:
            return
        a.asked = False
        if start != a.end:  # trimmed past it meanwhile, or read again from elsewhere
            return
        if not events:
            a.dry = True
            return
        a.events.extend(events)
        a.size += sum(map(len, events))
        self._on_ready(key)

    def size(self, key: str) -> int:
        return self._bytes.get(key, 0)

    def span(self, key: str) -> tuple[int, int] | None:
        # (MIN and MAX in one select scan every row of the key: 0.5 s for 300 MB; apart, each
        # is one look into the primary key)
        row = self._db.execute(
            "SELECT (SELECT MIN(seq) FROM events WHERE key = ?),"
            " (SELECT MAX(seq) FROM events WHERE key = ?)",
            (key, key),
        ).fetchone()
        return None if row is None or row[0] is None else (int(row[0]), int(row[1]) + 1)

    def save_position(self, key: str, value: int) -> None:
        self._db.execute("INSERT OR REPLACE INTO positions VALUES (?, ?)", (key, value))
        self.wrote = True

    def position(self, key: str) -> int | None:
        row = self._db.execute("SELECT value FROM positions WHERE key = ?", (key,)).fetchone()
        return None if row is None else int(row[0])

    def save_positions(
        self, key: str, at: int, positions: dict[int, int], gens: dict[int, int] | None = None
    ) -> None:
        rows = [(key + ACKED, at), *((f"{key}{ACKED}{e}", p) for e, p in positions.items())]
        rows += [(f"{key}{ACKED}{GEN}{e}", g) for e, g in (gens or {}).items()]
        with self._db:
            self._db.execute("BEGIN")
            self._db.execute(_DELETE_ACK_POSITIONS, (len(key) + 1, key + ACKED))
            self._db.executemany("INSERT OR REPLACE INTO positions VALUES (?, ?)", rows)
        self.wrote = True

    def note(self, prefix: str, name: str, value: int) -> None:
        with self._db:
            self._db.execute("BEGIN")
            self._db.execute(_DELETE_NOTES, (len(prefix), prefix))
            self._db.execute(
                "INSERT OR REPLACE INTO positions VALUES (?, ?)", (prefix + name, value)
            )
        self.wrote = True

    def notes(self, prefix: str) -> dict[str, int]:
        rows = self._db.execute(_NOTES, (len(prefix), prefix)).fetchall()
        return {str(k)[len(prefix) :]: int(v) for k, v in rows}

    def forget_notes(self, prefix: str) -> None:
        self._db.execute(_DELETE_NOTES, (len(prefix), prefix))
        self.wrote = True

    def saved_positions(self, key: str) -> tuple[int, dict[int, int]] | None:
        rows = self._db.execute(
            "SELECT key, value FROM positions WHERE substr(key, 1, ?) = ?",
            (len(key) + 1, key + ACKED),
        ).fetchall()
        at, positions = None, {}
        for name, value in rows:
            rest = name[len(key) + 1 :]
            if rest == "":
                at = int(value)
            elif rest.isdigit():
                positions[int(rest)] = int(value)
        return None if at is None else (at, positions)

    def saved_gens(self, key: str) -> dict[int, int]:
        prefix = key + ACKED + GEN
        rows = self._db.execute(
            "SELECT key, value FROM positions WHERE substr(key, 1, ?) = ?",
            (len(prefix), prefix),
        ).fetchall()
        rests = ((str(name)[len(prefix) :], int(value)) for name, value in rows)
        return {int(rest): value for rest, value in rests if rest.isdigit()}

    # -- what it costs ---------------------------------------------------------------------
    def held_bytes(self) -> int:
        """Bytes of events held over every edge."""
        return sum(self._bytes.values())

    def disk_bytes(self) -> int:
        """The file's size with its write-ahead log."""
        wal = self.path.with_name(FILE + "-wal")
        return sum(p.stat().st_size for p in (self.path, wal) if p.exists())

    def _vacuum(self) -> None:
        """An edge has drained: its pages are owed to the file system (given back by
        :meth:`tidy`, a step at a time, never all in this call)."""
        self.owed = True

    def tidy(self, pages: int = VACUUM_PAGES) -> bool:
        """Give at most ``pages`` free pages back to the file system; True while some are left.
        The last step checkpoints the log and truncates it, so the files are about the size
        of what is held (keep_tidy does that on its thread instead)."""
        if not self.owed:
            return False
        self._db.executescript(f"PRAGMA incremental_vacuum({pages});")  # (executescript: all
        if self._db.execute("PRAGMA freelist_count").fetchone()[0]:  # of them, not one page)
            return True
        self.owed = False
        if self._checkpointer is None:
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
        else:
            self.wrote = True  # keep_tidy truncates the log next
        return False

    def checkpoint(self, truncate: bool = False) -> None:
        """Copy the log into the file and sync it (``truncate``: and empty the log file), on
        a connection of its own: keep_tidy calls it on a thread, and the loop's writes go on
        meanwhile (a passive checkpoint never blocks them; a truncating one for a few ms)."""
        with self._checkpointing:
            if self._checkpointer is None:
                return
            mode = "TRUNCATE" if truncate else "PASSIVE"
            self._checkpointer.execute(f"PRAGMA wal_checkpoint({mode})").fetchall()

    def checkpoint_apart(self) -> None:
        """From now on the log is copied into the file by :meth:`checkpoint` (keep_tidy's
        thread). A checkpoint on another connection never catches up with writes that go
        on, and only a complete one lets the log start over, so the loop's own still runs
        past AUTOCHECKPOINT_PAGES (not 1,000): it finds the copying done but the last
        frames, and the log stays under about 16 MiB."""
        if self._checkpointer is None:
            self._checkpointer = sqlite3.connect(
                self.path, isolation_level=None, check_same_thread=False
            )
            self._checkpointer.execute(f"PRAGMA busy_timeout = {BUSY_MS}")
            self._db.execute(f"PRAGMA wal_autocheckpoint = {AUTOCHECKPOINT_PAGES}")


async def keep_tidy(store: SqliteSpill, period: float = TIDY_S) -> None:
    """Run beside the node for as long as it runs: every ``period``, give a drained store's
    pages back a step per loop turn, then checkpoint what was written on a thread (a drained
    store's log truncated)."""
    store.checkpoint_apart()
    while True:
        await asyncio.sleep(period)
        drained = store.owed
        while store.tidy():
            await asyncio.sleep(0)  # (the loop's other work between steps)
        if store.wrote:
            store.wrote = False
            await asyncio.to_thread(store.checkpoint, drained or not store.held_bytes())
