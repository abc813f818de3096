"""Capabilities and placement constraints (paper §3.3): what a node offers, what a vertex needs.

A node declares **capabilities**: labels (``camera``, ``lidar``, ``gpu``, ``storage``) and
amounts (``mem_mb: 4096``, ``gpu: 2``); a label is an amount of 1. Its ``cpu`` counts as one
too. A vertex may say ``requires: [camera]`` or ``requires: {gpu: 1, mem_mb: 512}`` instead of
``pinned:``, and ``near: VERTEX`` (as few hops as possible from that vertex's node) or
``apart_from: VERTEX`` (never on that vertex's node).

Before Algorithm 1 places chains, each such vertex is resolved to one node: the nodes that have
what it requires answer (in a deployment, to the deploying node's query), and the choice among
them is by their abilities, deterministically (:func:`rank`): nearest to its ``near`` vertex,
then the most CPU, then the most battery (wall power first), then the node id. From then on the
vertex is placed as if pinned there; the ranked list is kept, so after a failure the next live
candidate takes it. Pure: no I/O.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mso.errors import AppError, PlanningError

NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$")
MAX_CAPABILITIES = 64  # per node or per vertex: a document's bound
MAX_AMOUNT = 1e12

Capabilities = dict[str, float]


def parse_capabilities(spec: Any, where: str) -> Capabilities:
    """A list of labels or a mapping of name to a non-negative amount (``true`` is 1), as a
    node declares them or a vertex requires them. Raises :class:`AppError` naming ``where``."""
    if spec is None:
        return {}
    if isinstance(spec, str):
        spec = [spec]
    if isinstance(spec, list):
        items: list[tuple[Any, Any]] = [(name, 1.0) for name in spec]
    elif isinstance(spec, dict):
        items = list(spec.items())
    else:
        raise AppError(
            f"expected a list of names or a mapping of name to amount, got {spec!r}", field=where
        )
    if len(items) > MAX_CAPABILITIES:
        raise AppError(f"more than {MAX_CAPABILITIES} capabilities", field=where)
    out: Capabilities = {}
    for name, amount in items:
        if not isinstance(name, str) or not NAME.match(name):
            raise AppError(
                f"expected a capability name (letters, digits, _ . -), got {name!r}", field=where
            )
        if amount is True:
            amount = 1.0
        if (
            isinstance(amount, bool)
            or not isinstance(amount, int | float)
            or not math.isfinite(amount)
            or not 0 <= amount <= MAX_AMOUNT
        ):
            raise AppError(
                f"{name}: expected a non-negative amount (or true), got {amount!r}", field=where
            )
        if name in out:
            raise AppError(f"{name} given twice", field=where)
        out[name] = float(amount)
    return out


def offered(capabilities: Mapping[str, float], cpu: float) -> Capabilities:
    """What a node offers: its declared capabilities and its ``cpu``."""
    return {"cpu": float(cpu), **capabilities}


def missing(requires: Mapping[str, float], offers: Mapping[str, float]) -> list[str]:
    """What of ``requires`` a node offering ``offers`` lacks, in words (empty: it qualifies)."""
    out = []
    for name, amount in requires.items():
        have = offers.get(name, 0.0)
        if have < amount or (amount == 0 and name not in offers):
            out.append(name if amount == 1 and name != "cpu" else f"{name} >= {amount:g}")
    return out


def describe(requires: Mapping[str, float]) -> str:
    return ", ".join(
        name if amount == 1 and name != "cpu" else f"{name}: {amount:g}"
        for name, amount in requires.items()
    )


@dataclass(frozen=True)
class Candidate:
    """A node that answered: what it offers, its battery (None: wall power) and its hops to
    the nodes the constraints name (``near``)."""

    node: str
    offers: Mapping[str, float]
    battery_wh: float | None = None
    hops: Mapping[str, int] | None = None


def rank(
    requires: Mapping[str, float],
    candidates: Sequence[Candidate],
    *,
    near: str | None = None,
    apart: Sequence[str] = (),
) -> list[str]:
    """The nodes that qualify, best first: nearest (hops) to ``near``'s node if given, then
    the most CPU, the most battery (wall power first), the node id. ``apart`` nodes are out."""

    def key(c: Candidate) -> tuple[float, float, float, str]:
        hops = math.inf
        if near is not None:
            hops = 0 if c.node == near else float((c.hops or {}).get(near, math.inf))
        battery = math.inf if c.battery_wh is None else c.battery_wh
        return (hops if near is not None else 0.0, -c.offers.get("cpu", 0.0), -battery, c.node)

    fit = [c for c in candidates if c.node not in apart and not missing(requires, c.offers)]
    return [c.node for c in sorted(fit, key=key)]


@dataclass(frozen=True)
class Needs:
    """One vertex's constraints, as the app states them."""

    vertex: str
    requires: Mapping[str, float]
    near: str | None = None
    apart_from: str | None = None


def resolve(
    needs: Sequence[Needs],
    pinned: Mapping[str, str],
    candidates: Sequence[Candidate],
    *,
    alive: Callable[[str], bool] = lambda n: True,
) -> tuple[dict[str, str], dict[str, list[str]]]:
    """Each constrained vertex's node and its ranked candidates, in the order ``needs`` gives
    (a ``near``/``apart_from`` target is pinned or resolved before). Raises
    :class:`~mso.errors.PlanningError` naming the vertex and what no node has."""

    placed = dict(pinned)
    chosen: dict[str, str] = {}
    ranked: dict[str, list[str]] = {}
    live = [c for c in candidates if alive(c.node)]
    for n in needs:
        near = placed.get(n.near) if n.near is not None else None
        apart = [placed[n.apart_from]] if n.apart_from in placed else []
        order = rank(n.requires, live, near=near, apart=apart)
        if not order:
            raise PlanningError(why_not(n, live, apart))
        chosen[n.vertex] = placed[n.vertex] = order[0]
        ranked[n.vertex] = order
    return chosen, ranked


def why_not(n: Needs, candidates: Sequence[Candidate], apart: Sequence[str]) -> str:
    """The refusal for a vertex no node qualifies for: what it requires, what is missing."""
    req = describe(n.requires) or "nothing"
    if not candidates:
        return f"vertex {n.vertex!r} requires {req}: no node answered"
    lacks: dict[str, int] = {}
    for c in candidates:
        for m in missing(n.requires, c.offers):
            lacks[m] = lacks.get(m, 0) + 1
    absent = [m for m, k in lacks.items() if k == len(candidates)]
    if absent:
        return (
            f"vertex {n.vertex!r} requires {req}, and no node has {', '.join(absent)} "
            f"(nodes that answered: {', '.join(sorted(c.node for c in candidates))})"
        )
    if apart and n.apart_from is not None:
        return (
            f"vertex {n.vertex!r} requires {req} apart from {n.apart_from!r} (on {apart[0]}), "
            "and no other node has it"
        )
    return f"vertex {n.vertex!r} requires {req}, and no one node has all of it"
