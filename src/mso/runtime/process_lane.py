"""A process lane: one vertex instance in a child process (``isolation: process``).

Why: CPython's GIL lets one thread run Python at a time, so two CPU-bound pure-Python vertices
in one node's threads share one core, and the node's event loop gets the GIL only every switch
interval (5 ms) while they compute. In a child process a vertex has a core (and a GIL) of its
own. The cost: every event crosses a pipe, and a start costs a process.

What crosses: only bytes. Jobs and results are msgspec-encoded; the vertex travels as import
paths (its code, formats and state hooks) and its params, and the child imports the code by path
itself, as a node does; events and state stay the encoded bytes they already are. Nothing is
pickled (the child is started with the ``forkserver`` or ``spawn`` context and only reads
``Connection.recv_bytes``). So code given as a Python callable, not a path, cannot run here.

The interface is the thread executor's (``submit(effect)``; results to ``deliver`` from a reader
thread), so the driver could take either; docs/benchmarks.md compares the two.

A child that dies without being told to stop (a segfault in a C extension, an OOM kill,
``os._exit``) is reported, never silent: its reader sees the pipe close, collects the exit
status and delivers :class:`~mso.protocol.effects.VertexCrashed` ("killed by SIGKILL", "exit
code 3"); the node core then restores the instance (``docs/architecture.md``, Executor).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import multiprocessing
import signal
import threading
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import msgspec

from mso.model.app import Vertex
from mso.protocol import effects as fx

PULL_BATCH = 256
PULL_BUDGET_S = 0.005


# -- the wire between parent and child --------------------------------------------------------
class VertexSpec(msgspec.Struct, frozen=True):
    id: str
    kind: str
    code: str | None
    params: dict[str, Any]
    rate: float | None
    input: str | None
    output: str | None
    get_state: str | None
    set_state: str | None
    inputs: dict[int, str | None]  # edge -> format import path
    outputs: dict[int, str | None] = {}  # output edge -> format import path
    edge_names: dict[int, str] = {}  # edge -> "producer -> consumer"
    owners: bool = False  # say which input event each output came from (provenance)


class Start(msgspec.Struct, tag=True):
    instance: int
    app: str
    spec: VertexSpec
    state: bytes | None = None


class Feed(msgspec.Struct, tag=True):
    edge: int
    events: list[bytes]
    ts: float


class Run(msgspec.Struct, tag=True):
    first: int
    count: int
    now: float


class Grant(msgspec.Struct, tag=True):
    count: int


class Restore(msgspec.Struct, tag=True):
    state: bytes


class Snapshot(msgspec.Struct, tag=True):
    token: int


class Stop(msgspec.Struct, tag=True):
    pass


One = Start | Feed | Run | Grant | Restore | Snapshot | Stop


class Batch(msgspec.Struct, tag=True):
    """The jobs one turn of the node's loop made for this child, in order, in one write."""

    jobs: list[One]


Job = One | Batch


class Result(msgspec.Struct):
    kind: str  # the fx result class: one of RESULTS
    body: msgspec.Raw


RESULTS: dict[str, type[Any]] = {
    c.__name__: c
    for c in (fx.VertexStarted, fx.VertexProcessed, fx.VertexEmitted, fx.VertexSnapshot)
}


def _path(x: Any) -> str | None:
    """An import path for code or a format (a string already is one)."""
    if x is None or isinstance(x, str):
        return x
    if isinstance(x, type):
        return f"{x.__module__}:{x.__qualname__}"
    raise ValueError(f"a process lane needs import paths, not {type(x).__name__} objects")


def spec_of(start: fx.StartVertex) -> VertexSpec:
    v = start.vertex
    return VertexSpec(
        id=v.id,
        kind=start.kind,
        code=_path(v.code),
        params=dict(v.params),
        rate=v.rate,
        input=_path(v.input),
        output=_path(v.output),
        get_state=_path(v.get_state),
        set_state=_path(v.set_state),
        inputs={e: _path(f) for e, f in start.inputs.items()},
        outputs={e: _path(f) for e, f in start.outputs.items()},
        edge_names=dict(start.edge_names),
        owners=start.owners,
    )


# -- the child ---------------------------------------------------------------------------------
def _child(conn: Connection) -> None:
    """The child's loop: decode a job, run it on the worker, send the result back."""
    from mso.model.imports import resolve
    from mso.runtime.worker import VertexWorker

    jobs = msgspec.msgpack.Decoder(Job)
    enc = msgspec.msgpack.Encoder()
    worker: VertexWorker | None = None
    credit, loop_source = 0, False
    pending: deque[One] = deque()  # the rest of a batch

    def send(res: Any) -> None:
        body = msgspec.Raw(enc.encode(dataclasses.asdict(res)))
        conn.send_bytes(enc.encode(Result(type(res).__name__, body)))

    while True:
        free = worker is not None and loop_source and credit > 0 and not worker.ended
        free = free and not pending and not conn.poll(0)  # and no job waiting
        if free and worker is not None:  # a read loop
            res = worker.pull(min(credit, PULL_BATCH), PULL_BUDGET_S)
            credit -= res.calls
            send(res)
            continue
        if not pending:
            try:
                got = jobs.decode(conn.recv_bytes())
            except EOFError:
                return
            pending.extend(got.jobs if isinstance(got, Batch) else [got])
        job = pending.popleft()
        if isinstance(job, Start):
            s = job.spec
            fmts = {e: (resolve(f) if f else None) for e, f in s.inputs.items()}
            outs = {e: (resolve(f) if f else None) for e, f in s.outputs.items()}
            vertex = Vertex(
                s.id, s.code, 1.0, None, s.input, s.output, s.rate, s.params, s.get_state,
                s.set_state,
            )  # fmt: skip
            worker = VertexWorker(
                fx.StartVertex(
                    job.instance,
                    job.app,
                    vertex,
                    s.kind,
                    fmts,
                    None,
                    outs,
                    s.edge_names,
                    s.owners,
                )
            )
            started = worker.open()
            loop_source = started.mode == "loop"
            send(started)
        elif worker is None:
            continue
        elif isinstance(job, Feed):
            send(worker.feed(fx.FeedVertex(worker.start.instance, job.edge, job.events, job.ts)))
        elif isinstance(job, Run):
            send(worker.run_source(job.first, job.count, job.now))
        elif isinstance(job, Grant):
            credit += job.count
        elif isinstance(job, Restore):
            worker.restore(job.state)
        elif isinstance(job, Snapshot):
            send(worker.snapshot(job.token))
        elif isinstance(job, Stop):
            worker.close()
            conn.close()
            return


# -- the parent --------------------------------------------------------------------------------
class _ProcLane:
    """One child and its pipe. The child is started on the lane's own thread, never on the
    node's event loop: a start waits for the forkserver (the first one starts it, a Python
    that imports itself), which on a loaded machine took seconds, and a loop that stops for
    seconds sends no heartbeats: its peers declared the node failed in the middle of the
    deployment that asked for the vertex. Jobs submitted before the child runs wait, in
    order, behind its ``Start``."""

    def __init__(
        self, start: fx.StartVertex, deliver: Callable[[fx.VertexResult], None], ctx: Any
    ) -> None:
        self.deliver = deliver
        self.enc = msgspec.msgpack.Encoder()
        self.conn, self._child_conn = ctx.Pipe()
        self.proc = ctx.Process(target=_child, args=(self._child_conn,), daemon=True)
        self.instance = start.instance
        self.stopping = False  # told to stop: its pipe closing is no crash
        self.lock = threading.Lock()  # submit is called from the loop; sends stay whole
        self.waiting: list[One] | None = []  # jobs before the child runs (None: it runs)
        self.started = threading.Event()  # the start was tried (the child runs, or failed)
        self._start = Start(start.instance, start.app, spec_of(start), start.state)
        self.reader = threading.Thread(
            target=self._run, daemon=True, name=f"mso-p-{start.vertex.id}"
        )
        self.reader.start()

    def send(self, jobs: list[One]) -> None:
        """Write ``jobs`` in one message (one job alone as itself), or hold them behind the
        ``Start`` while the child is not running yet."""
        with self.lock:
            if self.waiting is not None:
                self.waiting.extend(jobs)
            elif jobs:
                job: Job = jobs[0] if len(jobs) == 1 else Batch(jobs)
                self.conn.send_bytes(self.enc.encode(job))

    def _run(self) -> None:
        """Start the child, give it its ``Start`` and what waited, then read its results."""
        try:
            self.proc.start()
        except OSError as exc:  # no process could be made (limits, memory): say so
            self.started.set()
            self.deliver(fx.VertexCrashed(self.instance, reason=f"could not start: {exc}"))
            return
        finally:
            self._child_conn.close()
        self.started.set()
        batch: list[One] = [self._start]
        with contextlib.suppress(OSError):  # the child is gone already: the read says how
            while batch:  # sent outside the lock: the loop never waits for the child here
                self.conn.send_bytes(self.enc.encode(Batch(batch)))
                with self.lock:
                    batch, self.waiting = self.waiting or [], ([] if self.waiting else None)
        self._read()

    def _read(self) -> None:
        dec = msgspec.msgpack.Decoder(Result)
        decoders = {k: msgspec.msgpack.Decoder(c) for k, c in RESULTS.items()}
        while True:
            try:
                raw = self.conn.recv_bytes()
            except (EOFError, OSError):
                if not self.stopping:
                    self.deliver(self._crashed())
                return
            res = dec.decode(raw)
            d = decoders.get(res.kind)
            if d is not None:
                self.deliver(d.decode(res.body))

    def _crashed(self) -> fx.VertexCrashed:
        """The child's pipe closed unasked: wait for its exit status and say it in words."""
        self.proc.join(2.0)
        if self.proc.is_alive():  # it closed its end of the pipe but lives on: end it
            self.proc.kill()
            self.proc.join(2.0)
            return fx.VertexCrashed(self.instance, reason="closed its pipe", exit_code=None)
        return fx.VertexCrashed(self.instance, reason=exit_words(self.proc.exitcode))


def _job(eff: fx.VertexEffect) -> One:
    """The child's job for an effect on a running instance."""
    if isinstance(eff, fx.FeedVertex):
        return Feed(eff.edge, eff.events, eff.ts)
    if isinstance(eff, fx.RunSource):
        return Run(eff.first, eff.count, eff.now)
    if isinstance(eff, fx.Credit):
        return Grant(eff.count)
    if isinstance(eff, fx.RestoreVertex):
        return Restore(eff.state)
    if isinstance(eff, fx.SnapshotVertex):
        return Snapshot(eff.token)
    if isinstance(eff, fx.StopVertex):
        return Stop()
    raise TypeError(f"no child job for {type(eff).__name__}")


def exit_words(code: int | None) -> str:
    """A child's exit status in words: "killed by SIGKILL", "exit code 3"."""
    if code is None:
        return "ended with no exit status"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class ProcessExecutor:
    """Runs vertex effects in one child process per instance (``context``: forkserver or
    spawn); the same interface as :class:`mso.runtime.executor.ThreadExecutor`.

    Submitted on a running event loop, a lane's jobs are written once per turn of that loop,
    together: a write releases the GIL, and taking it back waits for any thread that took it
    meanwhile (a lane's reader, woken by the child's results), which on a loaded machine may
    itself be waiting for a core. One write per job (a replay after a crash feeds one event
    a job) stopped the node's loop 25-65 ms a job, over 1 s for one read at load 13: no
    heartbeats, and its peer declared the node failed."""

    def __init__(
        self, deliver: Callable[[fx.VertexResult], None], context: str = "forkserver"
    ) -> None:
        self.deliver = deliver
        self.ctx = multiprocessing.get_context(context)
        self._lanes: dict[int, _ProcLane] = {}
        self._due: dict[_ProcLane, list[One]] = {}  # this turn's jobs, written at its end

    def submit(self, eff: fx.VertexEffect) -> None:
        if isinstance(eff, fx.StartVertex):
            self._lanes[eff.instance] = _ProcLane(eff, self.deliver, self.ctx)
            return
        lane = self._lanes.get(eff.instance)
        if lane is None:
            return
        if isinstance(eff, fx.StopVertex):
            lane.stopping = True
            del self._lanes[eff.instance]
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop here: write at once
            self._write(lane, [_job(eff)])
            return
        if not self._due:
            loop.call_soon(self.flush)
        self._due.setdefault(lane, []).append(_job(eff))

    def flush(self) -> None:
        """Write every lane's jobs of this turn, in order, one message a lane."""
        due, self._due = self._due, {}
        for lane, jobs in due.items():
            self._write(lane, jobs)

    @staticmethod
    def _write(lane: _ProcLane, jobs: list[One]) -> None:
        with contextlib.suppress(OSError):  # the child is gone: its reader reports how it ended
            lane.send(jobs)

    def pid(self, instance: int) -> int | None:
        """The process running ``instance`` (tests kill it to play a crash)."""
        lane = self._lanes.get(instance)
        return lane.proc.pid if lane is not None else None

    @property
    def instances(self) -> int:
        return len(self._lanes)

    def shutdown(self, timeout: float = 1.0) -> None:
        """Stop every child (their ``close()`` hooks run); kill what does not end in time."""
        self.flush()
        lanes = list(self._lanes.values())
        self._lanes.clear()
        for lane in lanes:
            lane.stopping = True
            self._write(lane, [Stop()])
        for lane in lanes:
            share = timeout / max(1, len(lanes))
            if not lane.started.wait(share) or lane.proc.pid is None:
                continue  # never started (or still starting): its daemon thread ends with us
            lane.proc.join(share)
            if lane.proc.is_alive():
                lane.proc.kill()
                lane.proc.join(0.5)
