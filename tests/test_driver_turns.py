"""The driver runs a cheap vertex's jobs in the turn of the loop that made them: a read's frames
or a timer's tick are handled, then the inline jobs they queued run before the turn ends (no
turn of their own: no epoll_wait, no handle; docs/benchmarks.md's 2-hop path trace). Jobs
queued elsewhere (a client's request, a worker thread's result) still get a turn of their own."""

from __future__ import annotations

import asyncio
import threading

import pytest

from mso.client import overlay_key
from mso.node import driver as d
from mso.node.core import NodeCore
from mso.protocol import messages as m


def make(monkeypatch: pytest.MonkeyPatch) -> tuple[d.NodeDriver, list[str]]:
    driver = d.NodeDriver(NodeCore("N1"), "127.0.0.1", 0, overlay_key("k"))
    ran: list[str] = []
    monkeypatch.setattr(driver.executor, "run_inline", lambda: ran.append("inline"))
    return driver, ran


def test_the_jobs_a_read_makes_run_when_its_frames_are_handled(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def run() -> None:
        driver, ran = make(monkeypatch)

        def receive(src: str, msg: m.Message, now: float) -> list[object]:
            driver._schedule_inline()  # as the executor does for a cheap instance's feed
            ran.append(f"frame from {src}")
            return []

        monkeypatch.setattr(driver.core, "receive", receive)
        ack = m.Ack("app", 0, 0, 1)
        driver._receive("N2", ack)
        driver._receive("N3", ack)  # two frames of one read: one inline turn after both
        assert ran == ["frame from N2", "frame from N3"]
        driver._read_done()  # the transport, at the end of the read
        assert ran == ["frame from N2", "frame from N3", "inline"]
        await asyncio.sleep(0)  # nothing was left for a later turn
        await asyncio.sleep(0)
        assert ran.count("inline") == 1

    asyncio.run(run())


def test_a_timer_runs_the_jobs_it_makes_before_it_returns(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def run() -> None:
        driver, ran = make(monkeypatch)

        def on_timer(key: object, now: float) -> list[object]:
            driver._schedule_inline()  # a rated source's tick asks for a run
            return []

        monkeypatch.setattr(driver.core, "on_timer", on_timer)
        driver._fire("tick")
        assert ran == ["inline"]

    asyncio.run(run())


def test_jobs_made_outside_a_read_or_a_timer_get_a_turn_of_their_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def run() -> None:
        driver, ran = make(monkeypatch)
        driver._schedule_inline()  # e.g. while a worker thread's results are drained
        assert ran == []
        for _ in range(3):
            await asyncio.sleep(0)
        assert ran == ["inline"]

    asyncio.run(run())


def test_a_prepare_that_overtakes_its_apps_sync_while_it_warms_follows_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Only the nodes that take part in an app hold it (issue 24.1): a restore's target is
    sent the app (``AppSync``) just ahead of its ``Prepare``. The sync of an app new to the
    node is held while its imports warm in a thread; the ``Prepare`` behind it must wait for it,
    or the target answers "does not run app" (the restore failed, the recovery ran twice)."""

    async def run() -> None:
        driver, _ = make(monkeypatch)
        imported = threading.Event()
        monkeypatch.setattr(d, "warm_imports", lambda document: imported.wait(10))
        got: list[str] = []
        both = asyncio.Event()

        def receive(src: str, msg: m.Message, now: float) -> list[object]:
            got.append(type(msg).__name__)
            if len(got) == 2:
                both.set()
            return []

        monkeypatch.setattr(driver.core, "receive", receive)
        sync = m.AppSync("pipe", "N1", "name: pipe", 1, {"mid": "N2"})
        driver._receive("N1", sync)
        driver._receive("N1", m.Prepare("pipe", "mid", 7, restore=True))
        driver._read_done()
        assert got == []  # the sync still warms: the prepare waits behind it
        imported.set()
        await asyncio.wait_for(both.wait(), 10)
        assert got == ["AppSync", "Prepare"]

    asyncio.run(run())
