"""Messages that overtook their app's announcement, held until it arrives: bounded. Sans-IO.

Another path may deliver a ``ChainPlaced`` or ``BuildChain`` before the ``AppAnnounce`` it
belongs to, so the core holds such messages and replays them when the announcement arrives. A
member can send them for apps it never announces: held forever, unbounded, they once grew a
node to 544 MB, kept after the sender left. So they are held within bounds, by count *and*
bytes, per sending peer and in total (a peer cannot take the others' share), for at most
:data:`EARLY_S` (a deployment's own deadline: past it the announcement is not coming), and are
dropped with their sender when it is declared failed. Every message refused or dropped is
returned as a reason the core counts (``refusals`` in status).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import msgspec

from mso.protocol import messages as m

EARLY_S = 30.0  # as long as a deployment may take (Deploy.DEADLINE_S)
MAX_APPS = 64  # apps with messages held at once


@dataclass(frozen=True)
class EarlyLimits:
    """How much one peer, and all peers together, may have held."""

    per_peer: int = 256
    per_peer_bytes: int = 4 << 20
    total: int = 1024
    total_bytes: int = 16 << 20
    hold_s: float = EARLY_S


@dataclass(frozen=True)
class _Held:
    at: float
    src: str
    app: str
    msg: m.Message
    size: int


class EarlyMessages:
    """The held messages, oldest first, with what each peer holds (count and bytes)."""

    def __init__(self, limits: EarlyLimits | None = None) -> None:
        self.limits = limits or EarlyLimits()
        self._held: deque[_Held] = deque()
        self._apps: dict[str, int] = {}  # app -> messages held for it
        self._peers: dict[str, tuple[int, int]] = {}  # peer -> (messages, bytes) held
        self._bytes = 0

    def __len__(self) -> int:
        return len(self._held)

    @property
    def bytes(self) -> int:
        return self._bytes

    def peer(self, src: str) -> tuple[int, int]:
        """(messages, bytes) ``src`` has held here."""
        return self._peers.get(src, (0, 0))

    def hold(self, src: str, app: str, msg: m.Message, now: float) -> list[str]:
        """Hold ``msg`` for ``app``; returns the reasons of what was refused or expired."""
        out = self.expire(now)
        lim = self.limits
        size = len(msgspec.msgpack.encode(msg))
        count, held = self.peer(src)
        if count >= lim.per_peer or held + size > lim.per_peer_bytes:
            return [*out, "early_over_peer_bound"]
        if len(self._held) >= lim.total or self._bytes + size > lim.total_bytes:
            return [*out, "early_over_total_bound"]
        if app not in self._apps and len(self._apps) >= MAX_APPS:
            return [*out, "early_too_many_apps"]
        self._held.append(_Held(now, src, app, msg, size))
        self._apps[app] = self._apps.get(app, 0) + 1
        self._peers[src] = (count + 1, held + size)
        self._bytes += size
        return out

    def pop(self, app: str) -> list[tuple[str, m.Message]]:
        """Every message held for ``app``, oldest first (its announcement arrived)."""
        if app not in self._apps:
            return []
        taken = self._remove(lambda h: h.app == app)
        return [(h.src, h.msg) for h in taken]

    def drop_app(self, app: str) -> int:
        return len(self._remove(lambda h: h.app == app)) if app in self._apps else 0

    def drop_peer(self, src: str) -> int:
        """Forget what ``src`` had held (it was declared failed); returns how many."""
        return len(self._remove(lambda h: h.src == src)) if src in self._peers else 0

    def expire(self, now: float) -> list[str]:
        """Drop what has waited past the deadline (oldest first)."""
        out = []
        while self._held and now - self._held[0].at > self.limits.hold_s:
            self._forget(self._held.popleft())
            out.append("early_expired")
        return out

    def clear(self) -> None:
        self._held.clear()
        self._apps.clear()
        self._peers.clear()
        self._bytes = 0

    def _remove(self, which: Callable[[_Held], bool]) -> list[_Held]:
        taken = [h for h in self._held if which(h)]
        if taken:
            self._held = deque(h for h in self._held if not which(h))
            for h in taken:
                self._forget(h)
        return taken

    def _forget(self, h: _Held) -> None:
        self._bytes -= h.size
        n = self._apps[h.app] - 1
        if n:
            self._apps[h.app] = n
        else:
            del self._apps[h.app]
        count, held = self._peers[h.src]
        if count > 1:
            self._peers[h.src] = (count - 1, held - h.size)
        else:
            del self._peers[h.src]
