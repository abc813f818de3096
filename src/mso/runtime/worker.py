"""Carrying out one vertex effect against one instance: the part every executor shares.

A :class:`VertexWorker` owns one :class:`~mso.runtime.instance.Instance` and turns each vertex
effect into a result: decode the inputs, call the user's code, encode what it returns, count
errors (a vertex that raises is counted, never fatal) and the CPU time it used. The thread
executor calls it from the vertex's own thread, the simulator inline in virtual time; both get
the same behaviour.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import msgspec

from mso.protocol import effects as fx
from mso.runtime.instance import Instance

STATE_SIZE_EVERY_S = 1.0  # how often the size of a busy vertex's state is measured

_excluded = threading.local()


@contextmanager
def not_charged() -> Iterator[None]:
    """CPU time spent inside is not the vertex's work and is not charged to it.

    For code that stands in for the environment, not for the app: a simulated sensor's world
    (ray casting a laser scan in a map, rendering a camera frame) is the hardware's job on a
    real robot, whose driver only packs the reading. The runtime's per-vertex CPU time (and so
    ``cpu_energy: measured``) and ``mso profile`` leave it out; everything else is charged.
    """
    t0 = time.thread_time()
    try:
        yield
    finally:
        _excluded.s = getattr(_excluded, "s", 0.0) + time.thread_time() - t0


def charged_thread_time() -> float:
    """This thread's CPU time less what ran inside :func:`not_charged`."""
    return time.thread_time() - getattr(_excluded, "s", 0.0)


class VertexWorker:
    def __init__(
        self,
        start: fx.StartVertex,
        cpu_clock: Callable[[], float] = charged_thread_time,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.start = start
        self.instance: Instance | None = None
        self.cpu_clock = cpu_clock
        self.clock = clock
        self.decoders: dict[int, msgspec.msgpack.Decoder[Any]] = {}
        self.seq = 0  # a loop source's next sequence number
        self._errors = 0
        self._last_error = ""
        self._sized_at = -STATE_SIZE_EVERY_S
        self._state_size = 0
        self.ended = False
        self.ended_inputs: set[int] = set()  # input edges whose stream has ended
        # output edge -> (its declared format, a decoder for it): outputs are checked at once
        self._checks: dict[int, tuple[type, msgspec.msgpack.Decoder[Any]]] = {
            e: (fmt, msgspec.msgpack.Decoder(fmt))
            for e, fmt in start.outputs.items()
            if isinstance(fmt, type)
        }
        # the one format every output edge declares, if they agree (the usual case): an event
        # of exactly that type fits with one comparison, no call, on the hot path
        formats = {fmt for fmt, _ in self._checks.values()}
        self._fits: type | None = formats.pop() if len(formats) == 1 else None

    # -- bookkeeping shared by every result -------------------------------------------------
    def _error(self, text: str) -> None:
        self._errors += 1
        self._last_error = text

    def _outcome(self, t0: float) -> dict[str, Any]:
        errors, last = self._errors, self._last_error
        self._errors, self._last_error = 0, ""
        now = self.clock()
        stats = self.instance.stats() if self.instance is not None else None  # meant to be cheap
        if self.instance is not None and now - self._sized_at >= STATE_SIZE_EVERY_S:
            self._sized_at = now
            try:
                self._state_size = len(msgspec.msgpack.encode(self.instance.get_state()))
            except Exception:  # user code: a state that cannot be taken pins the vertex
                self._state_size = -1
        return {
            "instance": self.start.instance,
            "cpu_s": self.cpu_clock() - t0,
            "errors": errors,
            "last_error": last,
            "stats": stats,
            "state_size": self._state_size,
        }

    # -- effects ----------------------------------------------------------------------------
    def open(self) -> fx.VertexStarted:
        t0 = self.cpu_clock()
        st = self.start
        try:
            inst = Instance(st.vertex, st.kind)
            if st.state is not None:
                inst.set_state(msgspec.msgpack.decode(st.state))
            for edge, fmt in st.inputs.items():
                self.decoders[edge] = msgspec.msgpack.Decoder(fmt if fmt is not None else Any)
            opener = inst.hook("open")
            if opener is not None:
                opener()
        except Exception as exc:  # user code failing at construction: refuse, change nothing
            return fx.VertexStarted(
                **self._outcome(t0), error=f"cannot create {st.vertex.id!r}: {_why(exc)}"
            )
        self.instance = inst
        return fx.VertexStarted(**self._outcome(t0), mode=inst.mode)

    def feed(self, eff: fx.FeedVertex) -> fx.VertexProcessed:
        t0 = self.cpu_clock()
        inst = self.instance
        outs: list[Any] = []
        # a merge's outputs say which event they were made from (mso.protocol.provenance)
        owners: list[int] | None = [] if self.start.owners else None
        ends, ended = 0, False
        decode = self.decoders[eff.edge].decode if eff.edge in self.decoders else None
        if inst is not None and decode is not None:
            fn = inst.fn
            for i, payload in enumerate(eff.events):
                if owners is not None:  # what the event before made (a path may ``continue``)
                    owners.extend([i - 1] * (len(outs) - len(owners)))
                if payload == fx.END_OF_STREAM:  # this input's stream is over
                    ends += 1
                    self.ended_inputs.add(eff.edge)
                    if not ended and self.ended_inputs >= set(self.start.inputs):
                        ended = True  # every input: the vertex ends, and says so downstream
                        outs.extend(self._end(inst))
                    continue
                try:
                    event = decode(payload)
                except (msgspec.DecodeError, msgspec.ValidationError, RecursionError) as exc:
                    edge = self.start.edge_names.get(eff.edge, f"edge {eff.edge}")
                    self._error(f"undecodable event on edge {edge}: {exc}")
                    continue
                try:
                    result = fn(event)
                except Exception as exc:
                    self._error(_why(exc))
                    continue
                if result is not None:
                    if isinstance(result, list):
                        outs.extend(result)
                    else:
                        outs.append(result)
        if owners is not None:
            owners.extend([len(eff.events) - 1] * (len(outs) - len(owners)))
        payloads = self._encode(outs, owners)
        if ended:
            payloads.append(fx.END_OF_STREAM)
            if owners is not None:
                owners.append(len(eff.events) - 1)
        return fx.VertexProcessed(
            **self._outcome(t0),
            edge=eff.edge,
            count=len(eff.events),
            outputs=payloads,
            owners=owners or [],
            ts=eff.ts,
            ends=ends,
            ended=ended,
        )

    def _end(self, inst: Instance) -> list[Any]:
        """Call the vertex's ``end()`` (a sink flushes there); what it returns goes out
        before the end-of-stream marker."""
        hook = inst.hook("end")
        if hook is None:
            return []
        try:
            result = hook()
        except Exception as exc:
            self._error(f"end: {_why(exc)}")
            return []
        if result is None:
            return []
        return list(result) if isinstance(result, list) else [result]

    def run_source(self, first: int, count: int, now: float) -> fx.VertexEmitted:
        """Call a rated source ``count`` times."""
        t0 = self.cpu_clock()
        outs: list[Any] = []
        inst = self.instance
        if inst is not None and not self.ended:
            fn = inst.fn
            for k in range(count):
                try:
                    event = fn(first + k, now)
                except StopIteration:  # a rated source whose stream is over
                    self.ended = True
                    count = k
                    break
                except Exception as exc:
                    self._error(_why(exc))
                    continue
                if event is not None:
                    outs.append(event)
        return fx.VertexEmitted(
            **self._outcome(t0), calls=count, outputs=self._encode(outs), ended=self.ended
        )

    def pull(self, count: int, budget_s: float) -> fx.VertexEmitted:
        """A free-running source: up to ``count`` calls (or ``next()``s), for at most
        ``budget_s`` of wall time, so what it made goes out in timely batches."""
        t0 = self.cpu_clock()
        outs: list[Any] = []
        inst = self.instance
        calls = 0
        if inst is not None and not self.ended:
            deadline = self.clock() + budget_s
            it, fn = inst.iterator, inst.fn
            while calls < count:
                calls += 1
                try:
                    event = next(it) if it is not None else fn(self.seq, self.clock())
                except StopIteration:
                    self.ended = True
                    break
                except Exception as exc:
                    self._error(_why(exc))
                    event = None
                self.seq += 1
                if event is not None:
                    outs.append(event)
                if self.clock() >= deadline:
                    break
        return fx.VertexEmitted(
            **self._outcome(t0), calls=calls, outputs=self._encode(outs), ended=self.ended
        )

    def restore(self, state: bytes) -> None:
        """Install a handed-over state; an error is reported with the next result."""
        if self.instance is None:
            return
        try:
            self.instance.set_state(msgspec.msgpack.decode(state))
        except Exception as exc:
            self._error(f"set_state: {_why(exc)}")

    def snapshot(self, token: int) -> fx.VertexSnapshot:
        t0 = self.cpu_clock()
        state = b""
        if self.instance is not None:
            try:
                state = msgspec.msgpack.encode(self.instance.get_state())
            except Exception as exc:
                self._error(f"get_state: {_why(exc)}")
                state = msgspec.msgpack.encode(None)
        return fx.VertexSnapshot(**self._outcome(t0), token=token, state=state)

    def close(self) -> None:
        inst, self.instance = self.instance, None
        closer = inst.hook("close") if inst is not None else None
        if closer is not None:
            try:
                closer()
            except Exception as exc:
                self._error(f"close: {_why(exc)}")

    def _encode(self, outs: list[Any], owners: list[int] | None = None) -> list[bytes]:
        """The outputs encoded; one that cannot be is counted and left out (and so is its
        entry in ``owners``, kept in step)."""
        encode = msgspec.msgpack.encode
        payloads: list[bytes] = []
        dropped: list[int] = []  # (the index in ``outs`` of each output left out)
        for ev in outs:
            try:
                payload = encode(ev)
            except (TypeError, ValueError, OverflowError) as exc:
                self._error(f"cannot encode {type(ev).__name__}: {exc}")
                dropped.append(len(payloads) + len(dropped))
                continue
            if self._checks and type(ev) is not self._fits and (why := self._mismatch(ev, payload)):
                self._error(why)  # here, at the producer that made it: its consumer never sees it
                dropped.append(len(payloads) + len(dropped))
                continue
            payloads.append(payload)
        if owners is not None and dropped:
            gone = set(dropped)
            owners[:] = [o for j, o in enumerate(owners) if j not in gone]
        return payloads

    def _mismatch(self, ev: Any, payload: bytes) -> str:
        """Why an output does not fit an output edge's declared format ("" if it does). An
        instance of the format fits at no cost; anything else (a dict, another Struct) is
        decoded as the consumer would, so what decodes there is still accepted."""
        for edge, (fmt, decoder) in self._checks.items():
            if isinstance(ev, fmt):
                continue
            try:
                decoder.decode(payload)
            except (msgspec.DecodeError, msgspec.ValidationError) as exc:
                name = self.start.edge_names.get(edge, f"edge {edge}")
                return (
                    f"output {type(ev).__name__} does not match {fmt.__name__}, the format of "
                    f"edge {name}: {exc}"
                )
        return ""


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"
