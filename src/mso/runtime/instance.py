"""A hosted vertex instance (the paper's "stone"): the user's code, called only by a worker.

Calling conventions (docs/app-format.md): a class is instantiated with ``params`` as keyword
arguments, a function is used as is (with ``params`` bound as keyword arguments). Then a source
is called ``(seq, now)`` and returns an event or None; an operator is called ``(event)`` and
returns an event, None, or a list of events; a sink is called ``(event)``. A rate-less source
is a read loop: called again as soon as backpressure allows (it may block); a generator function
(or an instance with ``__iter__``/``__next__``) is iterated instead, and its end is the end of
its stream. Optional hooks on the instance: ``open()`` once it runs, ``close()`` when it stops
here (undeploy, or it moved away), ``end()`` once every input's stream has ended (a sink flushes;
an operator may return final events), ``get_state()``/``set_state(state)`` for moves,
``stats()`` for status. A source ends its stream by returning (a generator) or raising
StopIteration. The app may name state hooks by import path instead.

Nothing here runs on the control plane: the executor calls it from the vertex's worker.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Iterator
from typing import Any

import msgspec

from mso.model.app import Vertex
from mso.model.imports import resolve


def _callable(code: Any) -> Any:
    return resolve(code) if isinstance(code, str) else code


class Instance:
    """One vertex instance: its code, its hooks, and how a source produces events."""

    def __init__(self, vertex: Vertex, kind: str) -> None:
        self.vertex = vertex
        self.kind = kind
        target = _callable(vertex.code) if vertex.code is not None else None
        self.iterator: Iterator[Any] | None = None
        if target is None:
            self.fn: Callable[..., Any] = _default_code(kind)
        elif isinstance(target, type):
            self.fn = target(**vertex.params)
        elif inspect.isgeneratorfunction(target):
            self.fn = target
            self.iterator = iter(target(**vertex.params))
        elif vertex.params:
            self.fn = functools.partial(target, **vertex.params)
        else:
            self.fn = target
        if kind == "source" and self.iterator is None and hasattr(self.fn, "__next__"):
            obj: Any = self.fn
            self.iterator = obj  # an iterator object is a generator source
        # a code-less stand-in source ticks once a second unless the app gives a rate
        self.rate = vertex.rate if vertex.rate or vertex.code is not None else 1.0

    @property
    def mode(self) -> str:
        """How a source runs: ``timer`` (rated), ``loop`` (read loop or generator)."""
        if self.kind != "source":
            return ""
        return "timer" if self.rate and self.iterator is None else "loop"

    def hook(self, name: str) -> Callable[[], Any] | None:
        method = getattr(self.fn, name, None)
        return method if callable(method) else None

    def stats(self) -> Any:
        """The vertex's own metrics, if its code defines ``stats()`` (shown by mso status)."""
        method = self.hook("stats")
        if method is None:
            return None
        try:  # plain data, or it could not be shown (nor sent) at all
            return msgspec.to_builtins(method())
        except Exception as exc:
            return {"error": f"stats(): {type(exc).__name__}: {exc}"}

    def get_state(self) -> Any:
        hook = self.vertex.get_state
        if hook is not None:
            return _callable(hook)(self.fn)
        method = self.hook("get_state")
        return method() if method is not None else None

    def set_state(self, state: Any) -> None:
        hook = self.vertex.set_state
        if hook is not None:
            _callable(hook)(self.fn, state)
            return
        method = getattr(self.fn, "set_state", None)
        if callable(method):
            method(state)


def _default_code(kind: str) -> Callable[..., Any]:
    """Stand-in logic for vertices without code: sources count, operators forward."""
    if kind == "source":
        return lambda seq, now: Tick(seq=seq, stamp=now)
    return lambda event: event if kind != "sink" else None


class Tick(msgspec.Struct, frozen=True):
    """The event a code-less source emits."""

    seq: int
    stamp: float
