"""Where an edge's producer spills the events it cannot deliver yet, and what it persists.

Sans-IO: the protocol only sees this interface; the driver provides it. The simulator gives
each node a :class:`MemorySpill` that outlives the node's restarts (as a file would); the daemon
a SQLite file under its state directory (:mod:`mso.daemon.spill`). Keys name an edge instance
(``app/epoch/edge``); events are kept by sequence number, contiguous per key: appended at the
end (or, when a held edge moves what it had in memory into the store, just before the first)
and trimmed at the front. Positions are small integers that must survive a restart (the next
sequence number of a source's edge), saved on change, and, while a source's edge holds events
here, the output positions its consumer's last ack brought (a restore after a restart numbers
the replay as the lost instances did); dropping a key forgets all of them. Notes are named
integers kept one under a prefix (where a vertex runs and at which move, as its host last said:
:func:`mso.protocol.procedures.placement.remember`).
"""

from __future__ import annotations

import itertools
from collections import deque
from typing import Protocol


def placement_notes(app: str, vertex: str = "") -> str:
    """The prefix of an app's placement notes (of one vertex's, given ``vertex``)."""
    return f"{app}/placed/{vertex}/" if vertex else f"{app}/placed/"


class SpillStore(Protocol):
    """A durable log of events per edge, and positions that survive a restart."""

    def append(self, key: str, seq: int, events: list[bytes]) -> None:
        """Keep ``events`` as ``seq``, ``seq + 1``, ... (after what ``key`` holds, or right
        before it)."""

    def read(self, key: str, start: int, count: int) -> list[bytes]:
        """Up to ``count`` events of ``key`` from ``start`` on, in order."""
        ...

    def ready(self, key: str, start: int, count: int) -> list[bytes]:
        """Up to ``count`` events of ``key`` from ``start`` on, in order, that can be had
        without waiting (a first part of them, perhaps none: a store that reads apart reads
        on meanwhile and its driver tells the node when they are in)."""
        ...

    def trim(self, key: str, below: int) -> None:
        """Forget the events of ``key`` below ``below``."""

    def drop(self, key: str) -> None:
        """Forget every event of ``key``."""

    def size(self, key: str) -> int:
        """Bytes of the events ``key`` holds."""
        ...

    def span(self, key: str) -> tuple[int, int] | None:
        """``(first, last + 1)`` of the events ``key`` holds, or None."""
        ...

    def save_position(self, key: str, value: int) -> None: ...

    def position(self, key: str) -> int | None: ...

    def save_positions(
        self, key: str, at: int, positions: dict[int, int], gens: dict[int, int] | None = None
    ) -> None:
        """The consumer's output positions that came with the ack of ``key`` up to ``at``
        (replacing those saved before), and the generations of their numberings (``gens``:
        those not 0, :class:`mso.protocol.channel.OutChannel`)."""

    def saved_positions(self, key: str) -> tuple[int, dict[int, int]] | None:
        """``(at, positions)`` saved for ``key``, or None."""
        ...

    def saved_gens(self, key: str) -> dict[int, int]:
        """The generations saved with ``key``'s positions (those not 0)."""
        ...

    def note(self, prefix: str, name: str, value: int) -> None:
        """Keep ``value`` as the one note under ``prefix`` (forgetting the others there)."""

    def notes(self, prefix: str) -> dict[str, int]:
        """The notes under ``prefix`` (name -> value)."""
        ...

    def forget_notes(self, prefix: str) -> None:
        """Forget every note under ``prefix``."""


class MemorySpill:
    """The simulator's spill store: in memory, per node, kept across the node's restarts."""

    def __init__(self) -> None:
        self._logs: dict[str, deque[tuple[int, bytes]]] = {}
        self._bytes: dict[str, int] = {}
        self._positions: dict[str, int] = {}
        self._ack_positions: dict[str, tuple[int, dict[int, int]]] = {}
        self._ack_gens: dict[str, dict[int, int]] = {}
        self._notes: dict[str, int] = {}  # prefix + name -> value

    def append(self, key: str, seq: int, events: list[bytes]) -> None:
        log = self._logs.setdefault(key, deque())
        numbered = [(seq + i, e) for i, e in enumerate(events)]
        if log and seq < log[0][0]:
            log.extendleft(reversed(numbered))
        else:
            log.extend(numbered)
        self._bytes[key] = self._bytes.get(key, 0) + sum(map(len, events))

    def read(self, key: str, start: int, count: int) -> list[bytes]:
        log = self._logs.get(key)
        if not log or count <= 0:
            return []
        skip = max(0, start - log[0][0])
        return [e for _, e in itertools.islice(log, skip, skip + count)]

    def ready(self, key: str, start: int, count: int) -> list[bytes]:
        return self.read(key, start, count)

    def trim(self, key: str, below: int) -> None:
        log = self._logs.get(key)
        while log and log[0][0] < below:
            self._bytes[key] -= len(log.popleft()[1])

    def drop(self, key: str) -> None:
        self._logs.pop(key, None)
        self._bytes.pop(key, None)
        self._positions.pop(key, None)
        self._ack_positions.pop(key, None)
        self._ack_gens.pop(key, None)

    def size(self, key: str) -> int:
        return self._bytes.get(key, 0)

    def span(self, key: str) -> tuple[int, int] | None:
        log = self._logs.get(key)
        return (log[0][0], log[-1][0] + 1) if log else None

    def held_bytes(self) -> int:
        return sum(self._bytes.values())

    def save_position(self, key: str, value: int) -> None:
        self._positions[key] = value

    def position(self, key: str) -> int | None:
        return self._positions.get(key)

    def save_positions(
        self, key: str, at: int, positions: dict[int, int], gens: dict[int, int] | None = None
    ) -> None:
        self._ack_positions[key] = (at, dict(positions))
        self._ack_gens[key] = dict(gens or {})

    def saved_positions(self, key: str) -> tuple[int, dict[int, int]] | None:
        saved = self._ack_positions.get(key)
        return None if saved is None else (saved[0], dict(saved[1]))

    def saved_gens(self, key: str) -> dict[int, int]:
        return dict(self._ack_gens.get(key, {}))

    def note(self, prefix: str, name: str, value: int) -> None:
        self.forget_notes(prefix)
        self._notes[prefix + name] = value

    def notes(self, prefix: str) -> dict[str, int]:
        return {k[len(prefix) :]: v for k, v in self._notes.items() if k.startswith(prefix)}

    def forget_notes(self, prefix: str) -> None:
        for k in [k for k in self._notes if k.startswith(prefix)]:
            del self._notes[k]
