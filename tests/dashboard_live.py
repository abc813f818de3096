"""A running emulation of the convoy with its dashboard, on an event loop in a thread of its own,
so a test can drive it with blocking clients (urllib, a browser)."""

from __future__ import annotations

import asyncio
import json
import threading
import time
import urllib.request
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mso.examples
from mso.dashboard.server import Dashboard
from mso.emu.controller import Emulator
from mso.emu.overlays import state_file
from mso.scenario import loads_scenario
from waits import patience

EXAMPLES = Path(mso.examples.__file__).parent  # the bundled app and scenario files
KEY = "dashboard-test-overlay-key-4f1c"


@dataclass
class LiveDashboard:
    loop: asyncio.AbstractEventLoop
    thread: threading.Thread
    emu: Emulator
    board: Dashboard
    url: str = ""
    state_file: Path = field(default_factory=Path)

    def run(self, coro: Any, timeout: float = 60.0) -> Any:
        fut: Future[Any] = asyncio.run_coroutine_threadsafe(coro, self.loop)
        return fut.result(timeout)

    def view(self) -> dict[str, Any]:
        with urllib.request.urlopen(self.url + "api/view", timeout=10) as r:
            doc: dict[str, Any] = json.loads(r.read())
            return doc

    def wait_for(
        self, check: Callable[[dict[str, Any]], bool], timeout: float = 15.0
    ) -> dict[str, Any]:
        """The first view (polled each update) for which ``check`` holds."""
        deadline = time.monotonic() + patience(timeout)
        while True:
            view = self.view()
            if view.get("apps") and check(view):
                return view
            if time.monotonic() > deadline:
                raise AssertionError(f"no such view within {timeout} s; last: {view}")
            self.run(self.board.wait_update(5.0))

    def stop(self) -> None:
        async def down() -> None:
            await self.board.stop()
            await self.emu.stop()

        try:
            self.run(down())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10)


# where the robots stand (metres): a zig-zag along a road, so a page that lays the topology out
# from positions draws it differently from one that lays it out by hops (all on one row)
POSITIONS = {"N1": (0, 0), "N2": (100, 40), "N3": (200, 0), "N4": (300, 40)}


def convoy_line_with_positions() -> str:
    """The bundled 4-robot line, its explicit links kept, each robot given a position."""
    text = (EXAMPLES / "convoy-line.yaml").read_text()
    for n, (x, y) in POSITIONS.items():
        assert f"  {n}: {{}}" in text, n
        text = text.replace(f"  {n}: {{}}", f"  {n}: {{pos: [{x}, {y}]}}")
    return text


def start_live(interval: float = 0.5, manage: bool = False) -> LiveDashboard:
    """The convoy on the 4-robot line, deployed from N1, rules off (only the test moves
    vertices), the dashboard on a free loopback port."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    emu = Emulator(loads_scenario(convoy_line_with_positions()), key=KEY, manage=manage)

    async def up() -> Dashboard:
        await emu.start()
        doc = (EXAMPLES / "convoy.yaml").read_text()
        reply = await emu.deploy(doc, "convoy.yaml", "N1")
        assert reply.ok, reply.error
        board = Dashboard(
            [emu.address(n) for n in emu.nodes], KEY, name=str(emu.name), interval=interval,
            positions=emu.node_positions, expected=list(emu.nodes),
        )  # fmt: skip
        emu.dashboard = await board.start()
        emu.write_state()
        await board.wait_update(10.0)
        return board

    try:
        board = asyncio.run_coroutine_threadsafe(up(), loop).result(60)
    except BaseException:
        asyncio.run_coroutine_threadsafe(emu.stop(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        raise
    live = LiveDashboard(loop, thread, emu, board, board.url, state_file(str(emu.name)))
    return live
