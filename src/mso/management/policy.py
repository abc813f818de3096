"""Pluggable objectives for the management rules (docs/policies.md). Pure: no I/O, no clock.

A policy scores "what if these vertices ran elsewhere" (lower is better) and may ask for actions
on its own. The relocation rule compares a vertex's "no change" score with the scores of moving it
upstream and downstream; :func:`estimate` predicts what such moves do to each node's load, drain
and lifetime, so most policies are a few lines over it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from mso.errors import MsoError, with_code_hint
from mso.management.views import (
    Action,
    NodeView,
    RemapChain,
    Snapshot,
    VertexView,
)
from mso.model.imports import ImportPathError, resolve

LIFETIME_CAP_S = 1e9
"""Lifetimes are compared up to this (≈ 32 years): a battery node that draws nothing yet."""

"""Weight of total drain in the lifetime score: breaks ties between equal minimum lifetimes only."""


class PolicyError(MsoError):
    """A policy spec that cannot be loaded; the message names where it came from."""


# -- the energy and load estimate ----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class NodeEstimate:
    """A node's predicted state if some vertices moved.

    ``lifetime_s`` is None for a wall-powered node and ``math.inf`` for a battery node that would
    draw nothing (not yet measured).
    """

    load: float
    drain_w: float
    lifetime_s: float | None


def _lifetime(remaining_j: float | None, drain_w: float) -> float | None:
    if remaining_j is None:
        return None
    return remaining_j / drain_w if drain_w > 0 else math.inf


def neighbour_nodes(
    snap: Snapshot, vertex: VertexView, moves: Mapping[str, str] | None = None
) -> tuple[str | None, str | None]:
    """The nodes of ``vertex``'s predecessor and successor in its chain, after ``moves``.

    Taken from the vertex's :class:`ChainView` (which knows when the successor shares the
    vertex's node); without one, ``vertex.upstream``/``vertex.downstream`` stand in.
    """
    pred, succ, _, _ = _neighbours(snap, vertex, moves or {})
    return pred, succ


def _neighbours(
    snap: Snapshot, v: VertexView, moves: Mapping[str, str]
) -> tuple[str | None, str | None, tuple[Any, ...], tuple[Any, ...]]:
    """(predecessor's node, successor's node, in-edge id, out-edge id), after ``moves``."""
    pred, succ = v.upstream, v.downstream
    in_id: tuple[Any, ...] = ("in", v.key)
    out_id: tuple[Any, ...] = ("out", v.key)
    chain = snap.chain(v.app, v.chain)
    if chain is not None and v.id in chain.vertices:
        i = chain.vertices.index(v.id)
        if i > 0:
            pred = moves.get(f"{v.app}/{chain.vertices[i - 1]}", chain.nodes[i - 1])
            in_id = (v.app, v.chain, i - 1)
        if i + 1 < len(chain.vertices):
            succ = moves.get(f"{v.app}/{chain.vertices[i + 1]}", chain.nodes[i + 1])
            out_id = (v.app, v.chain, i)
    return pred, succ, in_id, out_id


def estimate(snap: Snapshot, moves: Mapping[str, str]) -> dict[str, NodeEstimate]:
    """Predicted load, drain and lifetime of every node in ``snap.nodes`` after ``moves``.

    ``moves`` maps a hosted vertex's key (``app/id``) to its new node, which must have a view in
    ``snap.nodes`` (ValueError otherwise: nothing is known about it). Moving vertex v (cost c ms,
    rate r events/s) from A to B moves ``c * r / 1000 / cpu`` of load and ``cpu_w`` times that of
    drain (each side with its own cpu and power model). Each byte v receives from its
    predecessor's node costs that node ``tx_uj_per_byte`` and v's node ``rx_uj_per_byte``; the
    same for what v sends its successor; co-located vertices exchange bytes for free. Each node
    in view that relays between the two (:func:`relays`) pays both, receiving and sending on;
    nodes without a view pay nothing.
    """
    load = {n: view.load for n, view in snap.nodes.items()}
    drain = {n: view.drain_w for n, view in snap.nodes.items()}
    moved: list[tuple[VertexView, str]] = []
    for key in sorted(moves):
        target = moves[key]
        v = snap.vertex(key)
        if v is None:
            raise ValueError(f"cannot estimate moving {key!r}: it is not hosted on {snap.here}")
        if target == v.node:
            continue
        if target not in snap.nodes:
            raise ValueError(f"cannot estimate moving {key!r} to {target!r}: no view of that node")
        moved.append((v, target))

    def cpu(node: str, work: float) -> None:
        view = snap.nodes.get(node)
        if view is not None:
            busy = work / view.cpu if view.cpu > 0 else math.inf
            load[node] += busy
            drain[node] += view.power.cpu_w * busy

    def radio(sender: str | None, receiver: str | None, bytes_per_s: float) -> None:
        if sender is None or receiver is None or sender == receiver:
            return
        if sender in snap.nodes:
            drain[sender] += snap.nodes[sender].power.tx_uj_per_byte * bytes_per_s * 1e-6
        if receiver in snap.nodes:
            drain[receiver] += snap.nodes[receiver].power.rx_uj_per_byte * bytes_per_s * 1e-6
        for relay, share in relays(snap, sender, receiver).items():
            pw = snap.nodes[relay].power
            drain[relay] += (pw.rx_uj_per_byte + pw.tx_uj_per_byte) * share * bytes_per_s * 1e-6

    # every edge touching a moved vertex, once, with its ends before and after the moves
    edges: dict[tuple[Any, ...], tuple[str | None, str | None, str | None, str | None, float]] = {}
    for v, target in moved:
        work = v.cost * v.rate / 1000.0
        cpu(v.node, -work)
        cpu(target, work)
        pred0, succ0, in_id, out_id = _neighbours(snap, v, {})
        pred1, succ1, _, _ = _neighbours(snap, v, moves)
        edges.setdefault(in_id, (pred0, v.node, pred1, target, v.in_bytes_per_s))
        edges.setdefault(out_id, (v.node, succ0, target, succ1, v.out_bytes_per_s))
    for _, (s0, r0, s1, r1, rate) in sorted(edges.items(), key=lambda kv: repr(kv[0])):
        radio(s0, r0, -rate)
        radio(s1, r1, rate)

    return {
        n: NodeEstimate(load[n], drain[n], _lifetime(view.remaining_j, drain[n]))
        for n, view in snap.nodes.items()
    }


def relays(snap: Snapshot, sender: str, receiver: str) -> dict[str, float]:
    """The nodes in view that relay traffic from ``sender`` to ``receiver``, each with the
    share of it that crosses it, by the hop counts the nodes report (NodeView.hops).

    A node X lies on a shortest route when its hops to both ends add up to their distance
    (known if either end is in view and reports the other). Where several such nodes are the
    same number of hops from the sender (a mesh with equal routes), each takes an equal share:
    the routing protocol picks one, and which is not known here. Nothing is charged when the
    distance is unknown."""
    a, b = snap.nodes.get(sender), snap.nodes.get(receiver)
    dist = (a.hops.get(receiver) if a is not None else None) or (
        b.hops.get(sender) if b is not None else None
    )
    if dist is None or dist < 2:
        return {}
    levels: dict[int, list[str]] = {}
    for n, view in snap.nodes.items():
        to_a, to_b = view.hops.get(sender), view.hops.get(receiver)
        if n in (sender, receiver) or to_a is None or to_b is None:
            continue
        if to_a + to_b == dist:
            levels.setdefault(to_a, []).append(n)
    return {n: 1.0 / len(ns) for ns in levels.values() for n in ns}


def move_cost_j(snap: Snapshot, vertex: VertexView | str, target: str) -> float:
    """Joules it takes to ship the vertex's state to ``target``: tx at its node, rx at target."""
    tx_j, rx_j = move_cost_split_j(snap, vertex, target)
    return tx_j + rx_j


def move_cost_split_j(snap: Snapshot, vertex: VertexView | str, target: str) -> tuple[float, float]:
    """The move's energy as (joules at the source node, joules at the target node)."""
    v = snap.vertex(vertex) if isinstance(vertex, str) else vertex
    if v is None:
        raise ValueError(f"cannot cost moving {vertex!r}: it is not hosted on {snap.here}")
    if target == v.node:
        return 0.0, 0.0
    if target not in snap.nodes:
        raise ValueError(f"cannot cost moving {v.key!r} to {target!r}: no view of that node")
    src = snap.nodes.get(v.node)
    tx = 0.0 if src is None else src.power.tx_uj_per_byte * v.state_bytes * 1e-6
    return tx, snap.nodes[target].power.rx_uj_per_byte * v.state_bytes * 1e-6


def with_extra_drain(snap: Snapshot, watts: Mapping[str, float]) -> Snapshot:
    """``snap`` with ``watts`` added to some nodes' drain (and their lifetimes recomputed).

    The relocation rule charges a move's one-time energy this way, spread over the horizon, so
    that every policy that looks at drain or lifetime sees the move's cost.
    """
    nodes: dict[str, NodeView] = dict(snap.nodes)
    for n, w in watts.items():
        view = nodes.get(n)
        if view is not None and w:
            drain = view.drain_w + w
            nodes[n] = dataclasses.replace(
                view, drain_w=drain, lifetime_s=_lifetime(view.remaining_j, drain)
            )
    return dataclasses.replace(snap, nodes=nodes)


# -- scores over an estimate ---------------------------------------------------------------


Score = float | tuple[float, ...]
"""Lower is better. A tuple is compared level by level: the first level that differs decides."""


def lifetime_score(est: Mapping[str, NodeEstimate]) -> Score:
    """Leximin over battery lifetimes: the smallest first (negated), then the next smallest,
    and so on, then total drain; total drain alone if no node has a battery. A move that leaves
    the shortest-lived node as it is can still lengthen the next one — how a node that is not
    the bottleneck makes room for the bottleneck's work."""
    total = sum(e.drain_w for e in est.values())
    lives = sorted(
        min(e.lifetime_s, LIFETIME_CAP_S) for e in est.values() if e.lifetime_s is not None
    )
    if not lives:
        return total
    return (*(-life for life in lives), total)


def energy_score(est: Mapping[str, NodeEstimate]) -> float:
    """Total drain in watts."""
    return sum(e.drain_w for e in est.values())


def balance_score(est: Mapping[str, NodeEstimate]) -> float:
    """The highest load."""
    return max((e.load for e in est.values()), default=0.0)


def duration_words(seconds: float) -> str:
    """A lifetime as a person reads it: 45 s, 12 min, 3.2 h, 4 days."""
    if seconds >= LIFETIME_CAP_S:
        return "unlimited"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} days"


def _differs(a: Score, b: Score) -> int | None:
    """The first level at which two scores differ (None: they do not)."""
    xs = a if isinstance(a, tuple) else (a,)
    ys = b if isinstance(b, tuple) else (b,)
    for i, (x, y) in enumerate(zip(xs, ys, strict=False)):
        if not math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12):
            return i
    return None


def explain_lifetime(before: Score, after: Score) -> str:
    """A lifetime score's change in words: the level that decides (the shortest battery
    life, the next one, ...; or the total drain), before and after."""
    level = _differs(before, after)
    if not isinstance(before, tuple) or not isinstance(after, tuple):
        return explain_drain(before, after)
    if level is None:
        return "no change in battery lives"
    if level >= min(len(before), len(after)) - 1:
        return f"total drain {before[-1]:.2f} W -> {after[-1]:.2f} W (battery lives unchanged)"
    which = "shortest" if level == 0 else f"{_ordinal(level + 1)} shortest"
    was, will = duration_words(-before[level]), duration_words(-after[level])
    if was == will:  # a gain smaller than the words round to: say it in seconds
        return f"{which} battery life {was}, {_gain_words(-before[level], -after[level])}"
    return f"{which} battery life {was} -> {will}"


def _gain_words(before_s: float, after_s: float) -> str:
    """A small change of a lifetime in words: "0.4 s longer" (or shorter)."""
    d = after_s - before_s
    return f"{abs(d):.2g} s {'longer' if d >= 0 else 'shorter'}"


def explain_drain(before: Score, after: Score) -> str:
    b, a = _first(before), _first(after)
    return f"total drain {b:.2f} W -> {a:.2f} W"


def explain_load(before: Score, after: Score) -> str:
    b, a = _first(before), _first(after)
    return f"highest CPU load {b:.0%} -> {a:.0%}"


def _first(score: Score) -> float:
    return score[0] if isinstance(score, tuple) else score


def _ordinal(n: int) -> str:
    return {2: "2nd", 3: "3rd"}.get(n, f"{n}th")


def slo_violations(snap: Snapshot) -> list[Action]:
    """A remap for every chain this node coordinates whose measured delay exceeds its SLO."""
    out: list[Action] = []
    for c in sorted(snap.chains, key=lambda c: c.key):
        delay, slo = c.delay_ms, c.slo_ms
        if c.coordinator and delay is not None and slo is not None and delay > slo:
            reason = f"delay {delay:.1f} ms > SLO {slo:g} ms"
            out.append(RemapChain(c.app, c.index, reason))
    return out


def lifetime_weight(snap: Snapshot, node: str) -> float:
    """How much of ``node``'s capacity a remap's planner should see, by remaining lifetime:
    its expected lifetime over the longest among the battery nodes in view, in [0, 1]. A flat
    battery weighs 0; a wall-powered node, one whose lifetime is not known yet, and one not in
    view weigh 1 (nothing says to avoid them). Algorithm 1 gives each node a share of a chain's
    cost proportional to its capacity, so a node expected to die in half the time of the
    longest-lived one is given half the work it would otherwise get."""
    view = snap.nodes.get(node)
    if view is None or view.remaining_j is None:
        return 1.0
    if view.remaining_j <= 0:
        return 0.0
    if view.lifetime_s is None:
        return 1.0
    longest = max(
        (
            min(o.lifetime_s, LIFETIME_CAP_S)
            for o in snap.nodes.values()
            if o.battery and o.lifetime_s is not None
        ),
        default=0.0,
    )
    if longest <= 0:
        return 1.0
    return max(0.0, min(1.0, min(view.lifetime_s, LIFETIME_CAP_S) / longest))


# -- policies ------------------------------------------------------------------------------


class Policy:
    """Base class of objectives: subclass it and override ``score`` and/or ``actions``.

    ``score(snap, moves)`` says how good the placement would be if each vertex in ``moves``
    (``app/id`` → node) ran on its new node; lower is better. The relocation rule calls it with
    ``snap.nodes`` limited to the nodes a decision involves. The default is the lifetime
    objective. ``actions(snap)`` returns actions the policy wants taken whatever the scores say
    (default: none); they pass the same oscillation guard.
    """

    name: str = "policy"

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> Score:
        return lifetime_score(estimate(snap, moves))

    def actions(self, snap: Snapshot) -> list[Action]:
        return []

    def explain(self, before: Score, after: Score) -> str:
        """What a move changes, in this objective's words, for the move's log line (a
        subclass with its own score says what its score means; the default shows it)."""
        if type(self).score is Policy.score:  # the lifetime objective
            return explain_lifetime(before, after)
        return f"score {_shown(before)} -> {_shown(after)}"

    def capacity_weight(self, snap: Snapshot, node: str) -> float:
        """The factor (0..1) on ``node``'s probed capacity when an energy remap re-places
        chains (:class:`~mso.management.rules.EnergyRemapRule`): 0 keeps work off it. The
        default weighs by remaining lifetime (:func:`lifetime_weight`)."""
        return lifetime_weight(snap, node)

    def __repr__(self) -> str:
        return f"<policy {self.name}>"


class LifetimePolicy(Policy):
    """Maximise the smallest expected lifetime among battery-powered nodes (the default)."""

    name = "lifetime"


class EnergyPolicy(Policy):
    """Least total drain of the nodes involved."""

    name = "energy"

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> float:
        return energy_score(estimate(snap, moves))

    def explain(self, before: Score, after: Score) -> str:
        return explain_drain(before, after)


class BalancePolicy(Policy):
    """Lowest maximum load among the nodes involved."""

    name = "balance"

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> float:
        return balance_score(estimate(snap, moves))

    def explain(self, before: Score, after: Score) -> str:
        return explain_load(before, after)


class DelayPolicy(Policy):
    """Keep each chain's measured delay under its SLO by remapping it; relocate by ``fallback``."""

    name = "delay"

    def __init__(self, fallback: str = "balance") -> None:
        cls = POLICIES.get(fallback)
        if cls is None or cls is DelayPolicy:
            names = ", ".join(n for n in sorted(POLICIES) if n != "delay")
            raise ValueError(f"fallback must be one of {names}, got {fallback!r}")
        self.fallback: Policy = cls()

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> Score:
        return self.fallback.score(snap, moves)

    def explain(self, before: Score, after: Score) -> str:
        return self.fallback.explain(before, after)

    def actions(self, snap: Snapshot) -> list[Action]:
        return slo_violations(snap)


def _shown(score: Score) -> str:
    """A raw score, short: a tuple's first two levels."""
    if isinstance(score, tuple):
        return (
            "(" + ", ".join(f"{x:.4g}" for x in score[:2]) + (", ...)" if len(score) > 2 else ")")
        )
    return f"{score:.4g}"


POLICIES: dict[str, type[Policy]] = {
    "balance": BalancePolicy,
    "delay": DelayPolicy,
    "energy": EnergyPolicy,
    "lifetime": LifetimePolicy,
}
DEFAULT_POLICY = "lifetime"


class _Adapted(Policy):
    """A user object with ``score`` (and maybe ``actions``) that does not subclass Policy."""

    def __init__(self, inner: Any, name: str) -> None:
        self.inner = inner
        self.name = name

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> Score:
        got = self.inner.score(snap, moves)
        return tuple(float(x) for x in got) if isinstance(got, tuple) else float(got)

    def actions(self, snap: Snapshot) -> list[Action]:
        act: Callable[[Snapshot], Any] | None = getattr(self.inner, "actions", None)
        return [] if act is None else list(act(snap))

    def capacity_weight(self, snap: Snapshot, node: str) -> float:
        weigh: Callable[[Snapshot, str], Any] | None = getattr(self.inner, "capacity_weight", None)
        return lifetime_weight(snap, node) if weigh is None else float(weigh(snap, node))


def _policy_like(obj: Any) -> bool:
    return callable(getattr(obj, "score", None)) and (
        not hasattr(obj, "actions") or callable(obj.actions)
    )


def load_policy(spec: str | Mapping[str, Any] | Policy | None, *, where: str) -> Policy:
    """The policy a spec names; PolicyError (an MsoError) saying what is wrong otherwise.

    ``spec`` is None (the default, lifetime), a shipped name, an import path
    ``pkg.module:Attr`` (a Policy subclass, a factory, or an object with ``score()``), a mapping
    ``{name: NAME, params: {...}}`` or ``{code: PATH, params: {...}}`` whose params are passed as
    keyword arguments, or a Policy. ``where`` prefixes every message (e.g. ``"app.yaml: policy"``).
    """
    if spec is None:
        return POLICIES[DEFAULT_POLICY]()
    if isinstance(spec, Policy):
        return spec
    if isinstance(spec, str):
        return _load_named(spec, {}, where, allow_path=True)
    if isinstance(spec, Mapping):
        return _load_mapping(spec, where)
    if _policy_like(spec) and not isinstance(spec, type):
        return _Adapted(spec, str(getattr(spec, "name", type(spec).__name__)))
    raise PolicyError(
        f"{where}: expected a policy name, an import path pkg.module:attr or a mapping with "
        f"name or code and params, got {type(spec).__name__}"
    )


def _unknown(name: str, where: str) -> PolicyError:
    names = ", ".join(sorted(POLICIES))
    return PolicyError(
        f"{where}: unknown policy {name!r} (expected one of {names}, "
        f"or an import path pkg.module:attr)"
    )


def _load_mapping(spec: Mapping[str, Any], where: str) -> Policy:
    extra = sorted(str(k) for k in spec if k not in ("name", "code", "params"))
    if extra:
        raise PolicyError(f"{where}: unexpected key {extra[0]!r} (expected name or code, params)")
    if ("name" in spec) == ("code" in spec):
        raise PolicyError(f"{where}: expected exactly one of name (a shipped policy) or code")
    params = spec.get("params")
    if params is None:
        params = {}
    if not isinstance(params, Mapping) or not all(isinstance(k, str) for k in params):
        raise PolicyError(f"{where}: params: expected a mapping of names to values")
    if "name" in spec:
        name = spec["name"]
        if not isinstance(name, str) or name not in POLICIES:
            raise _unknown(str(name), where)
        return _load_named(name, params, where, allow_path=False)
    code = spec["code"]
    if not isinstance(code, str):
        raise PolicyError(f"{where}: code: expected an import path pkg.module:attr, got {code!r}")
    return _load_path(code, params, where)


def _load_named(name: str, params: Mapping[str, Any], where: str, *, allow_path: bool) -> Policy:
    cls = POLICIES.get(name)
    if cls is not None:
        made: Policy = _create(cls, params, f"policy {name!r}", where)
        return made
    if allow_path and ":" in name:
        return _load_path(name, params, where)
    raise _unknown(name, where)


def _load_path(path: str, params: Mapping[str, Any], where: str) -> Policy:
    try:
        obj = resolve(path)
    except ImportPathError as exc:
        raise PolicyError(f"{where}: {with_code_hint(str(exc))}") from None
    if isinstance(obj, type) or (callable(obj) and not _policy_like(obj)):
        made = _create(obj, params, repr(path), where)
    elif _policy_like(obj):
        if params:
            raise PolicyError(f"{where}: {path!r} is an object, not a class or factory: no params")
        made = obj
    else:
        made = None
    if not _policy_like(made):
        raise PolicyError(f"{where}: {path!r} does not provide score()/actions()")
    if isinstance(made, Policy):
        if made.name == Policy.name:
            made.name = path
        return made
    return _Adapted(made, str(getattr(made, "name", path)))


def _create(factory: Callable[..., Any], params: Mapping[str, Any], label: str, where: str) -> Any:
    try:
        return factory(**params)
    except (TypeError, ValueError) as exc:
        shown = f" with params {dict(params)!r}" if params else ""
        raise PolicyError(f"{where}: cannot create {label}{shown}: {exc}") from None
    except Exception as exc:  # user code: report, never crash the node
        raise PolicyError(f"{where}: creating {label} raised {type(exc).__name__}: {exc}") from None
