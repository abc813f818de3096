"""``isolation: process``: a vertex runs in a child process of its node, gets its state moved
exactly like a thread's, and its stream loses nothing."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any

import pytest

from mso.errors import AppError
from mso.model.appfile import loads_app

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


def test_isolation_is_validated_with_its_place() -> None:
    bad = APP.replace("isolation: process", "isolation: container")
    with pytest.raises(AppError, match=r"vertices\.count\.isolation.*thread, process"):
        loads_app(bad, file="iso.yaml")


def test_a_process_isolated_vertex_runs_apart_and_moves_with_its_state(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    path = os.environ.get("PYTHONPATH", "")  # node processes import the vertices from here
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))

    async def run() -> tuple[dict[str, Any], dict[str, int], list[Any]]:
        emu = Emulator(loads_scenario(LINE3), manage=False)
        await emu.start()
        try:
            reply = await emu.deploy(APP, "iso.yaml", "N1")
            assert reply.ok, reply.error
            pids = {n: node.process.pid for n, node in emu.nodes.items() if node.process}
            loop = asyncio.get_running_loop()

            async def wait_for(check: Any) -> dict[str, Any]:
                deadline = loop.time() + 20.0
                while True:  # bounded poll of the overlay's status
                    st = await emu.status()
                    if check(st) or loop.time() > deadline:
                        return st
                    await asyncio.sleep(0.1)  # poll period, not synchronisation

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
            st = await wait_for(counted(600))
            return st, pids, [home, target]
        finally:
            await emu.stop()

    st, pids, (home, target) = asyncio.run(run())
    count = st[target]["apps"]["iso"]["vertices"]["count"]
    assert count["stats"]["pid"] != pids[target]  # a child of the node, not the node
    assert count["stats"]["count"] >= 600  # the count went on from the moved state
    sink = st["N3"]["apps"]["iso"]["vertices"]["sink"]["stats"]
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0, sink
    assert sink["count"] == sink["next"]  # 0, 1, 2, ... with no gap and no repeat
    assert "count" not in st[home]["apps"]["iso"]["vertices"]
