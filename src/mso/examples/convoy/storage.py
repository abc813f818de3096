"""The trailing robot's log: SQLite in WAL mode, one row per result, each carrying its source's
sequence number and timestamp and the time it was stored, so completeness (no gap, no repeat)
and end-to-end delay come from the database alone; and the summary read back from it."""

from __future__ import annotations

import math
import os
import shutil
import sqlite3
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mso.examples.convoy.planning import Trajectory
from mso.examples.convoy.sensors import CAMERA_HZ, LASER_HZ, in_view
from mso.examples.convoy.vision import TargetReport
from mso.examples.convoy.world import SURVIVORS, on_straight, true_pose, world

DB_ENV = "MSO_CONVOY_DB"
FOUND_WITHIN_M = 1.5  # a reported target this close to a planted survivor found it
SCHEMA = """
CREATE TABLE IF NOT EXISTS trajectory (
    id INTEGER PRIMARY KEY, seq INTEGER NOT NULL, stamp REAL NOT NULL, odom_seq INTEGER,
    stored_at REAL NOT NULL, x REAL, y REAL, theta REAL, v REAL, w REAL, goal INTEGER);
CREATE TABLE IF NOT EXISTS targets (
    id INTEGER PRIMARY KEY, seq INTEGER NOT NULL, stamp REAL NOT NULL,
    stored_at REAL NOT NULL, hits INTEGER, targets TEXT);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
"""


_clock: Callable[[], float] = time.monotonic


def set_clock(clock: Callable[[], float]) -> None:
    """The clock new Storage instances stamp rows with: the simulator passes its virtual one,
    so delays come out in the time the sources stamped events with."""
    global _clock
    _clock = clock


def default_db() -> str:
    return os.environ.get(DB_ENV) or str(Path(tempfile.gettempdir()) / "mso-convoy.sqlite")


class Storage:
    """The sink. ``db`` defaults to $MSO_CONVOY_DB (else mso-convoy.sqlite in the temp dir);
    ``clock`` stamps the rows (the node's monotonic clock, the one sources stamp events with;
    the simulator sets its virtual clock)."""

    def __init__(self, db: str = "", seed: int = 7) -> None:
        self.path = db or default_db()
        self.seed = seed
        self.clock: Callable[[], float] = _clock
        self.conn: sqlite3.Connection | None = None
        self.rows = 0

    def dry_run(self, scratch: str) -> None:
        """``mso profile``: log into a copy of the database in ``scratch``, never the real one
        (its path may come from $MSO_CONVOY_DB, which profiling cannot see)."""
        real = Path(self.path)
        copy = Path(scratch) / real.name
        if real.is_file() and not copy.exists():
            shutil.copy2(real, copy)
        self.path = str(copy)

    def open(self) -> None:
        conn = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.executescript(SCHEMA)
        conn.execute("INSERT OR REPLACE INTO meta VALUES ('seed', ?)", (str(self.seed),))
        self.conn = conn

    def __call__(self, event: Trajectory | TargetReport) -> None:
        if self.conn is None:
            self.open()
        assert self.conn is not None
        now = self.clock()
        if isinstance(event, Trajectory):
            self.conn.execute(
                "INSERT INTO trajectory (seq, stamp, odom_seq, stored_at, x, y, theta, v, w, goal)"
                " VALUES (?,?,?,?,?,?,?,?,?,?)",
                (event.seq, event.stamp, event.odom_seq, now, event.x, event.y, event.theta,
                 event.v, event.w, event.goal),
            )  # fmt: skip
        else:
            targets = ";".join(f"{x:.2f},{y:.2f},{p:.3f}" for x, y, p in event.targets)
            self.conn.execute(
                "INSERT INTO targets (seq, stamp, stored_at, hits, targets) VALUES (?,?,?,?,?)",
                (event.seq, event.stamp, now, event.hits, targets),
            )
        self.rows += 1

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def stats(self) -> dict[str, int]:
        return {"rows": self.rows}


def _coverage(seqs: list[int]) -> dict[str, int]:
    distinct = len(set(seqs))
    return {
        "rows": len(seqs),
        "distinct": distinct,
        "repeats": len(seqs) - distinct,
        "gaps": (max(seqs) - min(seqs) + 1 - distinct) if seqs else 0,
        "first": min(seqs) if seqs else -1,
        "last": max(seqs) if seqs else -1,
    }


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def stored_by(path: str | Path, t: float) -> int:
    """Distinct results (trajectory and target rows) stored by time ``t`` (the rows' clock)."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return sum(
            int(conn.execute(f"SELECT COUNT(DISTINCT seq) FROM {table} WHERE stored_at <= ?",
                             (t,)).fetchone()[0])
            for table in ("trajectory", "targets")
        )  # fmt: skip
    finally:
        conn.close()


def summary(path: str | Path) -> dict[str, Any]:
    """What the log says: rows and their completeness per kind, end-to-end delay, the
    localization error against the ground truth, survivors found against those planted."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        seed_row = conn.execute("SELECT value FROM meta WHERE key='seed'").fetchone()
        traj = conn.execute("SELECT seq, stamp, stored_at, x, y FROM trajectory").fetchall()
        tgt = conn.execute("SELECT seq, stamp, stored_at, targets FROM targets").fetchall()
    finally:
        conn.close()
    seed = int(seed_row[0]) if seed_row else 7
    delays = [r[2] - r[1] for r in traj] + [r[2] - r[1] for r in tgt]
    errors, straight = [], []
    for seq, _, _, x, y in traj:
        t = seq / LASER_HZ
        tx, ty, _ = true_pose(t)
        e = math.hypot(x - tx, y - ty)
        errors.append(e)
        if on_straight(t):
            straight.append(e)
    last = max(tgt, key=lambda r: r[0]) if tgt else None
    found_at = [] if last is None or not last[3] else [
        tuple(float(v) for v in item.split(",")[:2]) for item in last[3].split(";")
    ]  # fmt: skip
    w = world(seed)
    seen = set()
    for seq in range(0, (last[0] + 1) if last else 0):
        for k, s in enumerate(SURVIVORS):
            if k not in seen and in_view(w, true_pose(seq / CAMERA_HZ), (s,)):
                seen.add(k)
    found = {
        k
        for k, (sx, sy) in enumerate(SURVIVORS)
        if any(math.hypot(sx - fx, sy - fy) <= FOUND_WITHIN_M for fx, fy in found_at)
    }
    phantoms = len(found_at) - sum(
        1
        for fx, fy in found_at
        if any(math.hypot(sx - fx, sy - fy) <= FOUND_WITHIN_M for sx, sy in SURVIVORS)
    )
    return {
        "trajectory": _coverage([r[0] for r in traj]),
        "targets": _coverage([r[0] for r in tgt]),
        "delay_ms_p50": None if not delays else 1e3 * (_pct(delays, 50) or 0.0),
        "delay_ms_p99": None if not delays else 1e3 * (_pct(delays, 99) or 0.0),
        "localization_error_m_mean": float(np.mean(errors)) if errors else None,
        "localization_error_m_max_straight": max(straight) if straight else None,
        "localization_error_m_max": max(errors) if errors else None,
        "survivors_planted": len(SURVIVORS),
        "survivors_in_view": len(seen),
        "survivors_found": len(found),
        "phantom_targets": phantoms,
    }
