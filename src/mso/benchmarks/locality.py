"""Locality of reconfiguration (issue 24): the control messages a relocation, a chain remap and a
global remap cost, and the nodes they involve, on grids of growing size.

The paper says an intra-chain remap "affects only the nodes in the vicinity of the change"; a
chain's nodes, its event neighbours and the relays between them. :func:`measure` deploys, on a
k x k grid (1 ms links), one measured app with three chains (two sources feeding a junction,
then a sink: ``s1-a-j``, ``s2-b-j``, ``j-c-sink``) near the grid's centre, plus N/20 background
apps of 4 vertices spread over the grid, with management rules off (nothing moves unasked).
Then, one at a time and each to quiescence, it relocates ``a`` downstream, moves it off the
chain's route (unmeasured: a remap keeps a chain where it runs unless its nodes are off the
probed route or the new plan saves enough), remaps ``a``'s chain and remaps the whole app,
and reads each one's episode from the simulator's census (:mod:`mso.sim.census`). The test
suite and ``bench/locality.py`` share it.
"""

from __future__ import annotations

import itertools
import random
from dataclasses import dataclass
from typing import Any

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.census import Tally
from mso.sim.runner import Simulation

APP = "measured"
SETTLE_S = 3.0  # after each trigger: past quiescence (a 1.5 s gap), with slack


def grid(k: int) -> Network:
    """k x k nodes ``G<row>_<col>``, 4-neighbour links of 1 ms."""
    ids = [[f"G{r}_{c}" for c in range(k)] for r in range(k)]
    links = [
        LinkSpec(ids[r][c], other, delay_ms=1.0)
        for r, c in itertools.product(range(k), range(k))
        for other in ([ids[r][c + 1]] if c + 1 < k else []) + ([ids[r + 1][c]] if r + 1 < k else [])
    ]
    return Network([NodeSpec(i) for row in ids for i in row], links)


def measured_app(k: int) -> str:
    """The measured app: sources two rows apart west of the centre, the sink east of it (code-
    less vertices: stand-ins that pass events on, all the study needs). ``planner: paper``
    spreads them over the nodes between, as the committed figures were measured."""
    mid = k // 2
    s1, s2, sink = f"G{mid - 1}_{mid - 2}", f"G{mid + 1}_{mid - 2}", f"G{mid}_{mid + 2}"
    return f"""
name: {APP}
planner: paper
vertices:
  s1: {{pinned: {s1}, rate: 20}}
  s2: {{pinned: {s2}, rate: 20}}
  a: {{}}
  b: {{}}
  j: {{}}
  c: {{}}
  sink: {{pinned: {sink}}}
edges: [[s1, a], [a, j], [s2, b], [b, j], [j, c], [c, sink]]
"""


def background_app(i: int, src: str, sink: str) -> str:
    return f"""
name: bg{i}
planner: paper
vertices:
  src: {{pinned: {src}, rate: 5}}
  p: {{}}
  q: {{}}
  sink: {{pinned: {sink}}}
edges: [[src, p], [p, q], [q, sink]]
"""


@dataclass
class Step:
    """One reconfiguration's episode and what the app looked like around it."""

    kind: str
    ok: bool
    tally: Tally
    before: dict[str, str]  # the app's placement before and after
    after: dict[str, str]
    allowed: frozenset[str]  # the app's nodes (before and after) and the relays between them

    @property
    def outside(self) -> set[str]:
        """Nodes involved that are neither the app's nor on a route between two of them."""
        return set(self.tally.nodes_involved | self.tally.relays) - self.allowed

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "ok": self.ok,
            "control_messages": self.tally.control_messages,
            "nodes_involved": len(self.tally.nodes_involved),
            "relays": len(self.tally.relays),
            "outside": sorted(self.outside),
            "by_type": dict(sorted(self.tally.by_type.items())),
            "moved": {v: [self.before[v], n] for v, n in self.after.items() if self.before[v] != n},
        }


def _placement(sim: Simulation) -> dict[str, str]:
    """Where the app's vertices run: the nodes that run them say so."""
    out = {}
    for n, core in sim.cores.items():
        for v in core.instances(APP):
            out[v] = n
    return out


def _between(net: Network, nodes: set[str]) -> frozenset[str]:
    """``nodes`` and every node on a route between two of them."""
    out = set(nodes)
    for a, b in itertools.permutations(sorted(nodes), 2):
        out.update(net.route(a, b) or [])
    return frozenset(out)


def _step(sim: Simulation, kind: str, via: str, msg: m.Message) -> Step:
    before = _placement(sim)
    n = len(sim.replies)
    t0 = sim.now
    sim.request(via, msg)
    sim.run_until(t0 + SETTLE_S)
    replies = [r for _, _, r in sim.replies[n:]]
    ok = bool(replies) and all(getattr(r, "ok", False) for r in replies)
    after = _placement(sim)
    episodes = [e for e in sim.census.episodes(cuts=[t0]) if e.since >= t0]
    tally = episodes[0] if episodes else sim.census.tally(t0, t0)
    allowed = _between(sim.network, set(before.values()) | set(after.values()))
    return Step(kind, ok, tally, before, after, allowed)


def measure(k: int, *, seed: int = 0, background: bool = True) -> list[Step]:
    """A relocation, a chain remap and a global remap of the measured app on a k x k grid."""
    net = grid(k)
    sim = Simulation(net, manage=False, wire=False, seed=seed)
    ids = sorted(net.nodes)
    apps = [measured_app(k)]
    if background:
        rng = random.Random(seed)
        apps += [background_app(i, *rng.sample(ids, 2)) for i in range(len(ids) // 20)]
    t = 0.0
    for doc in apps:  # deployed one after another, from their source's node
        sim.request(ids[0], m.DeployRequest(doc, "locality.yaml"))
        t += 0.5
        sim.run_until(t)
    sim.run_until(t + 2.0)
    failed = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply) and not r.ok]
    if failed:
        raise RuntimeError(f"deployment failed: {failed[0].error}")
    via = _placement(sim)["s1"]  # a client asks a node of the app
    chain = _chain_of(sim, via, "a")
    mid = k // 2
    off = f"G{mid - 2}_{mid - 2}"  # a neighbour of s1's node away from the chain's route
    relocation = _step(sim, "relocation", via, m.RelocateRequest(APP, "a", "downstream"))
    _step(sim, "detour", via, m.RelocateRequest(APP, "a", target=off))  # (not measured)
    return [
        relocation,
        _step(sim, "chain remap", via, m.RemapRequest(APP, [chain])),
        _step(sim, "global remap", via, m.RemapRequest(APP, [], everything=True)),
    ]


def _chain_of(sim: Simulation, node: str, vertex: str) -> int:
    dep = sim.cores[node].apps[APP]
    return next(c.index for c in dep.layout.chains if vertex in c.vertices)


__all__ = ["APP", "Step", "background_app", "grid", "measure", "measured_app"]
