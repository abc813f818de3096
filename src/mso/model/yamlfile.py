"""Load YAML keeping the line of every key and item, so errors can point at it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mso.errors import SpecError

# libyaml's composer when PyYAML was built with it (10x faster); the same node tree either way.
_COMPOSER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

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

    def __init__(self, file: str | None) -> None:
        self.file = file
        self.lines: dict[Path_, int] = {}
        self._loader = yaml.SafeLoader("")

    def construct(self, node: yaml.Node) -> Any:
        return self._loader.construct_object(node, deep=True)


def _walk(w: _Walker, node: yaml.Node, path: Path_) -> Any:
    lines, file = w.lines, w.file
    lines[path] = node.start_mark.line + 1
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


def load_yaml(text: str, file: str | None = None) -> Located:
    """Parse one YAML document; malformed YAML becomes a SpecError with its line."""
    try:
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
    walker = _Walker(file)
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
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise SpecError(f"cannot read file: {exc.strerror}", file=str(p)) from None
    except UnicodeDecodeError:
        raise SpecError("file is not UTF-8 text", file=str(p)) from None
    return load_yaml(text, str(p))
