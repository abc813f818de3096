"""Resolve ``package.module:attr`` import paths: vertex code is only ever loaded this way.

A node imports only from the modules its owner allowed (``mso node --allow-code``, the
``allow_code`` key of its configuration, ``$MSO_ALLOW_CODE``; the bundled examples by
default): :func:`allow_code` sets the process's allowlist, and :func:`resolve` checks every
path against it *before* importing anything, so an app naming ``os:system`` or
``subprocess:Popen`` is refused on every node with nothing imported or run. A process that set
no allowlist (a library use: the CLI validating a local file, the simulator, tests) may import
any module.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Iterable
from typing import Any

_PATH = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*$")


# what a node may import unless its owner says otherwise: the code shipped with mso
DEFAULT_ALLOWED = ("mso.examples", "mso.sim.vertices", "mso.benchmarks")
_MODULE = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*$")
_allowed: tuple[str, ...] | None = None


class ImportPathError(ValueError):
    """The import path is malformed or does not resolve; the message says which."""


def allow_code(modules: Iterable[str] | None) -> None:
    """Restrict this process to importing code from ``modules`` and their submodules
    (``None``: no restriction)."""
    global _allowed
    if modules is None:
        _allowed = None
        return
    names = tuple(modules)
    for name in names:
        if not isinstance(name, str) or not _MODULE.match(name):
            raise ImportPathError(f"expected a module name like 'pkg.module', got {name!r}")
    _allowed = names


def allowed_code() -> tuple[str, ...] | None:
    """The modules this process may import code from (``None``: any)."""
    return _allowed


def check_allowed(path: str) -> None:
    """Raise unless the module of ``path`` is on the allowlist (nothing is imported)."""
    if _allowed is None:
        return
    module = path.partition(":")[0]
    if any(module == a or module.startswith(a + ".") for a in _allowed):
        return
    raise ImportPathError(
        f"import path {path!r} is refused: module {module!r} is not on this node's code "
        f"allowlist ({', '.join(_allowed) or 'empty'}); its owner can allow it with "
        "--allow-code MODULE"
    )


def resolve(path: str) -> Any:
    """Import ``package.module:attr`` and return the attribute."""
    if not isinstance(path, str) or not _PATH.match(path):
        raise ImportPathError(f"expected an import path 'package.module:attr', got {path!r}")
    check_allowed(path)
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
