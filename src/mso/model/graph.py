"""Small graph algorithms the model shares."""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping, Sequence
from typing import TypeVar

T = TypeVar("T", bound=Hashable)


def topological_order(nodes: Sequence[T], successors: Mapping[T, Iterable[T]]) -> list[T]:
    """Kahn's algorithm, stable in the order of ``nodes``; nodes on a cycle are left out
    (so a result shorter than ``nodes`` means the graph has a cycle)."""
    indeg = dict.fromkeys(nodes, 0)
    for u in nodes:
        for w in successors.get(u, ()):
            indeg[w] += 1
    ready = [v for v in nodes if indeg[v] == 0]
    i = 0
    while i < len(ready):
        v = ready[i]
        i += 1
        for w in successors.get(v, ()):
            indeg[w] -= 1
            if indeg[w] == 0:
                ready.append(w)
    return ready
