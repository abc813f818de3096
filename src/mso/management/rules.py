"""Management rules (paper §3.5): when to relocate a vertex or remap a chain. Pure, deterministic.

Each evaluation the node hands :meth:`RuleEngine.evaluate` a :class:`Snapshot`; the rules propose
actions and the :class:`Guard` lets through only those that have been proposed long enough and
respect the rate limits, so a noisy monitor or a flapping link does not make vertices oscillate.
The guard records an action when it allows it (there is no separate "done" call): an action the
node then fails to carry out still counts against the rate limits, which is the safe side.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mso.errors import MsoError
from mso.management.policy import (
    LifetimePolicy,
    Policy,
    Score,
    estimate,
    move_cost_split_j,
    neighbour_nodes,
    with_extra_drain,
)
from mso.management.views import (
    Action,
    ActionKey,
    ChainView,
    NodeView,
    Relocate,
    RemapChain,
    RemapChains,
    Snapshot,
    VertexView,
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
    # after a vertex instance starts here, its start-up work (imports, open(), first calls) is
    # in this node's drain for this long: no draining judgement, no relocation or energy
    # remap off this node until then
    warmup_s: float = 10.0

    @property
    def critical_exit(self) -> float:
        """A draining node stays so until its lifetime ratio is back above this (hysteresis)."""
        return min(1.0, 1.25 * self.critical_ratio)

    def __post_init__(self) -> None:
        for name in ("energy_remap", "spare_pinned"):
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


def improvement(base: Score, new: Score) -> float:
    """How much better ``new`` is than ``base``, relative to ``|base|`` (0 if not better). For
    tuple scores, at the first level where they differ (a worse level there means 0)."""
    if isinstance(base, tuple) or isinstance(new, tuple):
        a = base if isinstance(base, tuple) else (base,)
        b = new if isinstance(new, tuple) else (new,)
        for x, y in zip(a, b, strict=False):
            if math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12):
                continue
            return improvement(x, y)
        return 0.0
    if math.isnan(base) or math.isnan(new) or new >= base:
        return 0.0
    if math.isinf(base) or math.isinf(new) or base == 0:
        return math.inf
    return (base - new) / abs(base)


# -- the oscillation guard -----------------------------------------------------------------


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


# -- rules ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Option:
    """One alternative for a vertex: stay (target None) or move, with its penalised score."""

    target: str | None
    direction: str  # "stay", "upstream" or "downstream"
    score: Score
    move_cost_j: float


class _PolicyRule:
    """A rule that weighs options by an app's policy, knowing whether this node is draining."""

    def __init__(
        self, policy: Policy, settings: RuleSettings, draining: frozenset[str] = frozenset()
    ) -> None:
        self.policy = policy
        self.settings = settings
        self.draining = draining


class RelocationRule(_PolicyRule):
    """Intra-chain remapping (§3.4.1): move a vertex upstream or downstream when it pays.

    For each movable vertex, "no change" is scored against moving it onto its ``upstream`` and
    ``downstream`` nodes (those with a view). The policy sees only the nodes the decision
    involves: the vertex's node, the candidates and its predecessor's and successor's nodes. A
    move's one-time state transfer (``move_cost_j``) is charged as extra drain spread over
    ``horizon_s`` — its tx share on the source, its rx share on the target — before the move is
    scored, so a move must pay for itself within the horizon under any policy that looks at
    drain or lifetime. The best move is proposed only if it beats "no change" by ``margin`` —
    or by anything at all when the vertex's node is in ``draining`` (its battery is expected to
    die far sooner than its neighbours', :func:`draining_update`) and the target would still
    outlive it: every joule the draining node keeps then counts, however small a share of its
    drain. A node whose battery is empty is never a target.
    Vertices of a chain whose routes changed less than ``route_settle_s`` ago wait.
    """

    name = "relocation"

    def options(self, snap: Snapshot, v: VertexView) -> list[Option]:
        """ "stay" first, then each candidate move; empty when the vertex has nowhere to go."""
        if v.node not in snap.nodes:
            return []
        targets: list[tuple[str, str]] = []
        for direction, node in (("upstream", v.upstream), ("downstream", v.downstream)):
            usable = node is not None and node != v.node and node in snap.nodes
            if node is not None and usable and _empty(snap.nodes[node]):
                continue  # a flat battery: whatever the scores say (all lifetimes there are 0)
            if node is not None and usable and all(node != t for _, t in targets):
                if estimate(snap, {v.key: node})[node].load > self.settings.max_load:
                    continue  # it would saturate the target's CPU: never worth it
                targets.append((direction, node))
        if not targets:
            return []
        pred, succ = neighbour_nodes(snap, v)
        involved = {v.node, *(t for _, t in targets), *(n for n in (pred, succ) if n is not None)}
        local = snap.with_nodes(involved)
        opts = [Option(None, "stay", self.policy.score(local, {}), 0.0)]
        horizon = self.settings.horizon_s
        for direction, target in targets:
            tx_j, rx_j = move_cost_split_j(local, v, target)
            charged = with_extra_drain(local, {v.node: tx_j / horizon, target: rx_j / horizon})
            score = self.policy.score(charged, {v.key: target})
            opts.append(Option(target, direction, score, tx_j + rx_j))
        return opts

    def propose(self, snap: Snapshot) -> list[Proposal]:
        out: list[Proposal] = []
        for v in sorted(snap.vertices, key=lambda v: v.key):
            if not v.movable or self._settling(snap, v):
                continue
            opts = self.options(snap, v)
            if len(opts) < 2:
                continue
            stay = opts[0]
            best = min(opts[1:], key=lambda o: (_nan(o.score), o.score, o.direction))
            gain = improvement(stay.score, best.score)
            draining = v.node in self.draining and _relieves(snap, v, best.target)
            margin = 0.0 if draining else self.settings.margin
            if best.target is None or gain <= margin:
                continue
            shown = "inf" if math.isinf(gain) else f"{gain:.2g}" if gain < 0.01 else f"{gain:.0%}"
            reason = (
                f"{self.policy.name}, {best.direction}: score {_show(stay.score)} -> "
                f"{_show(best.score)} ({shown} better, move {best.move_cost_j:.3g} J"
                + (f"; {v.node} draining)" if draining else ")")
            )
            action = Relocate(v.app, v.id, best.target, reason)
            out.append(Proposal(action, self.settings.confirm, gain, self.name))
        return out

    def _settling(self, snap: Snapshot, v: VertexView) -> bool:
        chain = snap.chain(v.app, v.chain)
        changed = None if chain is None else chain.route_changed_at
        return changed is not None and snap.now - changed < self.settings.route_settle_s


def _empty(view: NodeView) -> bool:
    return view.remaining_j is not None and view.remaining_j <= 0


def _relieves(snap: Snapshot, v: VertexView, target: str | None) -> bool:
    """Moving ``v`` to ``target`` leaves the target outliving ``v``'s node: the draining node
    is relieved, not swapped for a new bottleneck (which only the margin may allow)."""
    if target is None:
        return False
    est = estimate(snap, {v.key: target})
    src, dst = est[v.node].lifetime_s, est[target].lifetime_s
    return src is not None and (dst is None or dst >= src)


def lifetime_ratio(snap: Snapshot, node: str) -> float | None:
    """``node``'s expected lifetime over the longest of the other nodes in view (a wall-powered
    one counts as infinite, so the ratio is 0); None when it has no battery, its lifetime is
    not known yet, or no other node's is."""
    view = snap.nodes.get(node)
    if view is None or view.remaining_j is None or view.lifetime_s is None:
        return None
    others = [
        math.inf if o.remaining_j is None else o.lifetime_s
        for n, o in snap.nodes.items()
        if n != node and (o.remaining_j is None or o.lifetime_s is not None)
    ]
    longest = max((x for x in others if x is not None), default=None)
    if longest is None or longest <= 0:
        return None
    return 0.0 if math.isinf(longest) else view.lifetime_s / longest


def warming_until(snap: Snapshot, settings: RuleSettings) -> float | None:
    """When this node's figures are its own again, while they are not: ``warmup_s`` after a
    vertex instance last started here (``Snapshot.last_start``). Until then its drain, load and
    lifetime include the start-up (imports, ``open()``, first calls), a burst the node will
    not repeat; judged by them, a node with a long-lived battery can look as if it will die
    soon. None when the node is warm (or no start is known)."""
    if snap.last_start is None:
        return None
    until = snap.last_start + settings.warmup_s
    return until if snap.now < until else None


def draining_update(
    draining: frozenset[str], snap: Snapshot, settings: RuleSettings
) -> frozenset[str]:
    """The nodes deemed draining after ``snap``: this node joins when its lifetime falls under
    ``critical_ratio`` of its longest-lived neighbour's and leaves only once it is back above
    ``critical_exit`` (hysteresis: a ratio hovering at the threshold does not flip the rule
    on and off every evaluation). While this node warms up (:func:`warming_until`) its state
    stays as it was: a start-up burst neither makes it draining nor clears a judgement made
    on steady figures."""
    if warming_until(snap, settings) is not None:
        return draining
    ratio = lifetime_ratio(snap, snap.here)
    if ratio is None:
        return draining
    if ratio < settings.critical_ratio:
        return draining | {snap.here}
    if ratio > settings.critical_exit:
        return draining - {snap.here}
    return draining


class EnergyRemapRule(_PolicyRule):
    """Energy remap: a draining node sheds a chain end that relocation cannot move.

    A join or fork vertex (the tail of several chains, or the tail of one and the head of
    others) is never relocated (§3.4.1), and a route or SLO remap keeps a lone chain's ends; on
    a node in ``draining`` such a vertex can hold most of its drain. For the hosted unpinned one
    with the largest CPU drain, the node looks for the node in view where that vertex alone
    would beat "no change" by ``margin`` under the policy, the most (the move's state transfer
    charged as in :class:`RelocationRule`), among the nodes the policy's
    :meth:`~mso.management.Policy.capacity_weight` gives a weight above 0 — never this node, a
    flat battery, a node expected to die no later than this one, nor, within ``ping_pong_s``
    of its last move, the node the vertex came from (unless this node would die first, or
    within ``vertex_interval_s`` of the hold's end); and
    with ``spare_pinned``, a node that runs pinned vertices only when every other node in view
    does too (the paper's robot that "cannot offload any of its local sensing": its battery
    is kept for what only it can do, and the app ends when it dies, while movable work finds
    another host). It then asks for a
    remap of every chain that ends or starts at the vertex with the vertex placed there, and
    the planner re-placing the rest of those chains seeing each node's probed capacity times
    its weight.

    It does not ask for a vertex that arrived less than ``vertex_interval_s`` ago (the drains
    in view do not show it yet), nor while another host of those chains in view is
    shorter-lived (that node asks first). The guard allows one per app per
    ``energy_interval_s`` from this node, and none while a relocation or remap of the app runs
    here.
    """

    name = "energy"

    def propose(self, snap: Snapshot) -> list[Proposal]:
        here = snap.nodes.get(snap.here)
        if not self.settings.energy_remap or snap.here not in self.draining:
            return []
        if here is None or here.lifetime_s is None:
            return []
        ends = [v for v in snap.vertices if not v.pinned and len(self.chains_at(snap, v)) > 1]
        if not ends:
            return []
        # the chain end that costs this node the most CPU first; one proposal per app
        v = max(ends, key=lambda v: (v.cost * v.rate, v.key))
        moved = None if v.moved_at is None else snap.now - v.moved_at
        if moved is not None and moved < self.settings.vertex_interval_s:
            return []  # it just arrived: the drains in view do not show it yet
        chains = self.chains_at(snap, v)
        for c in chains:
            for n in c.nodes:
                other = snap.nodes.get(n)
                if (
                    n != snap.here
                    and other is not None
                    and other.battery
                    and (other.lifetime_s is not None and other.lifetime_s < here.lifetime_s)
                ):
                    return []  # a shorter-lived host of these chains: it asks first
        weights = self.weights(snap)
        if (
            moved is not None
            and moved < self.settings.ping_pong_s
            and v.moved_from in weights
            and here.lifetime_s
            > self.settings.ping_pong_s - moved + self.settings.vertex_interval_s
        ):
            # no ping-pong: not back to the node it left — unless this node is expected to die
            # before that hold lifts, or too soon after it to act then (one vertex interval):
            # in the energy study a robot that had just taken the join died with it 1 s before
            # the hold lifted; another, always expecting to live 4 s past the hold's end, died
            # 4 s after it, still holding the join
            weights[v.moved_from] = 0.0
        best = self.best_gain(snap, v, weights)
        if best is None:
            return []
        target, gain = best
        shown = "inf" if math.isinf(gain) else f"{gain:.0%}"
        reason = (
            f"{self.policy.name}: {snap.here} draining, sheds join/fork {v.id} "
            f"({shown} better on {target})"
        )
        indices = tuple(c.index for c in chains)
        action = RemapChains(
            v.app, indices, tuple(sorted(weights.items())), reason, ((v.id, target),)
        )
        return [Proposal(action, self.settings.confirm, gain, self.name)]

    @staticmethod
    def chains_at(snap: Snapshot, v: VertexView) -> list[ChainView]:
        """The chains ending or starting at ``v`` (longer than one vertex), by index."""
        return sorted(
            (
                c
                for c in snap.chains
                if c.app == v.app
                and len(c.vertices) > 1
                and v.id in (c.vertices[0], c.vertices[-1])
            ),
            key=lambda c: c.index,
        )

    def weights(self, snap: Snapshot) -> dict[str, float]:
        """The planner's capacity factor of each node in view (nodes not listed weigh 1)."""
        here = snap.nodes[snap.here]
        assert here.lifetime_s is not None
        out: dict[str, float] = {}
        for n, view in sorted(snap.nodes.items()):
            w = float(self.policy.capacity_weight(snap, n))
            shorter = view.battery and (
                _empty(view) or (view.lifetime_s is not None and view.lifetime_s <= here.lifetime_s)
            )
            out[n] = (
                0.0 if n == snap.here or shorter or not math.isfinite(w) else min(1.0, max(0.0, w))
            )
        return out

    def best_gain(
        self, snap: Snapshot, v: VertexView, weights: dict[str, float]
    ) -> tuple[str, float] | None:
        """The node in view (weight > 0) where ``v`` alone scores best under the policy, with
        its gain over "no change", if that beats ``margin``. All candidates are scored on the
        same nodes (this one and the candidates), so the policy compares like with like; the
        move's state transfer is charged over ``horizon_s``."""
        horizon = self.settings.horizon_s
        candidates = [
            n
            for n in sorted(n for n, w in weights.items() if w > 0)
            if estimate(snap, {v.key: n})[n].load <= self.settings.max_load
        ]
        if self.settings.spare_pinned and any(  # the robot that cannot offload its sensing
            n != snap.here and n not in snap.pinned_hosts for n in snap.nodes
        ):
            candidates = [n for n in candidates if n not in snap.pinned_hosts]
        if not candidates:
            return None
        local = snap.with_nodes({snap.here, *candidates})
        stay = self.policy.score(local, {})
        scored = []
        for n in candidates:
            tx_j, rx_j = move_cost_split_j(local, v, n)
            charged = with_extra_drain(local, {snap.here: tx_j / horizon, n: rx_j / horizon})
            scored.append((self.policy.score(charged, {v.key: n}), n))
        score, best = min(scored, key=lambda sn: (_nan(sn[0]), sn[0], sn[1]))
        gain = improvement(stay, score)
        return (best, gain) if gain > self.settings.margin else None


class ChainRouteRule:
    """Chain remapping (§3.4.2) after a route between a chain's nodes changed.

    Only the chain's coordinator proposes it, only once routes have been stable for
    ``route_settle_s`` (a link flapping faster never triggers it), only for a change newer than
    the chain's mapping (``placed_at``), and once per change: :meth:`done` marks it handled.
    """

    name = "route"

    def __init__(self, settings: RuleSettings) -> None:
        self.settings = settings
        self._handled: dict[tuple[str, int], float] = {}

    def propose(self, snap: Snapshot) -> list[Proposal]:
        out: list[Proposal] = []
        for c in sorted(snap.chains, key=lambda c: c.key):
            changed = c.route_changed_at
            if not c.coordinator or changed is None:
                continue
            if c.placed_at is not None and changed <= c.placed_at:
                continue
            if self._handled.get(c.key, -math.inf) >= changed:
                continue
            stable = snap.now - changed
            if stable < self.settings.route_settle_s:
                continue
            reason = f"route changed at {changed:.1f}, stable for {stable:.1f}s"
            out.append(Proposal(RemapChain(c.app, c.index, reason), 1, 0.0, self.name))
        return out

    def done(self, chain: ChainView) -> None:
        """The chain is being remapped: its routes as of now need nothing more."""
        if chain.route_changed_at is not None:
            seen = self._handled.get(chain.key, -math.inf)
            self._handled[chain.key] = max(seen, chain.route_changed_at)

    def forget(self, app: str) -> None:
        self._handled = {k: t for k, t in self._handled.items() if k[0] != app}


# -- the engine ----------------------------------------------------------------------------

LogEntry = tuple[float, str, str]


class RuleEngine:
    """Runs the rules on a snapshot and returns the actions the guard allows.

    Every app is managed by its own policy if one was set (:meth:`set_app_policy`, from the
    app's ``policy:``), else by the node's. Per app, each evaluation collects the policy's own
    ``actions()`` (relocations need ``confirm``, remaps ``slo_confirm`` evaluations in a row)
    and the relocation rule's proposal; the route rule adds chain remaps. At most one
    relocation is returned per evaluation. While this node warms up (:func:`warming_until`)
    the relocation and energy-remap rules propose nothing and the draining state stands: the
    figures they would weigh are the start-up's, not the node's. A policy that raises is
    reported in the log and its app skipped for that evaluation. ``log`` keeps recent decisions
    as ``(now, action, "allowed" | "held: why" | "ignored: why" | "error: what")``, each
    written when it changes.
    """

    def __init__(
        self,
        policy: Policy | None = None,
        settings: RuleSettings | None = None,
        *,
        log_size: int = 200,
    ) -> None:
        self.policy = policy if policy is not None else LifetimePolicy()
        self.settings = settings if settings is not None else RuleSettings()
        self.app_policies: dict[str, Policy] = {}
        self.guard = Guard(self.settings)
        self.route_rule = ChainRouteRule(self.settings)
        self.log: deque[LogEntry] = deque(maxlen=log_size)
        self.evaluations = 0
        self.draining: frozenset[str] = frozenset()  # this node, while its battery is draining
        self.warming: float | None = None  # until when this node warms up (warming_until)
        self._last: dict[tuple[Any, ...], str] = {}

    def set_app_policy(self, app: str, policy: Policy | None) -> None:
        """Manage ``app`` by ``policy`` (None: by the node's policy again)."""
        if policy is None:
            self.app_policies.pop(app, None)
        else:
            self.app_policies[app] = policy

    def policy_for(self, app: str) -> Policy:
        return self.app_policies.get(app, self.policy)

    def forget(self, app: str) -> None:
        """Drop what the engine keeps about an app that stopped."""
        self.app_policies.pop(app, None)
        self.route_rule.forget(app)

    def evaluate(self, snap: Snapshot) -> list[Action]:
        self.evaluations += 1
        seen: dict[tuple[Any, ...], str] = {}
        proposals = self.route_rule.propose(snap)
        was = self.draining
        self.draining = draining_update(was, snap, self.settings)
        if self.draining != was:
            ratio = lifetime_ratio(snap, snap.here)
            shown = "-" if ratio is None else f"{ratio:.2f}"
            what = "draining" if snap.here in self.draining else "no longer draining"
            self.log.append((snap.now, f"{snap.here} {what}", f"lifetime ratio {shown}"))
        warm = self.warming is None
        self.warming = warming_until(snap, self.settings)
        if warm and self.warming is not None:
            self.log.append(
                (
                    snap.now,
                    f"{snap.here} warming up",
                    f"a vertex started at {snap.last_start:.1f}: its drain is judged "
                    f"from {self.warming:.1f}",
                )
            )
        for app in snap.apps():
            policy = self.policy_for(app)
            view = snap.for_app(app)
            try:
                asked = list(policy.actions(view))
                relocations: list[Proposal] = []
                energy: list[Proposal] = []
                if self.warming is None:  # start-up in the figures: no move for energy or load
                    relocations = RelocationRule(policy, self.settings, self.draining).propose(view)
                    energy = EnergyRemapRule(policy, self.settings, self.draining).propose(view)
            except Exception as exc:  # user code: report it, keep the node running
                what = f"policy {policy.name} for {app}"
                self._note(
                    seen, ("error", app), snap.now, what, f"error: {type(exc).__name__}: {exc}"
                )
                continue
            for act in asked:
                proposal, problem = self._check(act, view, policy)
                if proposal is None:
                    decision = f"ignored: {problem}"
                    self._note(seen, ("ignored", repr(act)), snap.now, str(act), decision)
                else:
                    proposals.append(proposal)
            proposals.extend(relocations)
            proposals.extend(energy)
        allowed: list[Action] = []
        for p, why in self.guard.review(proposals, snap):
            a = p.action
            if why is None:
                allowed.append(a)
                indices: tuple[int, ...] = (a.chain,) if isinstance(a, RemapChain) else ()
                indices = a.chains if isinstance(a, RemapChains) else indices
                for index in indices:
                    chain = snap.chain(a.app, index)
                    if chain is not None:
                        self.route_rule.done(chain)
            self._note(seen, a.key, snap.now, str(a), "allowed" if why is None else f"held: {why}")
        self._last = seen
        return allowed

    def _check(self, act: object, snap: Snapshot, policy: Policy) -> tuple[Proposal | None, str]:
        """A policy's own action as a proposal, or why it cannot be one."""
        rule = f"policy {policy.name}"
        if isinstance(act, Relocate):
            v = snap.vertex(act.vertex_key)
            if v is None:
                return None, f"{act.vertex_key} is not hosted on {snap.here}"
            if not v.movable:
                return None, f"{v.key} is a chain end or pinned: never relocated"
            if act.target == v.node:
                return None, f"{v.key} already runs on {v.node}"
            if act.target not in snap.nodes:
                return None, f"no view of node {act.target}"
            return Proposal(act, self.settings.confirm, 0.0, rule), ""
        if isinstance(act, RemapChain):
            chain = snap.chain(act.app, act.chain)
            if chain is None or not chain.coordinator:
                return None, f"{snap.here} does not coordinate {act.app} chain {act.chain}"
            return Proposal(act, self.settings.slo_confirm, 0.0, rule), ""
        return None, f"not an action: {act!r}"

    def _note(
        self,
        seen: dict[tuple[Any, ...], str],
        key: tuple[Any, ...],
        now: float,
        what: str,
        decision: str,
    ) -> None:
        seen[key] = decision
        if self._last.get(key) != decision:
            self.log.append((now, what, decision))

    def status(self) -> dict[str, Any]:
        """Policies, settings and recent decisions, for ``mso status``."""
        s = self.settings
        return {
            "policy": self.policy.name,
            "app_policies": {a: p.name for a, p in sorted(self.app_policies.items())},
            "settings": {name: getattr(s, name) for name in s.__dataclass_fields__},
            "evaluations": self.evaluations,
            "draining": sorted(self.draining),
            "warming_until": self.warming,
            "decisions": [f"{t:.1f} {what}: {d}" for t, what, d in self.log],
        }


def _nan(score: Score) -> bool:
    return any(math.isnan(x) for x in (score if isinstance(score, tuple) else (score,)))


def _show(score: Score) -> str:
    """A score for the log: a tuple's first two levels are enough to see why."""
    if isinstance(score, tuple):
        return "(" + ", ".join(f"{x:.4g}" for x in score[:2]) + (", …)" if len(score) > 2 else ")")
    return f"{score:.4g}"
