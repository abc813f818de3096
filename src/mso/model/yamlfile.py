"""Load YAML keeping the line of every key and item, so errors can point at it.

Every document (app, scenario, node config, a deploy request's document) is untrusted: it is
loaded within limits on size, nesting depth and alias expansion, checked on libyaml's event
stream *before* the node tree is composed (libyaml's composer recurses in C and crashes on
deep nesting; a billion-laughs document expands exponentially only when walked).
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mso.errors import SpecError
from mso.model.gcpause import paused_gc

# libyaml's composer when PyYAML was built with it (10x faster); the same node tree either way.
_COMPOSER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

MAX_BYTES = 4 * 1024 * 1024  # a document larger than this is refused before parsing
MAX_DEPTH = 64  # nested mappings and sequences
MAX_ALIASES = 256  # alias references (``*name``)
MAX_EXPANDED = 20_000  # nodes an alias may add to the document when it is expanded
# keys, values and items: a 4 MiB document of tiny scalars (two million of them) took 21 s and
# 1 GB; this many is the largest app the limits allow (5,000 vertices, 20,000 edges) and more
MAX_NODES = 200_000

_STR = "tag:yaml.org,2002:str"

# A path into the document: ("vertices", "B", "cost") or ("edges", 3).
Path_ = tuple[str | int, ...]


@dataclass
class Located:
    """A parsed YAML document plus the 1-based line of each node, by path."""

    data: Any
    file: str | None
    lines: dict[Path_, int] = field(default_factory=dict)

    def line(self, path: Path_) -> int | None:
        """Line of ``path`` or of its nearest ancestor that has one."""
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return self.lines.get((), None)


class _Walker:
    """Turns a composed node tree into plain Python, recording each node's line."""

    def __init__(self, file: str | None, budget: int) -> None:
        self.file = file
        self.lines: dict[Path_, int] = {}
        self._loader = yaml.SafeLoader("")
        self.budget = budget  # nodes left to walk: aliases cannot expand beyond it

    def construct(self, node: yaml.Node) -> Any:
        if node.tag == _STR:  # most scalars: the parser already gave the text
            return node.value
        return self._loader.construct_object(node, deep=True)


def _walk(w: _Walker, node: yaml.Node, path: Path_) -> Any:
    lines, file = w.lines, w.file
    lines[path] = node.start_mark.line + 1
    w.budget -= 1
    if w.budget < 0:
        raise SpecError(
            f"aliases expand to more than {MAX_EXPANDED} extra nodes", file=file, line=lines[path]
        )
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = w.construct(key_node)
            if isinstance(key, bool):  # YAML 1.1 reads on/off/yes/no as booleans
                raise SpecError(
                    f"key {key_node.value!r} reads as a boolean; quote it: '{key_node.value}'",
                    file=file,
                    line=key_node.start_mark.line + 1,
                )
            if not isinstance(key, str | int):
                raise SpecError(
                    f"mapping keys must be strings, got {type(key).__name__}",
                    file=file,
                    line=key_node.start_mark.line + 1,
                )
            if key in out:
                raise SpecError(
                    f"duplicate key {key!r}",
                    file=file,
                    line=key_node.start_mark.line + 1,
                    field=".".join(str(p) for p in (*path, key)),
                )
            out[key] = _walk(w, value_node, (*path, key))
            lines[(*path, key)] = key_node.start_mark.line + 1
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_walk(w, item, (*path, i)) for i, item in enumerate(node.value)]
    return w.construct(node)


def _check_limits(text: str, file: str | None) -> int:
    """Depth and alias counts from the event stream; returns the number of nodes."""
    if len(text) > MAX_BYTES:
        raise SpecError(f"document is larger than {MAX_BYTES // 1024 // 1024} MiB", file=file)
    depth = nodes = aliases = 0
    for ev in yaml.parse(text, Loader=_COMPOSER):
        if isinstance(ev, yaml.CollectionStartEvent):
            depth += 1
            nodes += 1
            if depth > MAX_DEPTH:
                line = ev.start_mark.line + 1 if ev.start_mark else None
                raise SpecError(f"nested deeper than {MAX_DEPTH} levels", file=file, line=line)
        elif isinstance(ev, yaml.CollectionEndEvent):
            depth -= 1
        elif isinstance(ev, yaml.ScalarEvent):
            nodes += 1
            if nodes > MAX_NODES:  # counted as they come: the rest is never parsed
                line = ev.start_mark.line + 1 if ev.start_mark else None
                raise SpecError(f"more than {MAX_NODES:,} nodes", file=file, line=line)
        elif isinstance(ev, yaml.AliasEvent):
            aliases += 1
            if aliases > MAX_ALIASES:
                line = ev.start_mark.line + 1 if ev.start_mark else None
                raise SpecError(f"more than {MAX_ALIASES} aliases", file=file, line=line)
    return nodes


@paused_gc()
def load_yaml(text: str, file: str | None = None) -> Located:
    """Parse one YAML document within the limits; malformed YAML becomes a SpecError with its
    line."""
    try:
        nodes = _check_limits(text, file)
        root = yaml.compose(text, Loader=_COMPOSER)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        problem = exc.problem or str(exc)
        ctx = exc.context_mark
        if ctx is not None and line is not None and ctx.line + 1 < line:
            # the problem shows where parsing stopped; say where the construct began too
            problem += f" ({exc.context or 'started'} at line {ctx.line + 1})"
            if line > text.count("\n") + (0 if text.endswith("\n") else 1):
                line = ctx.line + 1  # past the end of the file: point at the opening line
        raise SpecError(f"malformed YAML: {problem}", file=file, line=line) from None
    except yaml.YAMLError as exc:
        raise SpecError(f"malformed YAML: {exc}", file=file) from None
    if root is None:
        return Located(None, file, {})
    walker = _Walker(file, nodes + MAX_EXPANDED)
    try:
        data = _walk(walker, root, ())
    except yaml.constructor.ConstructorError as exc:
        mark = exc.problem_mark
        raise SpecError(
            f"malformed YAML: {exc.problem}", file=file, line=mark.line + 1 if mark else None
        ) from None
    return Located(data, file, walker.lines)


def load_yaml_file(path: str | Path) -> Located:
    """Read and parse a YAML file; a missing or unreadable file is a SpecError."""
    return load_yaml(read_text_file(path), str(path))


def read_text_file(path: str | Path, limit: int = MAX_BYTES) -> str:
    """A regular file's UTF-8 text, at most ``limit`` bytes (never a device, FIFO or
    directory: ``/dev/zero`` would never end)."""
    p = Path(path)
    try:
        st = os.stat(p)
        if not stat.S_ISREG(st.st_mode):
            raise SpecError("not a regular file", file=str(p))
        with p.open("rb") as f:
            raw = f.read(limit + 1)
    except OSError as exc:
        raise SpecError(f"cannot read file: {exc.strerror}", file=str(p)) from None
    if len(raw) > limit:
        raise SpecError(f"file is larger than {limit // 1024 // 1024} MiB", file=str(p))
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise SpecError("file is not UTF-8 text", file=str(p)) from None
