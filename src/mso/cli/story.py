"""What ``mso emulate``'s console tells as the run goes: the moves as they happen, each with who
asked for it in words and how long it took (from the nodes' own records of their moves,
``moves`` in their status), and the operator's command lines read from its terminal or pipe."""

from __future__ import annotations

import asyncio
import os
import stat
import sys
import threading
from collections.abc import Callable
from typing import Any

from mso.emu.commands import Commands
from mso.statusview import move_line

Tell = Callable[[float, str], None]


def console_input(loop: asyncio.AbstractEventLoop) -> asyncio.Queue[str | None] | None:
    """Lines typed at the console (or piped in), as they come; None at the end of input. No
    queue when stdin is neither a terminal nor a pipe (a file, /dev/null, a test's buffer).

    A thread reads them: asyncio's pipe reader would make the terminal non-blocking, and the
    console's own output shares it."""
    try:
        mode = os.fstat(sys.stdin.fileno()).st_mode
    except (OSError, ValueError, AttributeError):
        return None
    if not (sys.stdin.isatty() or stat.S_ISFIFO(mode)):
        return None
    lines: asyncio.Queue[str | None] = asyncio.Queue()

    def read() -> None:
        while True:
            try:
                line = sys.stdin.readline(4096)
            except (OSError, ValueError, UnicodeDecodeError):
                line = ""
            try:
                loop.call_soon_threadsafe(lines.put_nowait, line or None)
            except RuntimeError:  # the loop is closed: the run is over
                return
            if not line:
                return

    threading.Thread(target=read, name="console", daemon=True).start()
    return lines


async def read_commands(lines: asyncio.Queue[str | None], commands: Commands, tell: Tell) -> None:
    """Carry out the console's command lines as they come (a bad one is answered, never
    fatal); at the end of input the run goes on."""
    while (line := await lines.get()) is not None:
        if not line.strip():
            continue
        answer = await commands.reply(line)
        if not answer["ok"]:
            tell(commands.emu.now(), f"command {line.strip()!r} refused: {answer['error']}")


class MoveWatch:
    """Tells each move once: the nodes' records (who asked, how long), and any change of
    placement no record explains (a node that restarted forgets its records)."""

    def __init__(self) -> None:
        self._seen: set[tuple[Any, ...]] = set()
        self._placement: dict[tuple[str, str], str] = {}

    def placed(self, app: str, placement: dict[str, str]) -> None:
        for v, n in placement.items():
            self._placement[(app, v)] = n

    def moves(self, nodes: dict[str, Any], app: str, now: float) -> list[tuple[float, str]]:
        """The moves of ``app`` not told yet, as (run time, line), oldest first; ``now`` is
        the run time of the status ``nodes`` (each record's age places it on that clock)."""
        out: list[tuple[float, str]] = []
        explained: set[str] = set()
        for nid, st in sorted(nodes.items()):
            for rec in st.get("moves", []):
                if rec.get("app") != app:
                    continue
                key = (nid, st.get("incarnation"), rec.get("seq"))
                if key in self._seen:
                    continue
                self._seen.add(key)
                if rec.get("vertex"):
                    explained.add(rec["vertex"])
                for part in str(rec.get("detail", "")).split():
                    explained.add(part.split("->")[0])  # a remap's "v->N" parts
                out.append((now - float(rec.get("ago_s", 0.0)), move_line(rec)))
        for nid, st in sorted(nodes.items()):
            for v in st.get("apps", {}).get(app, {}).get("vertices", {}):
                old = self._placement.get((app, v))
                self._placement[(app, v)] = nid
                if old is not None and old != nid and v not in explained:
                    out.append((now, f"{app}: {v} {old} -> {nid} (no node told who asked)"))
        return sorted(out)
