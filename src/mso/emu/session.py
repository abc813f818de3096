"""Entry points for Python code: an emulated overlay run beside the caller, and a simulation.

    from mso.emu.session import Emulation, simulate

    with Emulation("examples/convoy-line.yaml", app="examples/convoy.yaml") as emu:
        emu.overlay.relocate("convoy", "scan_matcher", direction="upstream")
        emu.fail("N3")                      # the emulator's own commands
        print(emu.overlay.status()["N4"]["apps"]["convoy"]["vertices"]["storage"])
    print(emu.story)                        # what happened, seconds after the start

    report = simulate("examples/convoy-line.yaml", "examples/convoy.yaml", duration=30)

:class:`Emulation` runs the user-space emulator (one ``mso node`` process per scenario node,
the scenario's timeline played) on an event loop of its own in a background thread, so plain
blocking code drives it; leaving the ``with`` stops every node. :func:`simulate` is
``mso simulate``: the same node code in virtual time, its report as a dict.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from mso.api import Overlay, deploy_request
from mso.errors import MsoError

if TYPE_CHECKING:
    from mso.emu.controller import Emulator
    from mso.model.app import App
    from mso.protocol import messages as m
    from mso.scenario import Scenario

T = TypeVar("T")
START_S = 60.0  # the nodes start and the app deploys within this (a loaded machine is slow)


def _scenario(scenario: Scenario | str | Path) -> Scenario:
    from mso.scenario import Scenario, load_scenario

    return scenario if isinstance(scenario, Scenario) else load_scenario(scenario)


class Emulation:
    """An emulated overlay, running until :meth:`stop` (or the end of a ``with``).

    ``app`` (an :class:`mso.App`, an app file's path or its text) is deployed from the first
    node once every node is up; ``deployed`` is its reply. ``overlay`` is an
    :class:`mso.api.Overlay` through the first node; :meth:`fail`, :meth:`restart`,
    :meth:`cut`, :meth:`heal` and :meth:`move` are the emulator's faults and commands, told in
    ``story`` with the run's clock (seconds after the start) as its console tells them."""

    def __init__(
        self,
        scenario: Scenario | str | Path,
        *,
        app: App | str | Path | None = None,
        name: str | None = None,
        manage: bool = True,
        heartbeat_s: float | None = None,
        dead_after_s: float | None = None,
        play: bool = True,
    ) -> None:
        from mso.emu.controller import Emulator

        self.scenario = _scenario(scenario)
        self._deploy = deploy_request(app) if app is not None else None  # errors first
        self.emulator: Emulator = Emulator(
            self.scenario,
            name=name,
            manage=manage,
            heartbeat_s=heartbeat_s,
            dead_after_s=dead_after_s,
        )
        self._play = play
        self.deployed: m.DeployReply | None = None
        self._loop = asyncio.new_event_loop()
        self._thread: threading.Thread | None = None
        self._player: asyncio.Task[None] | None = None
        self._overlay: Overlay | None = None

    # -- running -------------------------------------------------------------------------
    def start(self, timeout: float = START_S) -> Emulation:
        """Start every node (and deploy the app); returns once they answer."""
        if self._thread is not None:
            raise MsoError("this emulation was started already")
        self._thread = threading.Thread(target=self._loop.run_forever, name="mso-emulation")
        self._thread.daemon = True
        self._thread.start()
        try:
            self._call(self._start(), timeout)
        except BaseException:
            self.stop()
            raise
        return self

    async def _start(self) -> None:
        emu = self.emulator
        await emu.start()
        if self._play:
            self._player = asyncio.create_task(emu.play())
        if self._deploy is not None:
            origin = next(iter(emu.nodes))
            self.deployed = await emu.overlay(origin).deploy_request(self._deploy)

    def stop(self) -> None:
        """Stop every node process and the loop (again: nothing)."""
        if self._thread is None or not self._loop.is_running():
            return
        try:
            self._call(self._stop(), START_S)
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
            self._loop.close()

    async def _stop(self) -> None:
        if self._player is not None:
            self._player.cancel()
        await self.emulator.stop()

    def __enter__(self) -> Emulation:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _call(self, coro: Coroutine[Any, Any, T], timeout: float) -> T:
        """Run ``coro`` on the emulation's loop and wait for it (at most ``timeout`` s)."""
        if self._thread is None or not self._loop.is_running():
            coro.close()
            raise MsoError("the emulation is not running (start() it, or use `with`)")
        future = asyncio.run_coroutine_threadsafe(coro, self._loop)
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise MsoError(f"the emulator did not finish within {timeout:g} s") from None

    # -- what it offers ------------------------------------------------------------------
    @property
    def name(self) -> str:
        """The overlay's name (other ``mso`` commands find it by it)."""
        return str(self.emulator.name)

    @property
    def overlay(self) -> Overlay:
        """The overlay through its first node, as :class:`mso.api.Overlay`."""
        if self._overlay is None:
            first = next(iter(self.emulator.nodes), None)
            if first is None:
                raise MsoError("the emulation is not running (start() it, or use `with`)")
            self._overlay = Overlay(self.emulator.address(first), key=self.emulator.key)
        return self._overlay

    @property
    def story(self) -> list[tuple[float, str]]:
        """What happened (faults, commands, nodes that died), seconds after the start."""
        return list(self.emulator.story)

    @property
    def emptied(self) -> set[str]:
        """Nodes stopped by an empty battery (fail-stop)."""
        return set(self.emulator.emptied)

    def now(self) -> float:
        """Seconds since the run started (the clock of ``story``)."""
        return self._loop.time() - self.emulator.t0

    def status(self) -> dict[str, Any]:
        """Every reachable node's status (asked through each live node until one answers)."""
        return self._call(self.emulator.status(), 30.0)

    def fail(self, node: str) -> str:
        """Fail-stop ``node`` (SIGKILL); what the emulator did, in words."""
        return self._call(self.emulator.fail(node), 30.0)

    def restart(self, node: str) -> str:
        return self._call(self.emulator.restart(node), START_S)

    def cut(self, a: str, b: str) -> str:
        return self._call(self.emulator.cut(a, b), 30.0)

    def heal(self, a: str, b: str) -> str:
        return self._call(self.emulator.heal(a, b), 30.0)

    def move(self, node: str, x: float, y: float) -> str:
        return self._call(self.emulator.move(node, x, y), 30.0)


def simulate(
    scenario: Scenario | str | Path,
    app: App | str | Path,
    *,
    duration: float = 30.0,
    seed: int = 0,
    via: str | None = None,
    convergence_s: float = 0.0,
    manage: bool = True,
) -> dict[str, Any]:
    """``mso simulate`` from Python: the report (events per sink, moves, recoveries, failures,
    energy per node; ``mso simulate --json`` prints the same) of ``duration`` virtual seconds."""
    from mso.sim.play import simulate as run

    req = deploy_request(app)
    return run(
        _scenario(scenario), req.document, req.file, seed=seed, duration=duration,
        convergence_s=convergence_s, via=via, manage=manage,
    )  # fmt: skip
