"""Management rules (paper §3.5): when to relocate a vertex or remap a chain. Pure, deterministic.

Each rule looks at a :class:`~mso.management.views.Snapshot` and proposes actions; the
:class:`~mso.management.guard.Guard` decides which go through and the
:class:`~mso.management.engine.RuleEngine` runs both once per evaluation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mso.management.guard import Proposal, RuleSettings
from mso.management.policy import (
    Policy,
    Score,
    estimate,
    move_cost_split_j,
    neighbour_nodes,
    with_extra_drain,
)
from mso.management.views import (
    ChainView,
    NodeView,
    Relocate,
    RemapChain,
    RemapChains,
    Snapshot,
    VertexView,
)


def joules(j: float) -> str:
    """An energy as a person reads it: 67 µJ, 4.2 mJ, 1.3 J."""
    if j < 1e-3:
        return f"{j * 1e6:.2g} µJ"
    return f"{j * 1e3:.2g} mJ" if j < 1 else f"{j:.2g} J"


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
            shown = (
                "inf"
                if math.isinf(gain)
                else f"{gain * 100:.2g}%"
                if gain < 0.01
                else f"{gain:.0%}"
            )
            reason = (
                f"{self.policy.name} policy, {best.direction} to {best.target}: "
                f"{self.policy.explain(stay.score, best.score)} ({shown} better; the move "
                f"costs {joules(best.move_cost_j)}" + (f"; {v.node} draining)" if draining else ")")
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
    """``node``'s expected lifetime over the longest of the other *battery* nodes in view; None
    when it has no battery, its lifetime is not known yet, or no other battery node's is.

    A wall-powered peer is left out: measured against it (an infinite lifetime) every battery
    neighbour would be "draining" for ever and shed work for any gain at all (issue 25: 9.8 h
    of battery moved a tracker for 3 %). It stays a place to put work -- relocation and the
    policy's score see it like any node -- but a move onto it must beat the margin."""
    view = snap.nodes.get(node)
    if view is None or view.remaining_j is None or view.lifetime_s is None:
        return None
    others = [
        o.lifetime_s
        for n, o in snap.nodes.items()
        if n != node and o.remaining_j is not None and o.lifetime_s is not None
    ]
    longest = max(others, default=None)
    if longest is None or longest <= 0:
        return None
    return view.lifetime_s / longest


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
    within ``vertex_interval_s`` of the hold's end), nor, unless ``energy_outsiders``, a node
    that has no part in the app (neither hosts a vertex of it nor is this node's next hop
    toward one: the figures the rules weigh are each node's own word, and a captured node's
    would pull the join of an app it neither hosts nor relays onto itself); and
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
        part = snap.app_nodes.get(v.app)
        if part is not None and not self.settings.energy_outsiders:
            for n in weights:  # a node with no part in the app: its word steers none of it
                if n not in part:
                    weights[n] = 0.0
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
            reason = f"its route changed {stable:.1f} s ago and has held since"
            out.append(Proposal(RemapChain(c.app, c.index, reason), 1, 0.0, self.name))
        return out

    def done(self, chain: ChainView) -> None:
        """The chain is being remapped: its routes as of now need nothing more."""
        if chain.route_changed_at is not None:
            seen = self._handled.get(chain.key, -math.inf)
            self._handled[chain.key] = max(seen, chain.route_changed_at)

    def forget(self, app: str) -> None:
        self._handled = {k: t for k, t in self._handled.items() if k[0] != app}


def _nan(score: Score) -> bool:
    return any(math.isnan(x) for x in (score if isinstance(score, tuple) else (score,)))
