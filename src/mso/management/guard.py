"""The oscillation guard of the management rules (paper §3.5): their settings, and what lets a
proposal through.

The rules propose actions each evaluation; the :class:`Guard` lets through only those that have
been proposed long enough and respect the rate limits, so a noisy monitor or a flapping link
does not make vertices oscillate. The guard records an action when it allows it (there is no
separate "done" call): an action the node then fails to carry out still counts against the rate
limits, which is the safe side. Kept apart from the rules so the hold logic reads on its own.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mso.errors import MsoError
from mso.management.views import (
    Action,
    ActionKey,
    Relocate,
    RemapChain,
    RemapChains,
    Snapshot,
)


@dataclass(frozen=True, slots=True)
class RuleSettings:
    """Hysteresis and rate limits of the rules; docs/policies.md explains each default."""

    period_s: float = 1.0  # how often the node runs the rules
    confirm: int = 3  # evaluations in a row a relocation must be the best choice
    margin: float = 0.1  # relative improvement over "no change" a move must beat
    horizon_s: float = 60.0  # a move's one-time energy is spread over this long
    vertex_interval_s: float = 30.0  # a vertex moves at most once per interval
    node_interval_s: float = 5.0  # this node starts at most one relocation per interval
    route_settle_s: float = 3.0  # routes must be stable this long before a chain remap
    chain_interval_s: float = 15.0  # a chain is remapped at most once per interval
    slo_confirm: int = 3  # evaluations in a row a policy must ask for a remap
    max_load: float = 1.0  # a move never loads its target's CPU beyond this (1.0 = saturated)
    critical_ratio: float = 0.5  # a battery node expected to die this much sooner is draining
    energy_interval_s: float = 120.0  # an app is remapped for energy at most once per interval
    energy_remap: bool = True  # False: a draining node only relocates (no energy remaps)
    # an energy remap places the join on a node that runs pinned vertices only when no other
    # candidate is left (False: any candidate the policy weighs above 0)
    spare_pinned: bool = True
    # an energy remap may place the join on any node in view, also one that neither hosts nor
    # relays the app (False: only on the app's own nodes: its hosts and this node's next hops
    # toward them — a node's figures are its own word, and a captured node's false ones would
    # otherwise pull an app it has no part in onto itself)
    energy_outsiders: bool = False
    # after a vertex instance starts here, its start-up work (imports, open(), first calls) is
    # in this node's drain for this long: no draining judgement, no relocation or energy
    # remap off this node until then
    warmup_s: float = 10.0

    @property
    def critical_exit(self) -> float:
        """A draining node stays so until its lifetime ratio is back above this (hysteresis)."""
        return min(1.0, 1.25 * self.critical_ratio)

    def __post_init__(self) -> None:
        for name in ("energy_remap", "spare_pinned", "energy_outsiders"):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise MsoError(f"rule settings: {name}: expected true or false, got {value!r}")
        for name in ("confirm", "slo_confirm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise MsoError(f"rule settings: {name}: expected an integer >= 1, got {value!r}")
        for name in ("period_s", "horizon_s", "max_load"):
            value = getattr(self, name)
            if not _number(value) or value <= 0:
                raise MsoError(f"rule settings: {name}: expected a positive number, got {value!r}")
        for name in (
            "margin",
            "critical_ratio",
            "vertex_interval_s",
            "node_interval_s",
            "route_settle_s",
            "chain_interval_s",
            "energy_interval_s",
            "warmup_s",
        ):
            value = getattr(self, name)
            if not _number(value) or value < 0:
                raise MsoError(f"rule settings: {name}: expected a number >= 0, got {value!r}")
        if self.critical_ratio >= 1:
            raise MsoError(
                f"rule settings: critical_ratio: expected a number below 1, "
                f"got {self.critical_ratio!r}"
            )

    @property
    def ping_pong_s(self) -> float:
        """A vertex does not go back to the node it left for this long."""
        return 4 * self.vertex_interval_s


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True, slots=True)
class Proposal:
    """An action a rule wants, how many evaluations in a row it must be wanted, and its value.

    ``priority`` orders proposals of one kind (larger first): for relocations, the relative
    improvement, so the most useful one gets the evaluation's single relocation.
    """

    action: Action
    confirm: int = 1
    priority: float = 0.0
    rule: str = ""


class Guard:
    """Lets a proposal through only when it is confirmed and within every rate limit.

    - confirmation: an action must be proposed in ``confirm`` consecutive reviews (a review
      without it starts the count again);
    - a vertex moves at most once per ``vertex_interval_s`` (its own record and the snapshot's
      ``moved_at``, so moves made by other nodes count);
    - no ping-pong: a vertex is not sent back to the node it left within ``ping_pong_s``;
    - this node starts at most one relocation per ``node_interval_s`` and per review;
    - a chain is remapped at most once per ``chain_interval_s``, and its vertices are not
      relocated in the review that remaps it.

    Call :meth:`review` once per evaluation; ``allowed`` keeps the recent allowed actions.
    """

    def __init__(self, settings: RuleSettings, *, history: int = 100) -> None:
        self.settings = settings
        self.allowed: deque[tuple[float, Action]] = deque(maxlen=history)
        self._streak: dict[ActionKey, int] = {}
        self._moves: dict[str, tuple[float, str]] = {}  # vertex key -> (when, node it left)
        self._last_relocation: float | None = None
        self._remaps: dict[tuple[str, int], float] = {}
        self._energy: dict[str, float] = {}  # app -> when this node last remapped it for energy

    def streak(self, action: Action) -> int:
        """Consecutive reviews that have proposed ``action`` (0 right after it was allowed)."""
        return self._streak.get(action.key, 0)

    def review(
        self, proposals: Sequence[Proposal], snap: Snapshot
    ) -> list[tuple[Proposal, str | None]]:
        """Each distinct proposal with None (allowed) or why it is held; remaps first."""
        now = snap.now
        unique: dict[ActionKey, Proposal] = {}
        for p in proposals:
            unique.setdefault(p.action.key, p)
        self._streak = {k: self._streak.get(k, 0) + 1 for k in unique}
        self._forget(now)
        ordered = sorted(
            unique.values(),
            key=lambda p: (isinstance(p.action, Relocate), -p.priority, repr(p.action.key)),
        )
        remapped: set[tuple[str, int]] = set()
        relocated = False
        out: list[tuple[Proposal, str | None]] = []
        for p in ordered:
            a = p.action
            n = self._streak[a.key]
            why: str | None
            if n < p.confirm:
                why = f"confirming {n}/{p.confirm}"
            elif isinstance(a, RemapChain):
                why = self._remap_hold(a, now)
            elif isinstance(a, RemapChains):
                why = self._energy_hold(a, snap, remapped)
            else:
                why = self._relocation_hold(a, snap, remapped, relocated)
            if why is None:
                self._streak[a.key] = 0
                self.allowed.append((now, a))
                if isinstance(a, RemapChain):
                    remapped.add((a.app, a.chain))
                    self._remaps[a.app, a.chain] = now
                elif isinstance(a, RemapChains):
                    for c in a.chains:
                        remapped.add((a.app, c))
                        self._remaps[a.app, c] = now
                    self._energy[a.app] = now
                else:
                    relocated = True
                    v = snap.vertex(a.vertex_key)
                    self._moves[a.vertex_key] = (now, snap.here if v is None else v.node)
                    self._last_relocation = now
            out.append((p, why))
        return out

    def _remap_hold(self, a: RemapChain, now: float) -> str | None:
        last = self._remaps.get((a.app, a.chain))
        if last is not None and now - last < self.settings.chain_interval_s:
            limit = self.settings.chain_interval_s
            return f"chain remapped at {last:.1f} (at most once per {limit:g}s)"
        return None

    def _energy_hold(
        self, a: RemapChains, snap: Snapshot, remapped: set[tuple[str, int]]
    ) -> str | None:
        """Storms and ping-pong: one energy remap per app per ``energy_interval_s`` from this
        node, none while another reconfiguration of the app runs here, and the chain limit."""
        now, limit = snap.now, self.settings.energy_interval_s
        last = self._energy.get(a.app)
        if last is not None and now - last < limit:
            return f"{a.app} remapped for energy at {last:.1f} (at most once per {limit:g}s)"
        if a.app in snap.busy:
            return f"a relocation or remap of {a.app} is in flight here"
        for c in a.chains:
            if (a.app, c) in remapped:
                return f"chain {c} is being remapped"
            why = self._remap_hold(RemapChain(a.app, c), now)
            if why is not None:
                return why
        return None

    def _relocation_hold(
        self, a: Relocate, snap: Snapshot, remapped: set[tuple[str, int]], relocated: bool
    ) -> str | None:
        now, s = snap.now, self.settings
        v = snap.vertex(a.vertex_key)
        history = [self._moves[a.vertex_key]] if a.vertex_key in self._moves else []
        if v is not None and v.moved_at is not None:
            history.append((v.moved_at, v.moved_from or ""))
        if v is not None and (v.app, v.chain) in remapped:
            return "its chain is being remapped"
        last = max((t for t, _ in history), default=None)
        if last is not None and now - last < s.vertex_interval_s:
            return f"vertex moved at {last:.1f} (at most once per {s.vertex_interval_s:g}s)"
        for t, left in sorted(history):
            if left == a.target and now - t < s.ping_pong_s:
                return (
                    f"would go back to {left}, which it left at {t:.1f} "
                    f"(not within {s.ping_pong_s:g}s)"
                )
        if relocated:
            return "one relocation per evaluation"
        if self._last_relocation is not None and now - self._last_relocation < s.node_interval_s:
            return (
                f"this node started a relocation at {self._last_relocation:.1f} "
                f"(at most one per {s.node_interval_s:g}s)"
            )
        return None

    def _forget(self, now: float) -> None:
        """Drop records no limit can use any more, so the guard stays small."""
        keep = self.settings.ping_pong_s
        self._moves = {k: m for k, m in self._moves.items() if now - m[0] < keep}
        keep = self.settings.chain_interval_s
        self._remaps = {k: t for k, t in self._remaps.items() if now - t < keep}
        keep = self.settings.energy_interval_s
        self._energy = {k: t for k, t in self._energy.items() if now - t < keep}
