"""``mso demo``: the convoy on the emulated 4-robot line, then its log read back from SQLite.

Deploys examples/convoy.yaml on examples/convoy-demo.yaml (robot boards, a leader whose battery
is scaled down so its drain shows within the demo, CPU energy charged from measured CPU time),
prints the placement, then every few seconds each robot's battery and the relocations the
rules made; at the end it waits (bounded) for what is in flight to land and prints the summary
read back from the trailing robot's database: rows stored against events emitted, localization
error, survivors found against planted, end-to-end delay. Every node process is stopped.
"""

from __future__ import annotations

import asyncio
import os
import re
import sqlite3
import tempfile
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from mso.examples.convoy.storage import DB_ENV, summary

EXAMPLES = Path(__file__).resolve().parent.parent
APP_FILE = EXAMPLES / "convoy.yaml"
SCENARIO_FILE = EXAMPLES / "convoy-demo.yaml"
LEADER = "N1"


ROWS_OF = {"laser": "trajectory", "visible_camera": "targets"}  # source -> its table


def rows_below(db: Path, emitted: dict[str, int]) -> dict[str, int]:
    """Distinct rows of each table for the first ``emitted[source]`` events of its source:
    the sources keep emitting after the count was read, and rows of those later events are
    not part of the comparison (counting them read one row more than events emitted)."""
    out = dict.fromkeys(ROWS_OF, 0)
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    except sqlite3.OperationalError:
        return out
    try:
        for source, table in ROWS_OF.items():
            (n,) = conn.execute(
                f"SELECT COUNT(DISTINCT seq) FROM {table} "
                f"WHERE seq < (SELECT MIN(seq) FROM {table}) + ?",
                (emitted.get(source, 0),),
            ).fetchone()
            out[source] = int(n)
    except sqlite3.OperationalError:
        pass
    finally:
        conn.close()
    return out


def _battery_line(status: dict[str, Any], t: float) -> str:
    parts = []
    for node in sorted(status):
        mon = status[node]["monitor"]
        frac = mon.get("battery_fraction")
        level = "mains" if frac is None else f"{100 * frac:5.1f}%"
        parts.append(f"{node} {level} {mon['drain_w']:.3f} W")
    return f"t={t:5.1f}s  " + "  ".join(parts)


def _relocations(status: dict[str, Any]) -> list[str]:
    return [f"{n}: {d}" for n, st in sorted(status.items()) for d in st["management"]["done"]]


def _readable(done: str) -> str:
    """A rule's action as the demo prints it: without the node's clock reading and the policy's
    raw score vectors (the dashboard and `mso status --json` keep them)."""
    node, _, rest = done.partition(": ")
    rest = rest.split(" ", 1)[1] if rest[:1].isdigit() else rest  # "19490.0 relocate ..."
    return f"{node}: " + re.sub(r"score \([^)]*\) -> \([^)]*\) \(([^)]*)\)", r"\1", rest)


async def _run(console: Console, duration: float, db: Path, dashboard: bool) -> dict[str, Any]:
    from mso.emu.controller import Emulator
    from mso.scenario import load_scenario

    emu = Emulator(load_scenario(SCENARIO_FILE))
    await emu.start()
    loop = asyncio.get_running_loop()
    board: Any = None
    try:
        if dashboard:  # the live page, while the demo runs
            from mso.dashboard.server import start_dashboard

            nodes = list(emu.nodes)
            board = await start_dashboard(
                [emu.address(n) for n in nodes], emu.key, str(emu.name), "", 1.0,
                emu.node_positions, nodes,
            )  # fmt: skip
            emu.dashboard = board.url
            emu.write_state()
            console.print(
                f"dashboard: [bold]{board.url}[/bold] (open it now; it stops with the demo)"
            )
        reply = await emu.overlay("N1").deploy(APP_FILE)  # a refusal: one line, exit 2
        t0 = loop.time()
        table = Table(title=f"deployed in {reply.elapsed_ms:.0f} ms: vertex → robot")
        nodes = list(emu.nodes)
        for node in nodes:
            table.add_column(node)
        by_node = {n: [v for v, h in reply.placement.items() if h == n] for n in nodes}
        for i in range(max(len(v) for v in by_node.values())):
            table.add_row(*(by_node[n][i] if i < len(by_node[n]) else "" for n in nodes))
        console.print(table)
        seen: list[str] = []
        draining: set[str] = set()
        status: dict[str, Any] = {}
        while loop.time() - t0 < duration:
            await asyncio.sleep(min(3.0, max(0.1, duration - (loop.time() - t0))))
            status = await emu.status()
            console.print(_battery_line(status, loop.time() - t0), soft_wrap=True)
            for node in sorted(status):
                now_draining = node in status[node]["management"].get("draining", [])
                if now_draining != (node in draining):
                    draining ^= {node}
                    what = "its battery will die far sooner than its neighbours'"
                    console.print(
                        f"  {node} {'draining: ' + what if now_draining else 'no longer draining'}"
                    )
            for r in _relocations(status):
                if r not in seen:
                    seen.append(r)
                    console.print(
                        f"  [bold]relocation by the rules[/bold] {_readable(r)}", soft_wrap=True
                    )
        sources = {
            v: st["emitted"]
            for n in status.values()
            for v, st in n.get("apps", {}).get("convoy", {}).get("vertices", {}).items()
            if v in ("laser", "visible_camera")
        }
        stored = rows_below(db, sources)
        for _ in range(100):  # bounded: what was in flight lands within 10 s
            if all(stored[v] >= n for v, n in sources.items()):
                break
            await asyncio.sleep(0.1)
            stored = rows_below(db, sources)
        return {"status": status, "emitted": sources, "stored": stored, "relocations": seen}
    finally:
        if board is not None:
            await board.stop()
        await emu.stop()


def run_demo(console: Console, duration: float, dashboard: bool = False) -> dict[str, Any]:
    """Run the demo; returns the summary (also printed)."""
    with tempfile.TemporaryDirectory(prefix="mso-demo-") as tmp:
        db = Path(tmp) / "convoy.sqlite"
        old = os.environ.get(DB_ENV)
        os.environ[DB_ENV] = str(db)  # the node processes inherit it
        try:
            out = asyncio.run(_run(console, duration, db, dashboard))
        finally:
            if old is None:
                os.environ.pop(DB_ENV, None)
            else:
                os.environ[DB_ENV] = old
        s = summary(db)
    emitted, stored = out["emitted"], out["stored"]
    table = Table(title="read back from the trailing robot's SQLite log")
    table.add_column("what")
    table.add_column("value", justify="right")
    for source, kind in ROWS_OF.items():
        cov = s[kind]
        table.add_row(
            f"{kind} rows stored / {source} events emitted",
            f"{stored.get(source, 0)} / {emitted.get(source, 0)}"
            + ("" if cov["repeats"] == cov["gaps"] == 0 else f" ({cov['gaps']} gaps, "
               f"{cov['repeats']} repeats)"),
        )  # fmt: skip
    err = s["localization_error_m_max_straight"]
    table.add_row("localization error, straight part (max)", "-" if err is None else f"{err:.2f} m")
    table.add_row("localization error (mean)", f"{s['localization_error_m_mean'] or 0:.2f} m")
    table.add_row(
        "survivors found / in view so far / planted",
        f"{s['survivors_found']} / {s['survivors_in_view']} / {s['survivors_planted']}"
        + (f" ({s['phantom_targets']} phantom)" if s["phantom_targets"] else ""),
    )
    p50, p99 = s["delay_ms_p50"], s["delay_ms_p99"]
    table.add_row("end-to-end delay p50 / p99", f"{p50 or 0:.1f} / {p99 or 0:.1f} ms")
    off = [r for r in out["relocations"] if r.startswith(f"{LEADER}: ")]
    table.add_row(
        "relocations by the rules (off the leader)", f"{len(out['relocations'])} ({len(off)})"
    )
    console.print(table)
    return {
        "summary": s,
        "emitted": emitted,
        "stored": stored,
        "relocations": out["relocations"],
        "off_leader": off,
    }
