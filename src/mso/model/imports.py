"""Resolve ``package.module:attr`` import paths: vertex code is only ever loaded this way."""

from __future__ import annotations

import importlib
import re
from typing import Any

_PATH = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*$")


class ImportPathError(ValueError):
    """The import path is malformed or does not resolve; the message says which."""


def resolve(path: str) -> Any:
    """Import ``package.module:attr`` and return the attribute."""
    if not isinstance(path, str) or not _PATH.match(path):
        raise ImportPathError(f"expected an import path 'package.module:attr', got {path!r}")
    module_name, _, attr_path = path.partition(":")
    try:
        obj: Any = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise ImportPathError(
            f"import path {path!r} does not resolve: no module named {exc.name!r}"
        ) from None
    except Exception as exc:  # a module that fails while importing: report, never crash
        raise ImportPathError(
            f"import path {path!r} does not resolve: importing {module_name!r} raised "
            f"{type(exc).__name__}: {exc}"
        ) from None
    for part in attr_path.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ImportPathError(
                f"import path {path!r} does not resolve: {module_name!r} has no attribute "
                f"{attr_path!r}"
            ) from None
    return obj


def path_of(obj: Any) -> str | None:
    """The import path that resolves back to ``obj``, if there is one (for YAML export)."""
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if not module or not qualname or "<" in qualname:
        return None
    path = f"{module}:{qualname}"
    try:
        return path if resolve(path) is obj else None
    except ImportPathError:
        return None
