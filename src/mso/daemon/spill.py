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
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sqlite3
from pathlib import Path

from mso.errors import MsoError

FILE = "spill.sqlite3"
FORMAT = "mso-spill"
VERSION = "1"
# the positions table also holds, under ``key + ACKED`` (and ``+ edge``), the output positions
# the last ack of a held source edge brought (``save_positions``)
ACKED = "@"
_DELETE_ACK_POSITIONS = "DELETE FROM positions WHERE substr(key, 1, ?) = ?"


class SqliteSpill:
    """A :class:`~mso.protocol.spill.SpillStore` in ``state_dir/spill.sqlite3``."""

    def __init__(self, state_dir: Path) -> None:
        self.path = state_dir / FILE
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
        if self._bytes[key] <= 0:
            del self._bytes[key]
            self._vacuum()

    def drop(self, key: str) -> None:
        with self._db:
            self._db.execute("BEGIN")
            self._db.execute("DELETE FROM events WHERE key = ?", (key,))
            self._db.execute("DELETE FROM positions WHERE key = ?", (key,))
            self._db.execute(_DELETE_ACK_POSITIONS, (len(key) + 1, key + ACKED))
        if self._bytes.pop(key, 0):
            self._vacuum()

    def size(self, key: str) -> int:
        return self._bytes.get(key, 0)

    def span(self, key: str) -> tuple[int, int] | None:
        row = self._db.execute(
            "SELECT MIN(seq), MAX(seq) FROM events WHERE key = ?", (key,)
        ).fetchone()
        return None if row is None or row[0] is None else (int(row[0]), int(row[1]) + 1)

    def save_position(self, key: str, value: int) -> None:
        self._db.execute("INSERT OR REPLACE INTO positions VALUES (?, ?)", (key, value))

    def position(self, key: str) -> int | None:
        row = self._db.execute("SELECT value FROM positions WHERE key = ?", (key,)).fetchone()
        return None if row is None else int(row[0])

    def save_positions(self, key: str, at: int, positions: dict[int, int]) -> None:
        rows = [(key + ACKED, at), *((f"{key}{ACKED}{e}", p) for e, p in positions.items())]
        with self._db:
            self._db.execute("BEGIN")
            self._db.execute(_DELETE_ACK_POSITIONS, (len(key) + 1, key + ACKED))
            self._db.executemany("INSERT OR REPLACE INTO positions VALUES (?, ?)", rows)

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

    # -- what it costs ---------------------------------------------------------------------
    def held_bytes(self) -> int:
        """Bytes of events held over every edge."""
        return sum(self._bytes.values())

    def disk_bytes(self) -> int:
        """The file's size with its write-ahead log."""
        wal = self.path.with_name(FILE + "-wal")
        return sum(p.stat().st_size for p in (self.path, wal) if p.exists())

    def _vacuum(self) -> None:
        """An edge has drained: give the file's free pages back, and the log's."""
        self._db.executescript("PRAGMA incremental_vacuum;")  # (one page per step otherwise)
        self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
