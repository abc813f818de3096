"""The executor: vertex code never blocks the control plane, and cheap vertices pay no hand-off.

The node core emits vertex effects (start, feed, run a source, credit, snapshot, stop); the
driver hands them to :meth:`ThreadExecutor.submit`, which returns at once. Each instance has a
worker thread; results come back through ``deliver`` (the asyncio driver coalesces those of the
threads into one loop wake-up per burst). Per instance, effects run in order; instances run
concurrently.

**Adaptive placement.** Crossing to a thread and back (a queue, a wake-up of the other CPU,
``call_soon_threadsafe``) costs tens of microseconds per effect, more than most vertices take
(docs/benchmarks.md, the data plane's profile). So an instance whose calls are measured in
microseconds runs *on the loop's thread*: the same :class:`VertexWorker`, called by
:meth:`ThreadExecutor.run_inline` in batches the driver schedules with ``call_soon``. Every
instance starts on its thread (a constructor may import or load for seconds); after
``CHEAP_JOBS`` jobs in a row that were cheap there (by CPU time alone: its wall time there is
mostly waiting for the GIL or a CPU) it moves to the loop, and the first job on the loop that
goes over budget (``CALL_BUDGET_S`` of CPU per call, ``JOB_BUDGET_S`` per job), or
``BLOCKED_JOBS`` in a row ``BLOCK_S`` off the CPU having given it up themselves (it blocks; the
kernel preempting the loop's thread on a loaded machine is not the vertex's doing, and one wait
may be for the GIL its thread still held), sends it back to its thread, each time needing twice
as many cheap jobs to return. Order and state are exact: an instance moves to the loop only when
its thread has finished every job it was given (its results are already queued ahead), and
moves back with its unrun jobs, in order, onto its thread's queue; the worker is only ever used
by one thread at a time. A free-running source (a read loop that may block), an ``isolation:
process`` instance and one that asked for ``isolation: thread`` never run on the loop. What a
move costs the loop is the jobs that went over budget; a job that took ``HEAVY_S`` keeps its
instance on its thread for good, so a vertex that turns slow stalls the loop once at most (code
that may block for longer than the liveness window at once, e.g. on I/O, says ``isolation:
thread``).

Why threads at all: a worker thread per instance keeps state handover exact (the instance lives
in one place) and costs no serialisation; CPython switches the GIL every few milliseconds, so
the event loop keeps its heartbeats while a pure-Python vertex computes (docs/benchmarks.md has
the thread-versus-process measurements). A hung vertex holds only its own thread.
"""

from __future__ import annotations

import queue
import resource
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from mso.protocol import effects as fx
from mso.runtime.worker import VertexWorker

PULL_BATCH = 256  # calls a free-running source makes per result at most
PULL_BUDGET_S = 0.005  # ... or wall time, so its events leave in timely batches

# CPU time per call (event) on its thread for a job to count as cheap: a pass-through's job
# (decode, call, encode) takes 30-100 us there at 100 events/s, cold caches and all, and over
# 200 us on a loaded VM (a CPU shared by 5 or 6 busy threads): half the loop's budget
CHEAP_CALL_S = 500e-6
CHEAP_JOBS = 16  # cheap jobs in a row before an instance moves to the loop
MAX_CHEAP_JOBS = 4096  # ... at most, however often it was sent back
CALL_BUDGET_S = 1e-3  # on the loop, a job using more CPU per call sends the instance back ...
JOB_BUDGET_S = 5e-3  # ... or more in all (a feed is up to 256 events)
# on the loop, a job this long off the CPU that gave the CPU up itself (it blocked: I/O, a
# sleep, a lock) sends the instance back; one preempted by the kernel for as long (another
# process's turn on a loaded machine) did not: the loop stalls as much whatever it runs
BLOCK_S = 1e-3
# ... in this many jobs in a row: the first job after a move may wait for the GIL, which the
# instance's thread needs once more to park (5 ms at load 20); a vertex that blocks, blocks again
BLOCKED_JOBS = 2
FORGIVE_JOBS = 1024  # jobs within budget on the loop that halve what a return costs again
BATCH_S = 2e-3  # one turn of inline jobs runs about this long, then I/O and timers get theirs
HEAVY_S = 0.05  # a job on the loop this long keeps its instance on its thread for good (a
# tenth of the default liveness window: a vertex that can turn this slow must not get a second
# chance to stall heartbeats)


def voluntary_switches() -> int:
    """Context switches this thread asked for (it waited: I/O, a sleep, a lock, the GIL)."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


class _Lane:
    """One instance: its worker, its thread and queue, and where its jobs run now."""

    def __init__(self, start: fx.StartVertex, deliver: Callable[[fx.VertexResult], None]) -> None:
        self.worker = VertexWorker(start)
        self.deliver = deliver
        self.jobs: queue.SimpleQueue[fx.VertexEffect] = queue.SimpleQueue()
        self.credit = 0
        self.loop_source = False
        self.thread = threading.Thread(
            target=self._run, name=f"mso-{start.app}-{start.vertex.id}", daemon=True
        )
        self.put = 0  # jobs put on the thread's queue (written by the loop's thread only)
        self.done = 0  # ... and finished by the thread (written by the thread only)
        self.inline = False  # the instance runs on the loop's thread now
        self.pending: deque[fx.VertexEffect] = deque()  # jobs waiting for the loop, in order
        self.cheap = 0  # cheap jobs in a row on the thread
        self.need = CHEAP_JOBS  # cheap jobs in a row that move it to the loop
        self.within = 0  # jobs in a row within budget on the loop
        self.blocked = 0  # ... and that blocked, in a row
        self.moves = 0  # moves either way (tests and status read it)
        # never on the loop: it asked for its thread (code that may block or turn slow at once),
        # or one of its jobs on the loop took HEAVY_S
        self.stays = start.vertex.isolation == "thread"

    def _run(self) -> None:
        worker = self.worker
        cpu = time.thread_time
        while True:
            if self.loop_source and self.credit > 0 and not worker.ended and self.jobs.empty():
                pulled = worker.pull(min(self.credit, PULL_BATCH), PULL_BUDGET_S)
                self.credit -= pulled.calls
                self.deliver(pulled)
                continue
            job = self.jobs.get()
            if isinstance(job, fx.StartVertex):
                started = worker.open()
                self.loop_source = started.mode == "loop"
                self.deliver(started)
            elif isinstance(job, fx.Credit):
                self.credit += job.count
            elif isinstance(job, fx.StopVertex):
                worker.close()
                return
            else:
                c0 = cpu()
                res = self.run(job)
                used = cpu() - c0
                if res is not None:
                    self.deliver(res)
                n = calls(job)
                # by CPU time alone: here wall time says little of the vertex (a job waits for
                # the GIL while the loop runs, for a CPU on a loaded machine: a pass-through's
                # 100 us job took 2-16 ms of wall time at load 20, and every wait is a futex,
                # so it looks blocked); one that blocks is sent back by its first job on the
                # loop (below), each time needing twice as many cheap jobs to return
                self.cheap = (
                    self.cheap + 1 if used <= CHEAP_CALL_S * n and used <= JOB_BUDGET_S / 2 else 0
                )
            self.done += 1  # after its result: a move to the loop finds it queued ahead

    def run(self, job: fx.VertexEffect) -> fx.VertexResult | None:
        """Carry out a feed, a rated run, a restore or a snapshot (on whichever thread the
        instance runs now); its result is for ``deliver``, which the caller leaves out of the
        time it measures (from a thread it is the hand-off back, not the vertex's cost)."""
        worker = self.worker
        if isinstance(job, fx.FeedVertex):
            return worker.feed(job)
        if isinstance(job, fx.RunSource):
            return worker.run_source(job.first, job.count, job.now)
        if isinstance(job, fx.RestoreVertex):
            worker.restore(job.state)
        elif isinstance(job, fx.SnapshotVertex):
            return worker.snapshot(job.token)
        return None

    def may_move_inline(self) -> bool:
        """Cheap enough for long enough, and its thread idle (every job it got is done)."""
        return (
            self.cheap >= self.need
            and self.put == self.done
            and not self.loop_source
            and not self.stays
        )

    def to_thread(self) -> None:
        """Back to its thread, with the jobs not run yet, in order."""
        self.inline = False
        self.cheap = self.within = self.blocked = 0
        self.moves += 1
        while self.pending:
            self.put += 1
            self.jobs.put(self.pending.popleft())


def calls(job: fx.VertexEffect) -> int:
    """How many calls of user code a job makes (its budget scales with it)."""
    if isinstance(job, fx.FeedVertex):
        return max(1, len(job.events))
    if isinstance(job, fx.RunSource):
        return max(1, job.count)
    return 1


class ThreadExecutor:
    """Runs vertex effects on per-instance threads, or inline on the loop's thread for cheap
    instances when ``schedule`` is given (it asks the loop to call :meth:`run_inline` soon);
    ``deliver`` receives the results (see the module docstring)."""

    def __init__(
        self,
        deliver: Callable[[fx.VertexResult], None],
        schedule: Callable[[], None] | None = None,
    ) -> None:
        self.deliver = deliver
        self.schedule = schedule
        self._lanes: dict[int, _Lane] = {}
        self._ready: deque[_Lane] = deque()  # lanes with inline jobs waiting, in arrival order
        self._scheduled = False

    def submit(self, eff: fx.VertexEffect) -> None:
        if isinstance(eff, fx.StartVertex):
            lane = self._lanes[eff.instance] = _Lane(eff, self.deliver)
            lane.put += 1
            lane.jobs.put(eff)
            lane.thread.start()
            return
        lane_or_none = self._lanes.get(eff.instance)
        if lane_or_none is None:
            return  # already stopped: nothing to do
        lane = lane_or_none
        if isinstance(eff, fx.StopVertex):
            del self._lanes[eff.instance]
            if lane.inline:
                lane.to_thread()  # close() is user code too: on its thread, after the rest
        elif not lane.inline and self.schedule is not None and lane.may_move_inline():
            lane.inline = True
            lane.within = 0
            lane.moves += 1
        if lane.inline:
            if not lane.pending:
                self._ready.append(lane)
            lane.pending.append(eff)
            if not self._scheduled:
                self._scheduled = True
                assert self.schedule is not None
                self.schedule()
            return
        lane.put += 1
        lane.jobs.put(eff)

    def run_inline(self) -> None:
        """Run the inline jobs waiting, on the calling (the loop's) thread, for about
        ``BATCH_S``; what is left is scheduled again so I/O and timers get their turn."""
        self._scheduled = False
        perf, cpu = time.perf_counter, time.thread_time
        deadline = perf() + BATCH_S
        ready = self._ready
        v0 = voluntary_switches()  # read again only when a job was off the CPU for long
        while ready:
            lane = ready.popleft()
            while lane.inline and lane.pending:
                job = lane.pending.popleft()
                t0, c0 = perf(), cpu()
                res = lane.run(job)
                t1 = perf()
                # over budget: its CPU time, or time off the CPU that it gave up itself (it
                # blocked, on I/O or a sleep: the loop must not wait for that; a preemption
                # by the kernel is not the vertex's doing and stalls the loop as much anyway)
                used = cpu() - c0
                blocked = False
                if t1 - t0 - used > BLOCK_S:
                    v1 = voluntary_switches()
                    blocked, v0 = v1 != v0, v1
                if res is not None:
                    lane.deliver(res)
                lane.blocked = lane.blocked + 1 if blocked else 0
                over = used > min(JOB_BUDGET_S, CALL_BUDGET_S * calls(job))
                if over or lane.blocked >= BLOCKED_JOBS or (blocked and t1 - t0 >= HEAVY_S):
                    lane.need = min(2 * lane.need, MAX_CHEAP_JOBS)
                    lane.stays = lane.stays or t1 - t0 >= HEAVY_S
                    lane.to_thread()
                else:
                    lane.within += 1
                    if lane.within % FORGIVE_JOBS == 0:
                        lane.need = max(CHEAP_JOBS, lane.need // 2)
                if t1 > deadline and (lane.pending or ready):
                    if lane.pending and lane.inline:
                        ready.appendleft(lane)
                    self._scheduled = True
                    assert self.schedule is not None
                    self.schedule()
                    return

    def placement(self, instance: int) -> str | None:
        """Where an instance's jobs run now: ``loop`` or ``thread`` (None: not here)."""
        lane = self._lanes.get(instance)
        if lane is None:
            return None
        return "loop" if lane.inline else "thread"

    def moves(self, instance: int) -> int:
        lane = self._lanes.get(instance)
        return lane.moves if lane is not None else 0

    @property
    def instances(self) -> int:
        return len(self._lanes)

    def shutdown(self, timeout: float = 1.0) -> None:
        """Stop every instance (their ``close()`` hooks run); wait a little for them."""
        lanes = list(self._lanes.values())
        self._lanes.clear()
        self._ready.clear()
        for lane in lanes:
            lane.inline = False
            lane.pending.clear()
            lane.jobs.put(fx.StopVertex(lane.worker.start.instance, "shutdown"))
        for lane in lanes:
            lane.thread.join(timeout / max(1, len(lanes)))


class Executor:
    """The node's executor: each instance on a thread of this process, or — for a vertex
    with ``isolation: process`` — in a child process of its own (``mso.runtime.process_lane``,
    started on first use). One interface for the driver; results go to ``deliver`` either way."""

    def __init__(
        self,
        deliver: Callable[[fx.VertexResult], None],
        schedule: Callable[[], None] | None = None,
    ) -> None:
        self.deliver = deliver
        self.threads = ThreadExecutor(deliver, schedule)
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

    def run_inline(self) -> None:
        """Run the cheap instances' jobs waiting for the loop (see :class:`ThreadExecutor`)."""
        self.threads.run_inline()

    def placement(self, instance: int) -> str | None:
        """``loop``, ``thread`` or ``process``: where an instance's jobs run now."""
        if instance in self._in_process:
            return "process"
        return self.threads.placement(instance)

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
