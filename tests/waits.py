"""How long a test waits for something that should happen: a loaded machine (2 cores, other
suites beside) makes seconds into tens of seconds, so every deadline on a wait goes through
``patience``. A wait returns as soon as its event happens; only a failure waits the whole time.
``MSO_TEST_TIMEOUT_SCALE`` multiplies them (default 3: generous; raise it on a slower box)."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

_DEFAULT_SCALE = 3.0


def scale() -> float:
    """The factor from ``MSO_TEST_TIMEOUT_SCALE``; a bad value is an error, not a silent 1."""
    raw = os.environ.get("MSO_TEST_TIMEOUT_SCALE", "")
    if not raw:
        return _DEFAULT_SCALE
    try:
        factor = float(raw)
    except ValueError:
        raise ValueError(f"MSO_TEST_TIMEOUT_SCALE={raw!r}: not a number") from None
    if not factor > 0:
        raise ValueError(f"MSO_TEST_TIMEOUT_SCALE={raw!r}: must be > 0")
    return factor


def patience(seconds: float) -> float:
    """The deadline for a wait that takes ``seconds`` on a quiet machine, scaled."""
    return seconds * scale()


async def until(
    read: Callable[[], Awaitable[dict[str, Any]]],
    ok: Callable[[dict[str, Any]], bool],
    timeout: float,
    what: str,
    show: Callable[[dict[str, Any]], object] | None = None,
) -> dict[str, Any]:
    """Poll ``read()`` (a status) until ``ok`` holds, or fail saying what did not happen by
    the scaled deadline. A status call that gets no answer in time (a node just killed, a link
    just broken, a loaded machine) is polled again until that deadline, and so is a status that
    lacks what ``ok`` reads (a ``KeyError``: the node or app is not there yet). A failure prints
    ``show(last status)`` when given, else the whole status."""
    from mso.client import NodeUnreachable

    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience(timeout)
    got: dict[str, Any] = {}
    while True:
        try:
            got = await read()
        except NodeUnreachable:
            if loop.time() > deadline:
                raise
            await asyncio.sleep(0.1)
            continue
        try:
            if ok(got):
                return got
        except KeyError:  # a node, app or vertex not in the status yet: not yet
            pass
        if loop.time() > deadline:
            last = got if show is None else _shown(show, got)
            raise AssertionError(f"{what} within {patience(timeout):g} s; last: {last}")
        await asyncio.sleep(0.1)  # poll period, not synchronisation


async def holds(check: Callable[[], object], timeout: float, what: str) -> None:
    """Return once ``check()`` is true (state this process holds: a node driver's counters),
    looked at every 10 ms, or fail saying what did not happen by the scaled deadline."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience(timeout)
    while not check():
        if loop.time() > deadline:
            raise AssertionError(f"{what} within {patience(timeout):g} s")
        await asyncio.sleep(0.01)  # poll period, not synchronisation


async def answered(call: Callable[[], Awaitable[T]], timeout: float, what: str) -> T:
    """``call()``'s result once it stops raising :class:`MsoError` (a node still starting, a key
    not taken yet), asked again every 50 ms until the scaled deadline, where the last error is
    raised with what did not happen."""
    from mso.errors import MsoError

    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience(timeout)
    while True:
        try:
            return await call()
        except MsoError as exc:
            if loop.time() > deadline:
                raise AssertionError(f"{what} within {patience(timeout):g} s: {exc}") from exc
        await asyncio.sleep(0.05)  # poll period, not synchronisation


def listening(node: subprocess.Popen[bytes], log: Path, timeout: float = 20.0) -> int:
    """The port an ``mso node --listen 127.0.0.1:0`` process listens on, read from its log's
    start line (``listen=HOST:PORT``, written once it listens) as soon as it is there; a node
    that exits first fails at once with its log. A port picked by binding a socket and closing
    it could be taken by another worker's process before the node binds it: the kernel's pick
    at the node's own bind cannot."""
    deadline = time.monotonic() + patience(timeout)
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        found = re.search(r"event=start listen=[\d.]+:(\d+)", text)
        if found:
            return int(found.group(1))
        if node.poll() is not None:
            raise AssertionError(f"the node exited ({node.returncode}) before listening: {text}")
        if time.monotonic() > deadline:
            raise AssertionError(f"the node's start line within {patience(timeout):g} s: {text}")
        time.sleep(0.05)  # poll period, not synchronisation


def _shown(show: Callable[[dict[str, Any]], object], got: dict[str, Any]) -> object:
    """What a failed wait prints of the last status: the part that tells why (a whole status
    is cut off in CI's log)."""
    try:
        return show(got)
    except Exception as exc:  # a status without what ``show`` reads: say so, and print it all
        return f"({exc!r}) {got}"
