"""``mso demo``: the convoy on the emulated 4-robot line, each of the paper's three
reconfigurations happening for a reason the viewer sees, then its log read back from SQLite.

Deploys examples/convoy.yaml on examples/convoy-demo.yaml (robot boards; a leader whose battery
is scaled down so that it drains within the demo; a link that appears 8 s in and changes a
chain's route; a robot whose nearly empty battery stops it about 40 s in), plays the scenario's
changes, prints every few seconds each robot's battery and drain (with what its vertex code's
CPU takes) and, as they happen, each move with who asked and how long it took: the rules'
relocations off draining robots, the chain remap after the route change, the recovery after the
robot stopped. At the end it waits (bounded) for what is in flight to land and prints the
summary read back from the trailing robot's database (rows stored against events emitted:
nothing lost, the reconfigurations included; localization error; survivors; delay) and the
reconfigurations by kind. Every node process is stopped.
"""

from __future__ import annotations

import asyncio
import os
import sqlite3
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.table import Table

from mso.errors import MsoError
from mso.examples.convoy.storage import DB_ENV, summary

if TYPE_CHECKING:
    from mso.scenario import Scenario

EXAMPLES = Path(__file__).resolve().parent.parent
APP_FILE = EXAMPLES / "convoy.yaml"
SCENARIO_FILE = EXAMPLES / "convoy-demo.yaml"
# the paper's split: the story (the rules shed the leader's laser pipeline, a route change
# remaps, a recovery) starts from it; the default bytes split puts the pipeline near where the
# rules take it (docs/benchmarks.md)
PLANNER = "paper"
MIN_SHOWN_S = 3.0  # the demo runs at least this long after its deploy (three status polls)
LEADER = "N1"


ROWS_OF = {"laser": "trajectory", "visible_camera": "targets"}  # source -> its table
KINDS = {  # the paper's three reconfigurations, as the summary counts them
    "relocation": "relocations (§3.4.1)",
    "remap": "chain remaps (§3.4.2)",
    "recovery": "recoveries: global remaps after a failure (§3.4.3)",
}


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


def _battery_line(status: dict[str, Any], t: float, cpu_w: dict[str, float]) -> str:
    """Each robot's battery and drain, and of that drain what its vertex code's CPU takes."""
    parts = []
    for node in sorted(status):
        mon = status[node]["monitor"]
        frac = mon.get("battery_fraction")
        level = "mains" if frac is None else f"{100 * frac:5.1f}%"
        cpu = f" (CPU {1000 * cpu_w[node]:.0f} mW)" if node in cpu_w else ""
        parts.append(f"{node} {level} {mon['drain_w']:.3f} W{cpu}")
    return f"t={t:5.1f}s  " + "  ".join(parts)


class CpuWatts:
    """Each robot's vertex CPU power between two status samples (its monitor counts the energy
    the vertex code's CPU time cost; the rest of the drain is the board's idle and the radio)."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[float, float]] = {}

    def sample(self, status: dict[str, Any], t: float) -> dict[str, float]:
        out = {}
        for node, st in status.items():
            joules = float(st["monitor"].get("cpu_energy_j", 0.0))
            last = self._last.get(node)
            if last is not None and t > last[0] and joules >= last[1]:
                out[node] = (joules - last[1]) / (t - last[0])
            self._last[node] = (t, joules)
        return out


def kind_of(line: str) -> str:
    """Which of the paper's reconfigurations a told move is (its status record's words)."""
    if "(recovery)" in line or ": recovery " in line or "recovery after" in line:
        return "recovery"
    if ": remap " in line or "(remap)" in line:
        return "remap"
    return "relocation"


def _story(scenario: Scenario) -> list[str]:
    """What the viewer should watch for, from the scenario itself."""
    from mso.scenario.format import LinkChange

    net = scenario.network
    out = []
    leader = net.nodes[LEADER]
    if leader.battery_wh is not None:
        out.append(
            f"{LEADER}, the leader, runs on {leader.battery_wh:g} Wh: it drains far sooner than "
            "its neighbour, so the rules relocate work off it (a relocation, §3.4.1)"
        )
    for c in scenario.changes:
        if isinstance(c, LinkChange) and c.up:
            out.append(
                f"t={c.at:g} s: a link {c.a}-{c.b} appears, routes between them change, and a "
                "chain whose route changed is remapped onto its new one (a chain remap, §3.4.2)"
            )
    for n, spec in net.nodes.items():
        if n != LEADER and spec.battery_wh is not None and spec.battery_wh < 0.1:
            out.append(
                f"{n} runs on a nearly empty battery ({spec.battery_wh:g} Wh): when it "
                "empties, it stops (fail-stop); its neighbours detect it and the chains it "
                "touched are remapped onto the others (a recovery: the global remap, §3.4.3)"
            )
    return out


async def _run(console: Console, duration: float, db: Path, dashboard: bool) -> dict[str, Any]:
    from rich.markup import escape

    from mso.cli.story import MoveWatch
    from mso.emu.controller import Emulator
    from mso.scenario import load_scenario
    from mso.scenario.format import LinkChange

    scenario = load_scenario(SCENARIO_FILE)
    told: list[tuple[float, str]] = []

    def tell(at: float, text: str) -> None:
        told.append((at, text))
        console.print(f"t={at:5.1f}s  {escape(text)}", soft_wrap=True)

    for line in _story(scenario):
        console.print(f"  - {line}", soft_wrap=True)
    emu = Emulator(scenario)
    await emu.start()
    emu.tell = tell
    player = asyncio.create_task(emu.play())  # the scripted route change
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
        reply = await emu.overlay(LEADER).deploy(APP_FILE, planner=PLANNER)  # refused: exit 2
        table = Table(title=f"deployed in {reply.elapsed_ms:.0f} ms: vertex → robot")
        nodes = list(emu.nodes)
        for node in nodes:
            table.add_column(node)
        by_node = {n: [v for v, h in reply.placement.items() if h == n] for n in nodes}
        for i in range(max(len(v) for v in by_node.values())):
            table.add_row(*(by_node[n][i] if i < len(by_node[n]) else "" for n in nodes))
        console.print(table)
        watch, cpu = MoveWatch(), CpuWatts()
        watch.placed("convoy", reply.placement)
        changes = [c for c in scenario.changes if isinstance(c, LinkChange)]
        draining: set[str] = set()
        status: dict[str, Any] = {}
        # on the run's clock (the scripted changes' too), but never ending before it showed the
        # app running: a start and deploy that took the whole duration (4 node processes on a
        # loaded machine) left no status, no battery line and no event to count
        end = max(emu.t0 + duration, loop.time() + MIN_SHOWN_S)
        polls = 0
        while loop.time() < end:  # moves told within a second; batteries every 3 s
            await asyncio.sleep(min(1.0, max(0.1, end - loop.time())))
            while changes and changes[0].at <= emu.now():
                c = changes.pop(0)
                tell(c.at, f"link {c.a}-{c.b} {'up' if c.up else 'down'} (scripted)")
            try:
                status = await emu.status()
            except MsoError as exc:
                tell(emu.now(), f"status: {exc}")
                continue
            now = emu.now()
            for at, line in watch.moves(status, "convoy", now):
                tell(at, line)
            for node in sorted(status):
                now_draining = node in status[node]["management"].get("draining", [])
                if now_draining != (node in draining):
                    draining ^= {node}
                    what = "its battery will die far sooner than its neighbours'"
                    said = "draining: " + what if now_draining else "no longer draining"
                    tell(now, f"{node} {said}")
            polls += 1
            if polls % 3 == 0 or loop.time() >= end:
                line = _battery_line(status, now, cpu.sample(status, now))
                console.print(line, soft_wrap=True)
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
        # the moves (a remap that kept every vertex where it ran moved nothing: told, not counted)
        moves = [
            (at, text)
            for at, text in told
            if text.startswith("convoy: ") and not text.startswith("convoy: remap unchanged")
        ]
        return {
            "status": status,
            "emitted": sources,
            "stored": stored,
            "moves": moves,
            "emptied": sorted(emu.emptied),
            "told": told,
        }
    finally:
        player.cancel()
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
    lost = sum(max(0, n - stored.get(v, 0)) for v, n in emitted.items())
    table.add_row("events lost, the reconfigurations included", str(lost))
    kinds = {k: [m for m in out["moves"] if kind_of(m[1]) == k] for k in KINDS}
    for k, label in KINDS.items():
        table.add_row(label, str(len(kinds[k])))
    if out["emptied"]:
        table.add_row("stopped by an empty battery (fail-stop)", ", ".join(out["emptied"]))
    console.print(table)
    if out["moves"]:
        console.print("the reconfigurations, who asked and how long each took:")
        for at, text in out["moves"]:
            console.print(f"  t={at:5.1f}s  {text}", soft_wrap=True, markup=False)
    return {
        "summary": s,
        "emitted": emitted,
        "stored": stored,
        "moves": out["moves"],
        "kinds": {k: [text for _, text in v] for k, v in kinds.items()},
        "emptied": out["emptied"],
        "lost": lost,
    }
