"""An emulator's commands while it runs: one line each (``fail N3``, ``restart N3``,
``cut N1 N2``, ``heal N1 N2``, ``move N3 120 40``, ``stop``), typed at its console or sent by
``mso emulator`` / :class:`mso.api.EmulatorControl` over a Unix socket beside its state file
(in the directory only its user, and root, may enter). The reply is one line of JSON:
``{"ok": true, "said": "..."}`` or ``{"ok": false, "error": "..."}``.

A command's error is its reply, never the run's end: the emulator never gives up.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shlex
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from mso.emu.controller import Emulator
from mso.emu.overlays import control_file, give
from mso.errors import MsoError

HELP = (
    "commands: fail NODE | restart NODE | cut A B | heal A B | move NODE X Y | "
    "stop (ends the run with its summary) | help"
)
MAX_LINE = 1024  # a command is a few words: a longer line is refused, never buffered


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise MsoError(f"{what}: expected a number of metres, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise MsoError(f"{what}: expected a finite number, got {text!r}")
    return value


@dataclass
class Commands:
    """Parse and carry out command lines on ``emu``; ``stop`` sets ``done``."""

    emu: Emulator
    done: asyncio.Event = field(default_factory=asyncio.Event)

    async def run(self, line: str) -> str:
        """Carry out one command line; what it did, in words (an :class:`MsoError` if not)."""
        try:
            words = shlex.split(line)
        except ValueError as exc:
            raise MsoError(f"cannot read {line!r}: {exc}") from None
        if not words:
            return ""
        verb, args = words[0].lower(), words[1:]
        arity: dict[str, tuple[int, Callable[..., Awaitable[str]]]] = {
            "fail": (1, self.emu.fail),
            "restart": (1, self.emu.restart),
            "cut": (2, self.emu.cut),
            "heal": (2, self.emu.heal),
        }
        if verb in ("help", "?"):
            return HELP
        if verb in ("stop", "quit", "exit"):
            self.done.set()
            return "stopping: the summary follows"
        if verb == "move":
            if len(args) != 3:
                raise MsoError("move: expected NODE X Y (metres)")
            x, y = _number(args[1], "move X"), _number(args[2], "move Y")
            return await self.emu.move(args[0], x, y)
        if verb not in arity:
            raise MsoError(f"unknown command {verb!r}; {HELP}")
        n, act = arity[verb]
        if len(args) != n:
            raise MsoError(f"{verb}: expected {verb} {'NODE' if n == 1 else 'A B'}")
        return await act(*args)

    async def reply(self, line: str) -> dict[str, object]:
        """A command line's outcome as the socket's reply (told on the console too)."""
        try:
            said = await self.run(line)
        except MsoError as exc:
            return {"ok": False, "error": str(exc)}
        if said:
            self.emu.say(f"command {line.strip()!r}: {said}")
        return {"ok": True, "said": said}


class ControlSocket:
    """The emulator's command socket: one connection, one line in, one line out."""

    def __init__(self, commands: Commands, name: str) -> None:
        self.commands = commands
        self.path = control_file(name)
        self._server: asyncio.AbstractServer | None = None
        self._dir_fd: int | None = None

    async def start(self) -> None:
        self.path.unlink(missing_ok=True)
        where = str(self.path)
        if len(where.encode()) > 100:  # sun_path holds 108 bytes: bind through the folder
            self._dir_fd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY)
            where = f"/proc/self/fd/{self._dir_fd}/{self.path.name}"
        old = os.umask(0o177)  # the socket is its user's only (the folder is too)
        try:
            self._server = await asyncio.start_unix_server(self._serve, where, limit=MAX_LINE)
        finally:
            os.umask(old)
        give(self.path)  # under sudo, the user who ran it may command it

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                line = await asyncio.wait_for(reader.readline(), 5.0)
            except ValueError:  # longer than the limit
                line = b""
            if len(line) > MAX_LINE or not line.endswith(b"\n"):
                answer: dict[str, object] = {
                    "ok": False,
                    "error": f"expected one command line of at most {MAX_LINE} bytes",
                }
            else:
                try:
                    text = line.decode()
                except UnicodeDecodeError:
                    answer = {"ok": False, "error": "a command line must be UTF-8 text"}
                else:
                    answer = await self.commands.reply(text)
            writer.write(json.dumps(answer).encode() + b"\n")
            await writer.drain()
        except (TimeoutError, ValueError, OSError):
            pass  # a client that said nothing, too much, or left: nothing to answer
        finally:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None
        self.path.unlink(missing_ok=True)
        if self._dir_fd is not None:
            os.close(self._dir_fd)
            self._dir_fd = None
