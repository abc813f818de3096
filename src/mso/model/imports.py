"""Resolve ``package.module:attr`` import paths: vertex code is only ever loaded this way.

A node runs only code its owner named (``mso node --allow-code``, the ``allow_code`` key of its
configuration, ``$MSO_ALLOW_CODE``; mso's bundled vertex modules by default):
:func:`allow_code` sets the process's allowlist, and :func:`resolve` checks every path against
it twice. *Before* importing anything, the path's module must be allowed (or a submodule of an
allowed one), so ``os:system`` or ``subprocess:Popen`` is refused with nothing imported. *After*
following the attribute path, the object it reached must itself be code *defined in* an allowed
module: a class, a ``def`` function, or a class's method, whose ``__module__`` is allowed, whose
own name leads back to it (so not a lambda, a ``functools.partial``, or a callable made at run
time) and, for a function, whose code was compiled from an allowed module's file (so not a
wrapper an outside decorator made). The path may pass only through classes defined in allowed
modules: never through a module (``mso.benchmarks.common:os.system``, ``pkg.mod:sys.modules``),
an instance, or a special ``__name__`` (``Class.__init__.__globals__``, ``__builtins__``).
A process that set no allowlist (a library use: the CLI validating a local file, the simulator,
tests) may import any module and follow any path.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
import types
from collections.abc import Iterable
from typing import Any

_PATH = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*$")


# what a node may run unless its owner says otherwise: the vertex and format code shipped with
# mso. Not all of mso.examples and mso.benchmarks: their harnesses write files and start
# processes, and a policy's params become a callable's keyword arguments. mso.ros2 (the
# optional extra) holds the ROS 2 and bag vertices and the message formats.
DEFAULT_ALLOWED = (
    "mso.examples.convoy",
    "mso.sim.vertices",
    "mso.benchmarks.vertices",
    "mso.ros2",
)
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


def _is_allowed(module: object) -> bool:
    if _allowed is None:
        return True
    if not isinstance(module, str):
        return False
    return any(module == a or module.startswith(a + ".") for a in _allowed)


def _allowlist() -> str:
    return ", ".join(_allowed or ()) or "empty"


def check_allowed(path: str) -> None:
    """Raise unless the module of ``path`` is on the allowlist (nothing is imported)."""
    if _allowed is None:
        return
    module = path.partition(":")[0]
    if _is_allowed(module):
        return
    raise ImportPathError(
        f"import path {path!r} is refused: module {module!r} is not on this node's code "
        f"allowlist ({_allowlist()}); its owner can allow it with --allow-code MODULE"
    )


def _refuse(path: str, why: str) -> ImportPathError:
    return ImportPathError(
        f"import path {path!r} is refused: {why}; a node runs only classes and functions "
        f"defined in the modules on its code allowlist ({_allowlist()})"
    )


def _describe(obj: object) -> str:
    if isinstance(obj, types.ModuleType):
        return f"the module {obj.__name__!r}"
    if isinstance(obj, type | types.FunctionType):
        kind = "class" if isinstance(obj, type) else "function"
        return f"the {kind} {obj.__qualname__!r} of {obj.__module__!r}"
    return f"a {type(obj).__name__!r} object"


def _file_of(module: object) -> str | None:
    file = getattr(module, "__file__", None)
    return os.path.realpath(file) if isinstance(file, str) else None


def _compiled_in_allowed(fn: types.FunctionType) -> bool:
    """Was ``fn``'s code compiled from the file of an allowed module (not made by a decorator,
    ``exec`` or ``eval`` elsewhere and given an allowed ``__module__``)?"""
    source = os.path.realpath(fn.__code__.co_filename)
    if _file_of(sys.modules.get(fn.__module__)) == source:  # the common case, checked first
        return True
    return any(
        _is_allowed(name) and _file_of(mod) == source for name, mod in list(sys.modules.items())
    )


def _defined_at_home(obj: Any) -> bool:
    """Does ``obj``'s own ``__module__:__qualname__`` lead back to it (a definition, not a
    lambda, a ``<locals>`` function or a callable built at run time)?"""
    module = sys.modules.get(getattr(obj, "__module__", None) or "")
    qualname = getattr(obj, "__qualname__", None)
    if module is None or not isinstance(qualname, str) or "<" in qualname:
        return False
    target: Any = module
    for part in qualname.split("."):
        try:
            target = getattr(target, part)
        except Exception:  # missing, or a descriptor that raises
            return False
    if isinstance(target, types.MethodType):
        target = target.__func__
    return target is obj


def _check_defined(path: str, shown: str, obj: Any) -> None:
    """Raise unless ``obj`` (reached as ``shown``) is a class, a function or a class's method
    defined in an allowed module."""
    if isinstance(obj, types.MethodType):  # a classmethod reached through its class
        if not isinstance(obj.__self__, type):
            raise _refuse(path, f"{shown!r} is a method bound to an instance, not a definition")
        obj = obj.__func__
    if isinstance(obj, types.ModuleType):
        raise _refuse(path, f"{shown!r} is {_describe(obj)}, not a class or function")
    if not isinstance(obj, type | types.FunctionType):
        raise _refuse(
            path, f"{shown!r} is {_describe(obj)}, not a class or function defined in a module"
        )
    if not _is_allowed(obj.__module__):
        raise _refuse(
            path,
            f"{shown!r} is {_describe(obj)}, a module not on the allowlist (a name an "
            "allowed module imported from elsewhere)",
        )
    if not _defined_at_home(obj):
        raise _refuse(
            path,
            f"{shown!r} is {_describe(obj)}, which is not found under its own name there "
            "(a lambda, a nested function or one made at run time)",
        )
    if isinstance(obj, types.FunctionType) and not _compiled_in_allowed(obj):
        raise _refuse(
            path,
            f"{shown!r} is a function compiled from {obj.__code__.co_filename!r}, outside the "
            "allowed modules (a wrapper made by an outside decorator, exec or eval)",
        )


def resolve(path: str) -> Any:
    """Import ``package.module:attr`` and return the attribute (under an allowlist, only if it
    is code defined in an allowed module: see the module's docstring)."""
    if not isinstance(path, str) or not _PATH.match(path):
        raise ImportPathError(f"expected an import path 'package.module:attr', got {path!r}")
    check_allowed(path)
    module_name, _, attr_path = path.partition(":")
    parts = attr_path.split(".")
    if _allowed is not None:
        for part in parts:
            if part.startswith("__") and part.endswith("__"):
                raise _refuse(path, f"{part!r} is a special attribute")
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
    for i, part in enumerate(parts):
        shown = f"{module_name}:{'.'.join(parts[:i])}"
        if _allowed is not None and i > 0:  # pass only through classes defined in allowed code
            if not isinstance(obj, type):
                raise _refuse(
                    path, f"{shown!r} is {_describe(obj)}; a path may pass only through classes"
                )
            _check_defined(path, shown, obj)
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ImportPathError(
                f"import path {path!r} does not resolve: {module_name!r} has no attribute "
                f"{attr_path!r}"
            ) from None
        except Exception as exc:  # a descriptor that raises: report, never crash
            raise ImportPathError(
                f"import path {path!r} does not resolve: reading {part!r} raised "
                f"{type(exc).__name__}: {exc}"
            ) from None
    if _allowed is not None:
        _check_defined(path, path, obj)
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
