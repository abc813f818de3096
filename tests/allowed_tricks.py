"""A module a node's owner allowed (``--allow-code allowed_tricks``) that also holds every way
an attribute path could reach code the owner never named: imported modules, re-exported
names, lambdas, partials, exec'd and re-homed functions, outside decorators' wrappers,
instances and a module ``__getattr__``. ``tests/test_code_allowlist.py`` names each one.
Importing it runs nothing."""

from __future__ import annotations

import builtins  # noqa: F401  (reached as allowed_tricks:builtins.eval)
import contextlib
import functools
import os
import shutil
import subprocess
import sys  # noqa: F401  (reached as allowed_tricks:sys.modules)
import types
from collections.abc import Callable, Iterator
from os import system  # noqa: F401  (a re-exported builtin)
from subprocess import Popen  # noqa: F401  (a re-exported class)
from typing import Any


def plain(event: Any) -> Any:
    """Code defined here: allowed."""
    return event


class Holder:
    """A class defined here; some of its attributes come from elsewhere."""

    runner = staticmethod(os.system)
    sub = subprocess

    class Inner:
        def __call__(self, event: Any) -> Any:
            return event

    @classmethod
    def make(cls) -> Holder:
        return cls()

    def method(self, event: Any) -> Any:
        return event


class Sub(subprocess.Popen):  # type: ignore[type-arg]
    """Defined here (allowed); what it inherits was defined in subprocess (refused)."""


holder = Holder()
shell = lambda command: os.system(command)  # noqa: E731
run = functools.partial(subprocess.run, shell=True)
evaluate = eval
exec("def made(command):\n    return os.system(command)\n", globals())


def _outside() -> Callable[[str], int]:
    def inner(command: str) -> int:
        return os.system(command)

    return inner


nested = _outside()


@contextlib.contextmanager
def managed(command: str) -> Iterator[int]:
    yield 0


rmtree = types.FunctionType(shutil.rmtree.__code__, shutil.rmtree.__globals__, "rmtree")
rmtree.__module__ = __name__
rmtree.__qualname__ = "rmtree"


def __getattr__(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    return os.system
