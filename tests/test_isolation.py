"""``isolation: process``: a vertex runs in a child process of its node, gets its state moved
exactly like a thread's, and its stream loses nothing."""

from __future__ import annotations

import asyncio
import os
import signal
from pathlib import Path
from typing import Any

import pytest

from mso.errors import AppError
from mso.model.appfile import loads_app
from waits import until

TESTS = Path(__file__).resolve().parent
LINE3 = "name: l3\nnodes: {N1: {}, N2: {}, N3: {}}\nlinks: [[N1, N2], [N2, N3]]\n"
APP = """
name: iso
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 200,
        output: runtime_vertices:Num}
  count: {code: runtime_vertices:PidCounter, isolation: process, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N3}
edges: [[src, count], [count, sink]]
"""


def _vertices_importable(monkeypatch: pytest.MonkeyPatch) -> None:
    """Node processes import the test vertices from the tests directory."""
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))


async def _wait_for(emu: Any, check: Any) -> dict[str, Any]:
    """The overlay's status once ``check`` holds (see waits.until); a failure prints each
    node's vertices (state, crashes, stats), parked chains and failures, not the whole status."""
    return await until(emu.status, check, 20.0, "the status the test waits for", show=_apps)


def _apps(st: dict[str, Any]) -> dict[str, Any]:
    keep = ("state", "crashes", "restarts", "last_crash", "not_restarted", "stats", "errors")
    return {
        node: {
            "failed": s.get("failed_nodes"),
            "apps": {
                name: {
                    "parked": app.get("parked"),
                    "vertices": {
                        v: {k: x.get(k) for k in keep} for v, x in app["vertices"].items()
                    },
                }
                for name, app in s.get("apps", {}).items()
            },
        }
        for node, s in st.items()
    }


def test_isolation_is_validated_with_its_place() -> None:
    bad = APP.replace("isolation: process", "isolation: container")
    with pytest.raises(AppError, match=r"vertices\.count\.isolation.*thread, process"):
        loads_app(bad, file="iso.yaml")


def test_a_process_isolated_vertex_runs_apart_and_moves_with_its_state(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    _vertices_importable(monkeypatch)

    async def run() -> tuple[dict[str, Any], dict[str, int], list[Any]]:
        emu = Emulator(loads_scenario(LINE3), manage=False)
        await emu.start()
        try:
            reply = await emu.deploy(APP, "iso.yaml", "N1")
            assert reply.ok, reply.error
            pids = {n: node.process.pid for n, node in emu.nodes.items() if node.process}

            async def wait_for(check: Any) -> dict[str, Any]:
                return await _wait_for(emu, check)

            def counted(n: int) -> Any:
                return lambda st: (
                    (st["N3"]["apps"]["iso"]["vertices"]["sink"].get("stats") or {}).get("count", 0)
                    >= n
                )

            await wait_for(counted(200))
            home = reply.placement["count"]
            target = "N2" if home != "N2" else "N1"
            moved = await emu.relocate("iso", "count", target=target)
            assert moved.ok, moved.error

            def counts(st: dict[str, Any]) -> int:
                stats = st[target]["apps"]["iso"]["vertices"].get("count", {}).get("stats")
                return int((stats or {}).get("count", 0))

            # a vertex's stats come with its results, and the handover restores the state with
            # none: until the moved count has processed an event its stats say the count it
            # started with, 0 (a loaded run read them there: the sink had passed 600 before
            # the slow move was over)
            st = await wait_for(lambda st: counted(600)(st) and counts(st) >= 600)
            return st, pids, [home, target]
        finally:
            await emu.stop()

    st, pids, (home, target) = asyncio.run(run())
    count = st[target]["apps"]["iso"]["vertices"]["count"]
    assert count["stats"]["pid"] != pids[target]  # a child of the node, not the node
    # the count went on from the moved state: the sink's numbers (its count) have no gap nor
    # repeat across the move
    assert count["stats"]["count"] >= 600, (home, target, _apps(st))
    sink = st["N3"]["apps"]["iso"]["vertices"]["sink"]["stats"]
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0, sink
    assert sink["count"] == sink["next"]  # 0, 1, 2, ... with no gap and no repeat
    assert "count" not in st[home]["apps"]["iso"]["vertices"]


LINE2 = "name: l2\nnodes: {N1: {}, N2: {}}\nlinks: [[N1, N2]]\n"
CRASHY = """
name: {name}
vertices:
  src: {{code: runtime_vertices:CountingSource, pinned: N1, rate: 400,
        params: {{stall_at: {stall}, stall_s: 0.1}}, output: runtime_vertices:Num}}
  mid: {{code: runtime_vertices:ExitOn, isolation: process, pinned: N2,
        params: {params}, output: runtime_vertices:Num}}
  sink: {{code: runtime_vertices:Recorder, pinned: N2}}
edges: [[src, mid], [mid, sink]]
"""


def test_a_crashed_process_vertex_is_restored_in_place_and_loses_nothing(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``ok``'s child is SIGKILLed mid-stream, then (armed by the test once that crash shows)
    exits with code 3 on its next event: each time status counts the crash with its reason,
    the node stays up (nobody is declared failed) and a fresh child takes over: the sink gets
    every event once, in order. ``poison`` exits on event 300 every time, so each replay
    crashes it again: after MAX_RESTARTS restores it stays crashed, its chain is reported
    parked with the reason, and the sink has had exactly the events before it (the rest is
    held upstream). Its source stalls 0.1 s just before the fatal event, so that event reaches
    ``mid`` in one batch with those before it (as a loaded machine batches them): they still
    reach the sink, because a replay after a crash is fed one event at a time."""
    from mso.emu.controller import Emulator
    from mso.protocol.procedures.instance import MAX_RESTARTS
    from mso.scenario import loads_scenario

    _vertices_importable(monkeypatch)
    armed = tmp_path / "armed"  # ok's mid exits on its next event while this file exists

    async def run() -> tuple[list[dict[str, Any]], dict[str, Any]]:
        emu = Emulator(loads_scenario(LINE2), manage=False)
        await emu.start()
        try:
            for name, params, stall in (
                ("ok", f'{{seq: 0, armed: "{armed}"}}', -1),
                ("poison", "{seq: 300}", 296),
            ):
                app = CRASHY.format(name=name, params=params, stall=stall)
                reply = await emu.deploy(app, f"{name}.yaml", "N1")
                assert reply.ok, reply.error

            async def wait_for(check: Any) -> dict[str, Any]:
                return await _wait_for(emu, check)

            def v(st: dict[str, Any], app: str, vid: str) -> dict[str, Any]:
                got: dict[str, Any] = st["N2"]["apps"][app]["vertices"].get(vid, {})
                return got

            def sunk(st: dict[str, Any], app: str) -> int:
                return int((v(st, app, "sink").get("stats") or {}).get("count", 0))

            st = await wait_for(lambda st: sunk(st, "ok") >= 100)
            os.kill(v(st, "ok", "mid")["stats"]["pid"], signal.SIGKILL)
            seen = [await wait_for(lambda st: v(st, "ok", "mid").get("crashes", 0) >= 1)]
            armed.touch()  # the SIGKILL's crash is seen: now the exit, on the next event
            after = max(1200, sunk(seen[0], "ok") + 400)  # events that pass the exit's restore
            seen.append(
                await wait_for(
                    lambda st: (
                        v(st, "ok", "mid").get("crashes", 0) >= 2
                        and v(st, "ok", "mid").get("state") == "running"
                        and sunk(st, "ok") >= after
                    )
                )
            )
            seen.append(
                await wait_for(
                    lambda st: (  # and what it sent before its last crash has arrived
                        v(st, "poison", "mid").get("not_restarted", "")
                        and st["N2"]["apps"]["poison"]["parked"]
                        and sunk(st, "poison") >= 300
                    )
                )
            )
            return seen, await emu.status()
        finally:
            await emu.stop()

    (killed, exited, _poisoned), st = asyncio.run(run())
    assert "killed by SIGKILL" in killed["N2"]["apps"]["ok"]["vertices"]["mid"]["last_crash"]
    mid = exited["N2"]["apps"]["ok"]["vertices"]["mid"]
    assert (mid["crashes"], mid["restarts"]) == (2, 2), mid
    assert mid["last_crash"] == "N2: exit code 3"
    sink = exited["N2"]["apps"]["ok"]["vertices"]["sink"]["stats"]
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0, sink
    assert sink["count"] == sink["next"] >= 1200  # 0, 1, 2, ... with no gap and no repeat
    assert st["N2"]["apps"]["ok"]["vertices"]["mid"]["state"] == "running"
    poison = st["N2"]["apps"]["poison"]
    assert poison["vertices"]["mid"]["state"] == "crashed"
    assert poison["vertices"]["mid"]["crashes"] == MAX_RESTARTS + 1
    assert poison["vertices"]["mid"]["restarts"] == MAX_RESTARTS
    assert "exit code 3" in poison["vertices"]["mid"]["not_restarted"]
    assert list(poison["parked"].values()) == [poison["vertices"]["mid"]["not_restarted"]]
    psink = poison["vertices"]["sink"]["stats"]
    assert psink["count"] == psink["next"] == 300 and psink["repeats"] == 0, psink
    for node in ("N1", "N2"):  # the node never went down: everyone answers, nobody failed
        assert st[node]["failed_nodes"] == [] and st[node]["failures"] == []
        assert st[node]["illegal_transitions"] == 0 and st[node]["handler_errors"] == 0
