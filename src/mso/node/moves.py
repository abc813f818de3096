"""Who asked for each move, in words, and the node's last few moves for its status.

A move's procedure knows only what kind of asker started it (``by``: an operator's request, the
rules, a step of a remap, a restore after a crash or a failure). The core tells this log, when
it carries out a rule's action, which rule on which node asked and why; when the move's
``Happened`` comes, the log words it (``asked``) — "the relocation rule on N1: …", "an operator
(mso relocate)", "a recovery after N2 failed" — and keeps it, with the time it ended, for
status (``moves``: the console and the dashboard tell each once, on their own clock, from its
age). Sans-IO: times are passed in.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import msgspec

from mso.protocol.events import Happened

MOVES = frozenset({"relocation", "restore", "remap", "recovery"})
MAX_MOVES = 32  # kept for status: a poller every 2 s sees them all
MAX_ASKED = 256  # rule actions awaiting their move's end (a refused one is never answered)


class MoveRecord(msgspec.Struct, frozen=True, kw_only=True):
    """One move this node coordinated, as status shows it."""

    seq: int  # this node's count of moves: with its incarnation, tells a record once
    what: str  # relocation, restore, remap, recovery
    app: str
    vertex: str  # "" for a remap: ``detail`` says where each vertex went
    detail: str  # "N1 -> N2", "a->N2 b->N3"
    by: str  # the kind of asker: operator, rule, recovery, failure of N2, ...
    asked: str  # who asked, in words
    took_ms: float | None
    error: str
    ago_s: float  # how long before the status it ended


def asked_words(h: Happened) -> str:
    """Who asked for a move, in words, from the kind of asker its procedure knows."""
    by = h.by
    if by == "operator":
        return f"an operator (mso {'relocate' if h.what == 'relocation' else 'remap'})"
    if by == "rule":
        return "the rules of the coordinating node"
    if by == "remap":
        return "a step of a remap"
    if by == "recovery":
        return "a recovery (the vertex's node failed or restarted)"
    if by.startswith("failure of "):
        return f"a recovery after {by.removeprefix('failure of ')} failed"
    return by or "nobody said"


class MoveLog:
    """What the core tells of rule actions, and the moves that ended, bounded."""

    def __init__(self) -> None:
        # in the order asked: two remaps of one app asked in one evaluation (chains whose route
        # changed) are carried out one after the other, and each keeps its own words
        self._asked: dict[tuple[str, str], deque[str]] = {}
        self._moves: deque[tuple[float, MoveRecord]] = deque(maxlen=MAX_MOVES)
        self._seq = 0

    def asking(self, app: str, vertex: str, words: str) -> None:
        """A rule's action is being carried out: the move of ``vertex`` of ``app`` (``""``:
        a remap of it) is asked for by ``words``."""
        if (app, vertex) not in self._asked and len(self._asked) >= MAX_ASKED:
            self._asked.pop(next(iter(self._asked)))
        self._asked.setdefault((app, vertex), deque(maxlen=MAX_ASKED)).append(words)

    def happened(self, h: Happened, now: float) -> Happened:
        """``h`` with who asked in words; a move is kept for status (a remap's own steps are
        told by the remap's record)."""
        if h.what not in MOVES:
            return h
        asked = ""
        if h.by == "rule" and (queue := self._asked.get((h.app, h.subject))):
            asked = queue.popleft()
            if not queue:
                del self._asked[(h.app, h.subject)]
        h = replace(h, asked=asked or asked_words(h))
        if h.by != "remap":
            self._seq += 1
            rec = MoveRecord(
                seq=self._seq, what=h.what, app=h.app, vertex=h.subject, detail=h.detail,
                by=h.by, asked=h.asked, took_ms=h.took_ms, error=h.error, ago_s=0.0,
            )  # fmt: skip
            self._moves.append((now, rec))
        return h

    def status(self, now: float) -> list[MoveRecord]:
        return [
            msgspec.structs.replace(rec, ago_s=round(max(0.0, now - at), 3))
            for at, rec in self._moves
        ]
