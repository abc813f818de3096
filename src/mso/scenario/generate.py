"""Scenarios at scale, generated from one seed: a topology (grid, random geometric, a convoy
column of platoons) and a mobility model (random waypoint, Gauss-Markov, reference-point group
mobility), written as an ordinary scenario file (docs/scenario-format.md) that ``mso simulate``
and ``mso emulate`` load like any other.

Links come from positions and a radio range, so mobility can change them. The range is chosen
for the mean degree asked: the distance of the (N × degree / 2)-th closest pair, so about that
many links exist; then raised, if needed, to the smallest range that connects the network
(grid, platoons), or, for random geometric, the nodes cut off are moved next to a node of the
largest part (so the range, and the degree, stay what was asked). The same arguments and seed
always give the same file.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

import yaml

from mso.errors import MsoError

TOPOLOGIES = ("grid", "geometric", "platoon")
MOBILITY = ("none", "random_waypoint", "gauss_markov", "group")
MAX_NODES = 10_000
GRID_DEGREES = (4, 6, 8)  # square lattice, triangular lattice, square lattice with diagonals


class GenerateError(MsoError):
    """Arguments a scenario cannot be generated from (the CLI exits 2)."""


@dataclass(frozen=True)
class Spec:
    """What to generate. ``spacing`` is the distance between grid neighbours (a random
    geometric network has the same density: one node per spacing²; a platoon's vehicles are
    a third of it apart, in two lanes, and platoons one spacing apart)."""

    topology: str
    nodes: int
    seed: int = 0
    degree: float = 6.0
    spacing: float = 100.0
    platoon: int = 10  # vehicles per platoon; also the group size for group mobility
    mobility: str = "none"
    speed: tuple[float, float] = (1.0, 5.0)
    pause_s: float = 0.0
    step_s: float = 0.5
    name: str | None = None

    def check(self) -> None:
        """Raise GenerateError naming the first argument that is out of range."""
        if self.topology not in TOPOLOGIES:
            raise GenerateError(f"topology: expected one of {', '.join(TOPOLOGIES)}")
        if self.mobility not in MOBILITY:
            raise GenerateError(f"--mobility: expected one of {', '.join(MOBILITY)}")
        if not 2 <= self.nodes <= MAX_NODES:
            raise GenerateError(f"--nodes: expected 2 to {MAX_NODES}, got {self.nodes}")
        if self.topology == "grid" and self.degree not in GRID_DEGREES:
            raise GenerateError(
                f"--degree: a grid has degree 4 (square), 6 (triangular) or 8 (with diagonals), "
                f"got {self.degree:g}"
            )
        if not 1 <= self.degree < self.nodes:
            raise GenerateError(f"--degree: expected 1 to {self.nodes - 1}, got {self.degree:g}")
        for what, v in (("--spacing", self.spacing), ("--step", self.step_s)):
            if not (math.isfinite(v) and 0 < v <= 1e9):
                raise GenerateError(f"{what}: expected a number > 0, got {v:g}")
        if not 2 <= self.platoon <= self.nodes:
            raise GenerateError(f"--platoon: expected 2 to {self.nodes}, got {self.platoon}")
        lo, hi = self.speed
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi and hi > 0):
            raise GenerateError(
                f"--speed: expected MIN MAX with 0 <= MIN <= MAX, MAX > 0, got {lo:g} {hi:g}"
            )
        if not (math.isfinite(self.pause_s) and self.pause_s >= 0):
            raise GenerateError(f"--pause: expected seconds >= 0, got {self.pause_s:g}")


def generate(spec: Spec) -> dict[str, Any]:
    """The scenario document (a mapping, as its YAML file holds it)."""
    spec.check()
    rng = random.Random(spec.seed)
    ids = [f"N{i}" for i in range(1, spec.nodes + 1)]
    if spec.topology == "grid":
        pos, radio = _grid(spec)
    elif spec.topology == "geometric":
        pos, radio = _geometric(spec, rng)
    else:
        pos, radio = _platoons(spec)
    pos = [(round(x, 2), round(y, 2)) for x, y in pos]
    name = spec.name or f"{spec.topology}-{spec.nodes}-s{spec.seed}"
    doc: dict[str, Any] = {
        "name": name,
        "radio_range": round(radio, 3),
        "nodes": {n: {"pos": [x, y]} for n, (x, y) in zip(ids, pos, strict=True)},
    }
    if spec.mobility != "none":
        doc["mobility"] = _mobility(spec, ids, pos)
    return doc


def dumps(doc: dict[str, Any], spec: Spec) -> str:
    """The scenario as YAML text, with a header saying how it was made."""
    body = dict(doc)
    nodes = body.pop("nodes")
    pos = [(a["pos"][0], a["pos"][1]) for a in nodes.values()]
    degree = round(2 * len(_pairs(pos, doc["radio_range"])) / len(pos), 2)
    head = (
        f"# generated: mso scenario generate {spec.topology} --nodes {spec.nodes} "
        f"--seed {spec.seed} --degree {spec.degree:g} --spacing {spec.spacing:g} "
        f"--mobility {spec.mobility}\n# mean degree at start: {degree}\n"
    )
    text = f"name: {body['name']}\nradio_range: {body['radio_range']}\n"
    if "mobility" in body:
        text += yaml.safe_dump(
            {"mobility": body["mobility"]}, sort_keys=False, default_flow_style=None, width=100
        )
    lines = ["nodes:"] + [
        f"  {n}: {{pos: [{a['pos'][0]}, {a['pos'][1]}]}}" for n, a in nodes.items()
    ]
    return head + text + "\n".join(lines) + "\n"


# -- topologies ---------------------------------------------------------------------------------
Points = list[tuple[float, float]]


def _grid(spec: Spec) -> tuple[Points, float]:
    s, n = spec.spacing, spec.nodes
    side = math.ceil(math.sqrt(n))
    if spec.degree == 6:  # a triangular lattice: rows half a spacing apart sideways
        row = s * math.sqrt(3) / 2
        pos = [((k % side) * s + (k // side % 2) * s / 2, (k // side) * row) for k in range(n)]
        return pos, s * 1.01
    pos = [((k % side) * s, (k // side) * s) for k in range(n)]
    return pos, s * (1.01 if spec.degree == 4 else 1.5)


def _geometric(spec: Spec, rng: random.Random) -> tuple[Points, float]:
    """Uniform positions; of up to 20 draws, the one with the fewest nodes cut off from the
    largest part, whose cut-off nodes are then moved next to a node of that part."""
    side = spec.spacing * math.sqrt(spec.nodes)
    best: tuple[int, Points, float, list[set[int]]] | None = None
    for _ in range(20):
        pos = [(rng.uniform(0, side), rng.uniform(0, side)) for _ in range(spec.nodes)]
        radio = _range_for_degree(pos, spec.degree)
        parts = _components(len(pos), _pairs(pos, radio))
        cut = len(pos) - max(map(len, parts))
        if best is None or cut < best[0]:
            best = (cut, pos, radio, parts)
        if cut == 0:
            break
    assert best is not None
    _, pos, radio, parts = best
    for _ in range(spec.nodes):  # bounded: each turn joins at least one node to the main part
        if len(parts) == 1:
            break
        main = max(parts, key=len)
        anchors = sorted(main)
        for part in parts:
            if part is main:
                continue
            for i in sorted(part):  # next to a node of the main part, within range
                a = pos[rng.choice(anchors)]
                angle, dist = rng.uniform(-math.pi, math.pi), radio * rng.uniform(0.3, 0.9)
                x = min(max(a[0] + dist * math.cos(angle), 0.0), side)
                pos[i] = (x, min(max(a[1] + dist * math.sin(angle), 0.0), side))
        parts = _components(len(pos), _pairs(pos, radio))
    return pos, radio


def _platoons(spec: Spec) -> tuple[Points, float]:
    """A convoy column: platoons of ``spec.platoon`` vehicles in two lanes (vehicles a third
    of a spacing apart), one after the other along x, half a spacing between two."""
    gap, lane = spec.spacing / 3, spec.spacing / 6
    length = math.ceil(spec.platoon / 2) * gap
    pos = []
    for k in range(spec.nodes):
        p, i = divmod(k, spec.platoon)
        pos.append((p * (length + spec.spacing / 2) + (i // 2) * gap, (i % 2) * lane))
    return pos, _range_to_connect(pos, _range_for_degree(pos, spec.degree))


def _range_for_degree(pos: Points, degree: float) -> float:
    """The range giving about ``degree`` links per node: the distance of the
    (N × degree / 2)-th closest pair (among the pairs within a range grown until there are
    that many: linear in N, where sorting every pair's distance is quadratic)."""
    want = max(1, round(len(pos) * degree / 2))
    xs, ys = [p[0] for p in pos], [p[1] for p in pos]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 1e-9)
    radio = span * math.sqrt(degree / (math.pi * len(pos)))  # uniform density's guess
    for _ in range(200):  # bounded: the range grows by a quarter each turn
        pairs = _pairs(pos, radio)
        if len(pairs) >= want:
            break
        radio *= 1.25
    dists = sorted(math.dist(pos[a], pos[b]) for a, b in pairs)
    return dists[min(want, len(dists)) - 1] * 1.0001


def _range_to_connect(pos: Points, radio: float) -> float:
    """``radio``, raised by tenths until every node is connected."""
    for _ in range(200):  # bounded: a range over the whole span connects every node
        if len(_components(len(pos), _pairs(pos, radio))) == 1:
            break
        radio *= 1.1
    return radio


def _pairs(pos: Points, radio: float) -> list[tuple[int, int]]:
    from mso.model.network import pairs_within

    ids = [str(i) for i in range(len(pos))]
    return [(int(a), int(b)) for a, b in pairs_within(dict(enumerate(pos)), radio, ids)]


def _components(n: int, links: list[tuple[int, int]]) -> list[set[int]]:
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in links:
        adj[a].append(b)
        adj[b].append(a)
    seen: set[int] = set()
    parts = []
    for s in range(n):
        if s in seen:
            continue
        part, todo = {s}, [s]
        while todo:
            for w in adj[todo.pop()]:
                if w not in part:
                    part.add(w)
                    todo.append(w)
        seen |= part
        parts.append(part)
    return parts


# -- mobility -----------------------------------------------------------------------------------
def _mobility(spec: Spec, ids: list[str], pos: Points) -> dict[str, Any]:
    w = max(x for x, _ in pos) + spec.spacing
    h = max(y for _, y in pos) + spec.spacing
    out: dict[str, Any] = {
        "model": spec.mobility,
        "area": [round(w, 1), round(h, 1)],
        "speed": [spec.speed[0], spec.speed[1]],
    }
    if spec.mobility == "gauss_markov":
        out.update(alpha=0.75, interval_s=1.0)
    else:
        out["pause_s"] = spec.pause_s
    if spec.mobility == "group":
        size = spec.platoon
        out["groups"] = [ids[i : i + size] for i in range(0, len(ids), size)]
        out["radius"] = round(spec.spacing / 6, 2)
    out.update(seed=spec.seed, step_s=spec.step_s)
    return out


# -- apps for studies ---------------------------------------------------------------------------
PIPELINE = """\
name: {name}
vertices:
  src: {{code: mso.sim.vertices:Source, params: {{name: src}}, rate: {rate:g}, pinned: {src},
        output: mso.sim.vertices:Ev}}
  p1: {{code: mso.sim.vertices:Pass, cost: 1, output: mso.sim.vertices:Ev}}
  p2: {{code: mso.sim.vertices:Pass, cost: 1, output: mso.sim.vertices:Ev}}
  sink: {{code: mso.sim.vertices:Sink, params: {{run: {run}, name: sink}}, pinned: {sink}}}
edges: [[src, p1], [p1, p2], [p2, sink]]
"""


def pipelines(
    nodes: list[str], count: int, *, seed: int = 0, rate: float = 5.0, run: str = "study"
) -> list[tuple[str, str]]:
    """``count`` apps of 4 vertices (a numbering source, two pass-throughs, a recording sink:
    :mod:`mso.sim.vertices`), each source and sink pinned to two nodes drawn from ``seed``;
    returns (source node, app document) pairs, to deploy from the source's node."""
    rng = random.Random(seed)
    out = []
    for i in range(count):
        src, sink = rng.sample(nodes, 2)
        doc = PIPELINE.format(name=f"app{i}", rate=rate, src=src, sink=sink, run=run)
        out.append((src, doc))
    return out


__all__ = [
    "MOBILITY", "TOPOLOGIES", "GenerateError", "Spec", "dumps", "generate", "pipelines",
]  # fmt: skip
