"""Which accepted connections a node keeps: slots per source, a handshake deadline, back-off.

A MANET is open air, so anyone may open connections to a node. A connection that has not yet
proved the overlay key and said who it is (*pending*) takes a slot of a small pool; one that
has (*introduced*) leaves it. An outsider with no key used to hold every slot by reopening each
the moment the handshake deadline closed it (0 of 31 legitimate status requests answered), so:

- a new connection is never refused for the pool: when its source (the remote address) holds
  ``max_pending_per_address`` pending slots, or the pool ``max_pending``, the *oldest* pending
  connection of the source that weighs most (unknown, most strikes, most slots) is closed
  instead (``evicted``). An outsider's
  connections are always older than a member's fresh one, which proves the key within a round
  trip and leaves the pool, so it would have to open a pool's worth of connections within that
  round trip to push a member's out;
- a source whose connections fail the handshake (its deadline passed, or a wrong key) or are
  evicted *backs off*: each is a strike (strikes halve every ``strike_half_life_s``) and its pending
  connections get ``handshake_s / (1 + strikes)`` (never less than ``handshake_min_s``) and are
  evicted before those of a source with fewer strikes;
- sources a connection recently came from that proved the key (*known*) are evicted last;
- introduced clients are bounded in number (``max_connections``, ``max_per_address`` from one
  source); a neighbour the routing view names is always taken (a link is worth more than a
  client), never counted against them.

Sans-IO: the transport tells it what happened (with the time) and closes what it returns. Its
tables are bounded (``max_sources`` addresses remembered).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol, TypeVar

from mso.net.limits import ConnectionCounters, Limits

MAX_SOURCES = 4096  # addresses whose strikes or known status are remembered
V = TypeVar("V")


class Slot(Protocol):
    """What admission needs of a connection."""

    address: str
    opened: float

    def abort(self) -> None: ...


class Admission:
    """The pending pool, each source's strikes and whether it is known."""

    def __init__(self, limits: Limits, counters: ConnectionCounters) -> None:
        self.limits = limits
        self.counters = counters
        self.pending: dict[str, list[Slot]] = {}  # by source, oldest first
        self._strikes: dict[str, tuple[float, float]] = {}  # source -> (strikes, as of)
        self._known: dict[str, float] = {}  # source -> when a connection from it proved the key

    @property
    def pending_count(self) -> int:
        return sum(len(slots) for slots in self.pending.values())

    def strikes(self, address: str, now: float) -> float:
        """The source's failed handshakes, halving every ``strike_half_life_s``."""
        n, at = self._strikes.get(address, (0.0, now))
        return float(n * 0.5 ** ((now - at) / self.limits.strike_half_life_s))

    def known(self, address: str, now: float) -> bool:
        at = self._known.get(address)
        return at is not None and now - at <= self.limits.known_for_s

    def deadline(self, conn: Slot, now: float) -> float:
        """When a pending connection must have proved the key and said who it is."""
        lim = self.limits
        if self.known(conn.address, now):
            return conn.opened + lim.handshake_s
        allowed = lim.handshake_s / (1.0 + self.strikes(conn.address, now))
        return conn.opened + max(lim.handshake_min_s, allowed)

    def admit(self, conn: Slot, now: float) -> list[Slot]:
        """Take a new connection into the pool; returns the pending ones to close for it."""
        lim, evict = self.limits, []
        mine = self.pending.setdefault(conn.address, [])
        if len(mine) >= lim.max_pending_per_address:
            evict.append(mine.pop(0))
        elif self.pending_count >= lim.max_pending:
            evict.append(self._victim(now))
        mine.append(conn)
        self.counters.evicted += len(evict)
        for victim in evict:  # a strike: its source made us close a connection
            self._drop_empty(victim.address)
            self._strike(victim.address, now)
        return evict

    def _victim(self, now: float) -> Slot:
        """The oldest pending connection of the source that weighs most: unknown before
        known, then the most strikes, then the most pending slots."""

        def weight(address: str) -> tuple[bool, float, int]:
            return (
                not self.known(address, now),
                self.strikes(address, now),
                len(self.pending[address]),
            )

        source = max((a for a, slots in self.pending.items() if slots), key=weight)
        return self.pending[source].pop(0)

    def introduced(self, conn: Slot, now: float) -> None:
        """The connection proved the key and said who it is: it leaves the pool, and its
        source is known."""
        self.gone(conn)
        self._remember(self._known, conn.address, now)

    def failed(self, conn: Slot, now: float) -> None:
        """Its handshake failed (deadline, wrong key): a strike for its source."""
        self.gone(conn)
        self._strike(conn.address, now)

    def _strike(self, address: str, now: float) -> None:
        self._remember(self._strikes, address, (self.strikes(address, now) + 1, now))

    def is_pending(self, conn: Slot) -> bool:
        return conn in self.pending.get(conn.address, ())

    def gone(self, conn: Slot) -> None:
        slots = self.pending.get(conn.address)
        if slots is not None and conn in slots:
            slots.remove(conn)
            self._drop_empty(conn.address)

    def overdue(self, now: float) -> Iterable[Slot]:
        """Pending connections past their deadline."""
        return [c for slots in self.pending.values() for c in slots if now > self.deadline(c, now)]

    def _drop_empty(self, address: str) -> None:
        if not self.pending.get(address, True):
            del self.pending[address]

    @staticmethod
    def _remember(table: dict[str, V], address: str, value: V) -> None:
        table.pop(address, None)  # most recent last, so the oldest is dropped first
        table[address] = value
        while len(table) > MAX_SOURCES:
            del table[next(iter(table))]
