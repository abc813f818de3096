"""The real convoy app end to end on the emulated 4-robot line: every result the leader's
sensors caused is a row in the trailing robot's SQLite log, once, also across a relocation of
the stateful target map (the targets it found move with it; the Bayesian filter before it is a
join, a chain end, which relocation never moves)."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from mso.emu.controller import Emulator
from mso.examples.convoy.storage import DB_ENV, summary
from mso.scenario import load_scenario
from waits import patience, until

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


def seqs(db: Path, table: str) -> list[int]:
    if not db.exists():
        return []
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [r[0] for r in conn.execute(f"SELECT seq FROM {table}")]
    except sqlite3.OperationalError:  # not created yet
        return []
    finally:
        conn.close()


def scans(n: int) -> Any:
    """A status where the leader's laser has emitted ``n`` scans: the convoy's world moves on
    its sensors' clock (a scan's sequence number), not the host's."""
    return lambda st: st["N1"]["apps"]["convoy"]["vertices"]["laser"]["emitted"] >= n


def test_convoy_rows_in_sqlite_equal_events_emitted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    db = tmp_path / "convoy.sqlite"
    monkeypatch.setenv(DB_ENV, str(db))  # the node processes inherit it
    doc = (EXAMPLES / "convoy.yaml").read_text(encoding="utf-8")

    async def run() -> tuple[dict[str, Any], dict[str, int], str]:
        emu = Emulator(load_scenario(EXAMPLES / "convoy-line.yaml"))
        await emu.start()
        try:
            reply = await emu.deploy(doc, "convoy.yaml", "N1")
            assert reply.ok, reply.error
            await until(lambda: emu.status("N1"), scans(20), 20, "4 s of scans (the world's)")
            host = reply.placement["target_map"]
            target = "N2" if host != "N2" else "N3"
            moved = await emu.relocate("convoy", "target_map", target=target)
            assert moved.ok, moved.error
            await until(lambda: emu.status("N1"), scans(40), 20, "4 s more of scans")
            status = await emu.status()
            sources = status["N1"]["apps"]["convoy"]["vertices"]
            emitted = {v: sources[v]["emitted"] for v in ("laser", "visible_camera")}
            deadline = asyncio.get_running_loop().time() + patience(10.0)
            while asyncio.get_running_loop().time() < deadline:  # what was in flight lands
                traj, tgt = seqs(db, "trajectory"), seqs(db, "targets")
                if (
                    len(set(traj)) >= emitted["laser"]
                    and len(set(tgt)) >= emitted["visible_camera"]
                ):
                    break
                await asyncio.sleep(0.1)  # poll period
            return status, emitted, target
        finally:
            await emu.stop()

    status, emitted, target = asyncio.run(run())
    assert "target_map" in status[target]["apps"]["convoy"]["vertices"]
    assert emitted["laser"] >= 30 and emitted["visible_camera"] >= 3
    s = summary(db)
    # every laser scan emitted became one trajectory row, every frame pair one target row:
    # no gap, no repeat (rows beyond the count are scans emitted after it was read)
    for table, source in (("trajectory", "laser"), ("targets", "visible_camera")):
        cov = s[table]
        assert cov["first"] == 0 and cov["gaps"] == 0 and cov["repeats"] == 0, cov
        assert cov["rows"] >= emitted[source], (table, cov, emitted)
    errors = sum(
        v["errors"] for n in status.values() for v in n["apps"]["convoy"]["vertices"].values()
    )
    assert errors == 0
    assert s["localization_error_m_max"] < 0.3
    # the first survivor, seen before and after the move, is found, and nothing else
    assert s["survivors_found"] == s["survivors_in_view"] >= 1 and s["phantom_targets"] == 0
    assert s["delay_ms_p50"] is not None and s["delay_ms_p50"] < 1000
