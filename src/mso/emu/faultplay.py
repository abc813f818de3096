"""Seeded random fault sequences for an emulator: kill by hand, fail, restart, cut, heal and
move in random order, each a command the console takes (or a SIGKILL, as a user's ``kill -9``).
The CI test plays a short one, ``bench/emulator_faults.py`` fifty; both end by restarting every
node and healing every cut, so the run's summary has every node in it."""

from __future__ import annotations

import random
from dataclasses import dataclass

KINDS = ("kill", "fail", "restart", "cut", "heal", "move")


@dataclass(frozen=True)
class Step:
    """One fault: ``kill`` is a SIGKILL by hand (no command), the rest are command lines."""

    kind: str
    line: str  # the command line ("fail N2"); "kill N2" is no command: a SIGKILL by hand
    node: str = ""


def random_sequence(
    seed: int,
    nodes: list[str],
    links: list[tuple[str, str]],
    steps: int,
    *,
    keep: tuple[str, ...] = (),
    area: tuple[float, float] = (300.0, 300.0),
    home: dict[str, tuple[float, float]] | None = None,
) -> list[Step]:
    """``steps`` faults valid in turn (a node fails only if up, restarts only if down, a link is
    healed only if cut), then the restarts, heals and moves back ``home`` that bring everything
    back. The nodes in ``keep`` never fail (those the app's source and sink are pinned to)."""
    rng = random.Random(seed)
    up, cut, moved = set(nodes), set[tuple[str, str]](), set[str]()
    out: list[Step] = []
    for _ in range(steps):
        choices = []
        victims = sorted(n for n in up if n not in keep)
        if len(victims) > 1:  # at least one node besides ``keep`` stays up
            choices += ["kill", "fail"]
        if set(nodes) - up:
            choices.append("restart")
        if set(links) - cut:
            choices.append("cut")
        if cut:
            choices.append("heal")
        choices.append("move")
        kind = rng.choice(choices)
        if kind in ("kill", "fail"):
            node = rng.choice(victims)
            up.discard(node)
            out.append(Step(kind, f"{kind} {node}", node))
        elif kind == "restart":
            node = rng.choice(sorted(set(nodes) - up))
            up.add(node)
            out.append(Step(kind, f"restart {node}", node))
        elif kind == "cut":
            a, b = rng.choice(sorted(set(links) - cut))
            cut.add((a, b))
            out.append(Step(kind, f"cut {a} {b}"))
        elif kind == "heal":
            a, b = rng.choice(sorted(cut))
            cut.discard((a, b))
            out.append(Step(kind, f"heal {a} {b}"))
        else:
            node = rng.choice(nodes)
            x, y = rng.uniform(0, area[0]), rng.uniform(0, area[1])
            moved.add(node)
            out.append(Step(kind, f"move {node} {x:.0f} {y:.0f}", node))
    out += [Step("restart", f"restart {n}", n) for n in sorted(set(nodes) - up)]
    out += [Step("heal", f"heal {a} {b}") for a, b in sorted(cut)]
    for node in sorted(moved & set(home or {})):
        x, y = (home or {})[node]
        out.append(Step("move", f"move {node} {x:g} {y:g}", node))
    return out
