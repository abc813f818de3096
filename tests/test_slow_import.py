"""An app whose code takes seconds to import deploys without its nodes looking dead: the
driver imports it in a thread before the core loads the app, so heartbeats keep flowing."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any

import pytest

from waits import patience

TESTS = Path(__file__).resolve().parent
LINE3 = "name: l3\nnodes: {N1: {}, N2: {}, N3: {}}\nlinks: [[N1, N2], [N2, N3]]\n"
APP = """
name: slow
vertices:
  src: {code: slow_import_vertices:Source, pinned: N1, rate: 20,
        output: slow_import_vertices:Num}
  sink: {code: slow_import_vertices:Sink, pinned: N3}
edges: [[src, sink]]
"""


def test_a_slow_import_does_not_get_a_node_declared_failed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    path = os.environ.get("PYTHONPATH", "")  # node processes import the vertices from here
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))

    async def run() -> dict[str, Any]:
        emu = Emulator(loads_scenario(LINE3), manage=False)
        await emu.start()
        try:
            reply = await emu.deploy(APP, "slow.yaml", "N1")
            assert reply.ok, reply.error
            loop = asyncio.get_running_loop()
            deadline = loop.time() + patience(20.0)
            status: dict[str, Any] = {}
            while loop.time() < deadline:  # bounded poll until events reach the sink
                status = await emu.status()
                sink = status["N3"]["apps"]["slow"]["vertices"]["sink"].get("stats") or {}
                if sink.get("count", 0) >= 10:
                    break
                await asyncio.sleep(0.1)  # poll period, not synchronisation
            return status
        finally:
            await emu.stop()

    status = asyncio.run(run())
    for node, s in status.items():  # a 2 s import on every node, 0.5 s failure detection
        assert s["failures"] == [] and s["failed_nodes"] == [], (node, s["failures"])
    assert status["N3"]["apps"]["slow"]["vertices"]["sink"]["stats"]["count"] >= 10
