"""A hosted vertex instance (the paper's "stone"): the user's code and its counters.

Calling conventions (docs/app-format.md): a class is instantiated with ``params`` as keyword
arguments, a function is used as is (with ``params`` bound as keyword arguments). Then a source
is called ``(seq, now)`` and returns an event or None; an operator is called ``(event)`` and
returns an event, None, or a list of events; a sink is called ``(event)``. State hooks are the
instance's ``get_state()``/``set_state(state)`` methods or the app's ``get_state``/``set_state``
import paths, called with the instance.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import msgspec

from mso.model.app import Vertex
from mso.model.imports import resolve


def _callable(code: Any) -> Any:
    return resolve(code) if isinstance(code, str) else code


class Stone:
    """One vertex instance on this node."""

    def __init__(self, vertex: Vertex, kind: str) -> None:
        self.vertex = vertex
        self.kind = kind
        target = _callable(vertex.code) if vertex.code is not None else None
        if target is None:
            self.fn: Callable[..., Any] = _default_code(kind)
        elif isinstance(target, type):
            self.fn = target(**vertex.params)
        elif vertex.params:
            self.fn = functools.partial(target, **vertex.params)
        else:
            self.fn = target
        # a code-less stand-in source ticks once a second unless the app gives a rate
        self.rate = vertex.rate if vertex.rate or vertex.code is not None else 1.0
        self.next_at = 0.0  # a rated source's next emission time
        self.processed = 0
        self.emitted = 0
        self.errors = 0
        self.cpu_s = 0.0
        self.bytes_in = 0  # encoded size of the events it consumed and produced
        self.bytes_out = 0
        self.last_error = ""

    def stats(self) -> Any:
        """The vertex's own metrics, if its code defines ``stats()`` (shown by mso status)."""
        method = getattr(self.fn, "stats", None)
        if not callable(method):
            return None
        try:
            return method()
        except Exception as exc:
            return {"error": f"{type(exc).__name__}: {exc}"}

    def get_state(self) -> Any:
        hook = self.vertex.get_state
        if hook is not None:
            return _callable(hook)(self.fn)
        method = getattr(self.fn, "get_state", None)
        return method() if callable(method) else None

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
