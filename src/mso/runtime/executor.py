"""The executor: vertex code runs in worker threads, never on the control plane.

The node core emits vertex effects (start, feed, run a source, credit, snapshot, stop); the
driver hands them to :meth:`ThreadExecutor.submit`, which queues each on its instance's own
thread and returns at once. So heartbeats, probes, markers and acks are never queued behind
user code: a vertex that computes for seconds only delays its own events. Results come back
through ``deliver`` (called from worker threads; the asyncio driver coalesces them into one
loop wake-up per burst). Per instance, effects run in order; instances run concurrently.

Why threads: a worker thread per instance keeps state handover exact (the instance lives in one
place) and costs no serialisation; CPython switches the GIL every few milliseconds, so the
event loop keeps its heartbeats while a pure-Python vertex computes (docs/benchmarks.md has the
thread-versus-process measurements). A hung vertex holds only its own thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any

from mso.protocol import effects as fx
from mso.runtime.worker import VertexWorker

PULL_BATCH = 256  # calls a free-running source makes per result at most
PULL_BUDGET_S = 0.005  # ... or wall time, so its events leave in timely batches


class _Lane:
    """One instance's worker thread and its queue of effects."""

    def __init__(self, start: fx.StartVertex, deliver: Callable[[fx.VertexResult], None]) -> None:
        self.worker = VertexWorker(start)
        self.deliver = deliver
        self.jobs: queue.SimpleQueue[object] = queue.SimpleQueue()
        self.credit = 0
        self.loop_source = False
        self.thread = threading.Thread(
            target=self._run, name=f"mso-{start.app}-{start.vertex.id}", daemon=True
        )

    def _run(self) -> None:
        worker = self.worker
        while True:
            if self.loop_source and self.credit > 0 and not worker.ended and self.jobs.empty():
                res = worker.pull(min(self.credit, PULL_BATCH), PULL_BUDGET_S)
                self.credit -= res.calls
                self.deliver(res)
                continue
            job = self.jobs.get()
            if isinstance(job, fx.StartVertex):
                started = worker.open()
                self.loop_source = started.mode == "loop"
                self.deliver(started)
            elif isinstance(job, fx.FeedVertex):
                self.deliver(worker.feed(job))
            elif isinstance(job, fx.RunSource):
                self.deliver(worker.run_source(job.first, job.count, job.now))
            elif isinstance(job, fx.Credit):
                self.credit += job.count
            elif isinstance(job, fx.RestoreVertex):
                worker.restore(job.state)
            elif isinstance(job, fx.SnapshotVertex):
                self.deliver(worker.snapshot(job.token))
            elif isinstance(job, fx.StopVertex):
                worker.close()
                return


class ThreadExecutor:
    """Runs vertex effects on per-instance threads; ``deliver`` receives the results."""

    def __init__(self, deliver: Callable[[fx.VertexResult], None]) -> None:
        self.deliver = deliver
        self._lanes: dict[int, _Lane] = {}

    def submit(self, eff: fx.VertexEffect) -> None:
        if isinstance(eff, fx.StartVertex):
            lane = self._lanes[eff.instance] = _Lane(eff, self.deliver)
            lane.jobs.put(eff)
            lane.thread.start()
            return
        lane_or_none = self._lanes.get(eff.instance)
        if lane_or_none is None:
            return  # already stopped: nothing to do
        lane_or_none.jobs.put(eff)
        if isinstance(eff, fx.StopVertex):
            del self._lanes[eff.instance]

    @property
    def instances(self) -> int:
        return len(self._lanes)

    def shutdown(self, timeout: float = 1.0) -> None:
        """Stop every instance (their ``close()`` hooks run); wait a little for them."""
        lanes = list(self._lanes.values())
        self._lanes.clear()
        for lane in lanes:
            lane.jobs.put(fx.StopVertex(lane.worker.start.instance, "shutdown"))
        for lane in lanes:
            lane.thread.join(timeout / max(1, len(lanes)))


class Executor:
    """The node's executor: each instance on a thread of this process, or — for a vertex
    with ``isolation: process`` — in a child process of its own (``mso.runtime.process_lane``,
    started on first use). One interface for the driver; results go to ``deliver`` either way."""

    def __init__(self, deliver: Callable[[fx.VertexResult], None]) -> None:
        self.deliver = deliver
        self.threads = ThreadExecutor(deliver)
        self.processes: Any = None  # a ProcessExecutor once a vertex asks for one
        self._in_process: set[int] = set()

    def submit(self, eff: fx.VertexEffect) -> None:
        if isinstance(eff, fx.StartVertex) and eff.vertex.isolation == "process":
            try:
                if self.processes is None:
                    from mso.runtime.process_lane import ProcessExecutor

                    self.processes = ProcessExecutor(self.deliver)
                self.processes.submit(eff)
            except (ValueError, OSError) as exc:  # code given as an object, no process left
                error = f"cannot start {eff.vertex.id!r} in a process of its own: {exc}"
                self.deliver(fx.VertexStarted(eff.instance, error=error))
                return
            self._in_process.add(eff.instance)
            return
        if eff.instance in self._in_process:
            self.processes.submit(eff)
            if isinstance(eff, fx.StopVertex):
                self._in_process.discard(eff.instance)
            return
        self.threads.submit(eff)

    def pid(self, instance: int) -> int | None:
        """The child process running ``instance`` (None on a thread): tests kill it."""
        if instance not in self._in_process or self.processes is None:
            return None
        pid: int | None = self.processes.pid(instance)
        return pid

    @property
    def instances(self) -> int:
        return self.threads.instances + len(self._in_process)

    def shutdown(self, timeout: float = 1.0) -> None:
        self.threads.shutdown(timeout)
        if self.processes is not None:
            self.processes.shutdown(timeout)
        self._in_process.clear()
