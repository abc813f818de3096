"""User policy plug-ins, loaded by import path (``custom_policy:...``) in test_management.py."""

from __future__ import annotations

from collections.abc import Mapping

from mso.management import Action, Policy, Relocate, Snapshot


class PreferNode(Policy):
    """Wants every hosted vertex on one node: stands in for any site-specific objective."""

    name = "prefer-node"

    def __init__(self, node: str = "D") -> None:
        self.node = node

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> float:
        return float(sum(moves.get(v.key, v.node) != self.node for v in snap.vertices))


class Unnamed(Policy):
    """A subclass that sets no name: it is named after its import path."""


class ScoreOnly:
    """Duck-typed: not a Policy subclass, no actions()."""

    name = "score-only"

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> float:
        return 0.0


def make_scorer() -> ScoreOnly:
    return ScoreOnly()


class NotAPolicy:
    def actions(self, snap: Snapshot) -> list[Action]:
        return []


class Broken(Policy):
    name = "broken"

    def score(self, snap: Snapshot, moves: Mapping[str, str]) -> float:
        raise RuntimeError("sensor table missing")


class MovesChainHead(Policy):
    """Asks for something the rules must refuse: relocating a chain's head."""

    name = "moves-head"

    def __init__(self, vertex: str = "A") -> None:
        self.vertex = vertex

    def actions(self, snap: Snapshot) -> list[Action]:
        return [Relocate("app", self.vertex, "D", "why not")]
