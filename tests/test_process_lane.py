"""The process-lane prototype: a vertex in a child process, only bytes crossing, same results
as the thread executor gives for the same effects."""

from __future__ import annotations

import asyncio
import os
import queue
import signal
from typing import Any

import msgspec
import pytest

from mso.model.app import Vertex
from mso.protocol import effects as fx
from mso.runtime.process_lane import ProcessExecutor, spec_of
from runtime_vertices import Num


def _collect(results: queue.SimpleQueue[fx.VertexResult], n: int) -> list[fx.VertexResult]:
    """Wait for ``n`` results (bounded: a missing result fails the test, it does not hang)."""
    return [results.get(timeout=30.0) for _ in range(n)]


def test_operator_feed_snapshot_restore_in_a_child() -> None:
    results: queue.SimpleQueue[fx.VertexResult] = queue.SimpleQueue()
    ex = ProcessExecutor(results.put, "spawn")
    vertex = Vertex("c", "runtime_vertices:Counter", input=Num, output=Num)
    ev = msgspec.msgpack.encode(Num(seq=9))
    try:
        ex.submit(fx.StartVertex(1, "app", vertex, "operator", {0: Num}))
        ex.submit(fx.FeedVertex(1, 0, [ev, ev, ev], 1.5))
        ex.submit(fx.SnapshotVertex(1, 7))
        ex.submit(fx.RestoreVertex(1, msgspec.msgpack.encode(None)))
        started, processed, snap = _collect(results, 3)
    finally:
        ex.shutdown(5.0)
    assert isinstance(started, fx.VertexStarted) and started.error == ""
    assert isinstance(processed, fx.VertexProcessed)
    assert (processed.edge, processed.count, processed.ts) == (0, 3, 1.5)
    decoded = [msgspec.msgpack.decode(p, type=Num).seq for p in processed.outputs]
    assert decoded == [0, 1, 2]  # the child's instance kept its state between events
    assert isinstance(snap, fx.VertexSnapshot) and snap.token == 7
    assert ex.instances == 0


def test_a_rated_source_runs_in_a_child() -> None:
    results: queue.SimpleQueue[fx.VertexResult] = queue.SimpleQueue()
    ex = ProcessExecutor(results.put, "spawn")
    vertex = Vertex("s", "runtime_vertices:CountingSource", rate=10.0, output=Num)
    try:
        ex.submit(fx.StartVertex(2, "app", vertex, "source"))
        ex.submit(fx.RunSource(2, 5, 3, 0.0))
        started, emitted = _collect(results, 2)
    finally:
        ex.shutdown(5.0)
    assert isinstance(started, fx.VertexStarted) and started.mode == "timer"
    assert isinstance(emitted, fx.VertexEmitted) and emitted.calls == 3
    assert [msgspec.msgpack.decode(p, type=Num).seq for p in emitted.outputs] == [5, 6, 7]


def test_code_given_as_an_object_is_refused() -> None:
    """Only import paths cross to the child: nothing is pickled."""
    start = fx.StartVertex(3, "app", Vertex("f", lambda e: e), "operator")
    with pytest.raises(ValueError, match="import paths"):
        spec_of(start)


def test_a_child_that_dies_unasked_is_reported_with_its_exit_status() -> None:
    """A SIGKILL and an ``os._exit(3)`` each come back as VertexCrashed, in words; a child
    told to stop is no crash; effects for a dead child are dropped, never raised."""
    results: queue.SimpleQueue[fx.VertexResult] = queue.SimpleQueue()
    ex = ProcessExecutor(results.put, "spawn")
    vertex = Vertex("x", "runtime_vertices:ExitOn", input=Num, output=Num, params={"seq": 5})
    ev = [msgspec.msgpack.encode(Num(seq=s)) for s in range(7)]
    try:
        for i in (1, 2, 3):
            ex.submit(fx.StartVertex(i, "app", vertex, "operator", {0: Num}))
        started = _collect(results, 3)
        assert all(isinstance(r, fx.VertexStarted) and not r.error for r in started)
        pid = ex.pid(1)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        (killed,) = _collect(results, 1)
        assert isinstance(killed, fx.VertexCrashed) and killed.instance == 1
        assert killed.reason == "killed by SIGKILL"
        ex.submit(fx.FeedVertex(1, 0, ev[:1], 0.0))  # to the dead child: dropped quietly
        ex.submit(fx.FeedVertex(2, 0, ev[:4], 0.0))
        ex.submit(fx.FeedVertex(2, 0, ev[4:], 0.0))  # seq 5: the child exits with code 3
        fed, exited = _collect(results, 2)
        assert isinstance(fed, fx.VertexProcessed) and fed.count == 4
        assert isinstance(exited, fx.VertexCrashed) and exited.instance == 2
        assert exited.reason == "exit code 3"
        ex.submit(fx.StopVertex(3, "undeploy"))
        ex.submit(fx.StopVertex(1, "crashed"))
        ex.submit(fx.StopVertex(2, "crashed"))
        assert ex.instances == 0
    finally:
        ex.shutdown(5.0)
    with pytest.raises(queue.Empty):  # the stopped child is not reported as a crash
        results.get(timeout=0.5)


class _CountingConn:
    """A lane's end of the pipe that counts the parent's writes."""

    def __init__(self, conn: Any) -> None:
        self.conn, self.writes = conn, 0

    def send_bytes(self, buf: bytes) -> None:
        self.writes += 1
        self.conn.send_bytes(buf)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.conn, name)


def test_the_jobs_of_one_loop_turn_reach_the_child_in_one_write() -> None:
    """Submitted on an event loop, a turn's jobs for a child are written at the turn's end in
    one write (a write lets another thread take the GIL, and on a loaded machine taking it back
    stopped the node's loop 25-65 ms a job: no heartbeats for over a second during a replay fed
    one event a job). The child still runs them one by one, in order."""
    results: queue.SimpleQueue[fx.VertexResult] = queue.SimpleQueue()
    ex = ProcessExecutor(results.put, "spawn")
    vertex = Vertex("c", "runtime_vertices:Counter", input=Num, output=Num)
    ev = msgspec.msgpack.encode(Num(seq=9))

    async def run() -> tuple[int, list[fx.VertexResult]]:
        loop = asyncio.get_running_loop()
        ex.submit(fx.StartVertex(1, "app", vertex, "operator", {0: Num}))
        (started,) = await loop.run_in_executor(None, _collect, results, 1)
        assert isinstance(started, fx.VertexStarted) and started.error == ""
        lane = ex._lanes[1]
        conn = lane.conn = _CountingConn(lane.conn)
        for i in range(10):  # one turn: a replay's events, one job each
            ex.submit(fx.FeedVertex(1, 0, [ev], float(i)))
        assert conn.writes == 0  # not yet: at the turn's end
        await asyncio.sleep(0)  # (the next turn: the flush ran before it)
        return conn.writes, await loop.run_in_executor(None, _collect, results, 10)

    try:
        writes, fed = asyncio.run(run())
    finally:
        ex.shutdown(5.0)
    assert writes == 1
    assert all(isinstance(r, fx.VertexProcessed) and r.count == 1 for r in fed)
    seqs = [msgspec.msgpack.decode(r.outputs[0], type=Num).seq for r in fed]  # type: ignore[union-attr]
    assert seqs == list(range(10))  # one result a job, in order, the state kept between them
