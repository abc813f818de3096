"""The driver runs a cheap vertex's jobs in the turn of the loop that made them: a read's frames
or a timer's tick are handled, then the inline jobs they queued run before the turn ends (no
turn of their own: no epoll_wait, no handle; docs/benchmarks.md's 2-hop path trace). Jobs
queued elsewhere (a client's request, a worker thread's result) still get a turn of their own."""

from __future__ import annotations

import asyncio

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
