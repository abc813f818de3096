"""What a node's core holds, by component (issue 24: per-node memory independent of N beyond
the node's own apps): deep sizes of the objects each component reaches, each object charged
once, to the first to reach it. ``bench/node_memory.py`` and the tests use it."""

from __future__ import annotations

import gc
import sys
import types
from collections.abc import Iterable
from typing import Any

# components walked one level deeper: their own attributes are the rows
EXPAND = ("membership", "dataplane", "manager", "deployer", "relocator", "restorer", "remapper")
# code and ways back into a core or the simulator: never walked
STOP_TYPES = (
    type,
    types.ModuleType,
    types.FunctionType,
    types.BuiltinFunctionType,
    types.MethodType,
    types.CodeType,
    types.FrameType,
)


class Walker:
    """Deep sizes with one ``seen`` set: each object counted once, to the first to reach it.
    ``stop`` (the simulator, the cores themselves) is never walked into."""

    def __init__(self, stop: Iterable[object]) -> None:
        self.keep = list(stop)  # alive while their ids are in ``seen``
        self.seen: set[int] = {id(x) for x in self.keep}

    def size(self, root: object, block: frozenset[int] | set[int] = frozenset()) -> int:
        """The bytes of what ``root`` reaches that nothing reached before, not through
        ``block`` (the node's other components: each is a row of its own)."""
        total, todo = 0, [root]
        seen, getsizeof, referents = self.seen, sys.getsizeof, gc.get_referents
        while todo:
            obj = todo.pop()
            i = id(obj)
            if i in seen or (i in block and obj is not root) or isinstance(obj, STOP_TYPES):
                continue
            seen.add(i)
            total += getsizeof(obj)
            todo.extend(referents(obj))
            if isinstance(obj, dict):
                todo.extend(obj.keys())  # a str-keyed dict does not traverse its keys
        return total


def parts(core: Any) -> list[tuple[str, object]]:
    """A core's components: expanded ones by their attributes, each app held by its fields
    (``apps.<field>``, summed over the apps), and the apps table itself (``apps``)."""
    out: list[tuple[str, object]] = []
    attrs = dict(vars(core))
    apps = attrs.pop("apps")
    for name in EXPAND:
        obj = attrs.pop(name, None)
        if obj is not None:
            out += [(f"{name}.{sub}", val) for sub, val in _attrs(obj).items()]
    out += list(attrs.items())
    for dep in apps.values():
        out += [(f"apps.{f}", val) for f, val in _attrs(dep).items()]
    out.append(("apps", apps))
    return out


def _attrs(obj: object) -> dict[str, object]:
    if hasattr(obj, "__dict__"):
        return dict(vars(obj))
    out: dict[str, object] = {}
    slots: Iterable[str] = getattr(type(obj), "__slots__", ())
    for s in slots:
        try:  # the slot itself: a getattr would make a lazy table (AppState.__getattr__)
            out[s] = getattr(type(obj), s).__get__(obj, type(obj))
        except AttributeError:
            continue
    return out


def by_component(walker: Walker, core: Any) -> dict[str, int]:
    """Bytes per component of one core, not counting what ``walker`` has seen already."""
    row: dict[str, int] = {}
    found = parts(core)
    block = {id(v) for _, v in found} | {id(core)}
    for name, val in found:
        row[name] = row.get(name, 0) + walker.size(val, block)
    return row
