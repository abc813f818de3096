"""Seeded fault schedules, in the style of FoundationDB's and TigerBeetle's simulators.

From one seed, :func:`generate` draws a connected topology (line, mesh or random geometric, 3 to
8 nodes), an app (a pipeline, a merge of two sources, or a fork to two sinks, with the recording
vertices of :mod:`mso.sim.vertices`) and a schedule over virtual time: crashes and restarts,
partitions and heals, link flaps, message loss, and relocations and remaps requested at random
moments. The scenario part is plain timeline changes (``mso.scenario``), so the simulator plays
it with the same player as the emulator. Then everything heals and a quiet period follows, and
:mod:`mso.sim.invariants` checks the result.

:func:`run` is deterministic: the same seed gives the same event log (every delivery, change and
request, in order), so a failing seed replays exactly. Nothing here reads a clock.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import random
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mso.model.appfile import loads_app
from mso.model.chains import form_chains
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.scenario.format import (
    Change,
    Heal,
    LinkChange,
    LossChange,
    NodeFailure,
    NodeRestart,
    Partition,
    Scenario,
)
from mso.scenario.timeline import Timeline
from mso.sim import vertices
from mso.sim.invariants import (
    STATUS_CLIENT,
    AppHolders,
    HeldFailed,
    Violation,
    check,
    check_procedures,
    repeats,
)
from mso.sim.play import Call, drive
from mso.sim.runner import Simulation
from mso.sim.schedule import Schedule, Settings

KINDS = ("crash", "partition", "flap", "loss", "relocate", "remap")
RESTART = "restart"  # a daemon restart, drawn with ``Settings.restarts``
HOLDERS_EVERY_S = 0.01  # how often the run looks whether the app went with its holders


@dataclass
class Result:
    seed: int
    topology: str
    nodes: int
    faults: Counter[str]
    violations: list[Violation]
    log: list[str] = field(default_factory=list)
    repeats: int = 0  # events a sink got in two instances (invariants.repeats)

    @property
    def digest(self) -> str:
        """A short hash of the event log: two runs of one seed must agree."""
        return hashlib.sha256("\n".join(self.log).encode()).hexdigest()[:16]


def _topology(rng: random.Random) -> tuple[str, Network]:
    n = rng.randint(3, 8)
    ids = [f"N{i}" for i in range(1, n + 1)]
    kind = rng.choice(("line", "mesh", "geometric"))
    pairs: set[tuple[str, str]] = set()
    if kind in ("line", "mesh"):
        pairs = {(ids[i], ids[i + 1]) for i in range(n - 1)}
        if kind == "mesh":
            for a, b in itertools.combinations(ids, 2):
                if rng.random() < 0.3:
                    pairs.add((a, b))
    else:
        radius = 0.45
        for _ in range(50):  # bounded: widen the range until the graph is connected
            pos = {i: (rng.random(), rng.random()) for i in ids}
            pairs = {
                (a, b) for a, b in itertools.combinations(ids, 2)
                if math.dist(pos[a], pos[b]) <= radius
            }  # fmt: skip
            if _connected(ids, pairs):
                break
            radius += 0.05
        else:  # pragma: no cover - 50 widenings always connect the unit square
            pairs = {(ids[i], ids[i + 1]) for i in range(n - 1)}
    links = [LinkSpec(a, b, delay_ms=round(rng.uniform(0.5, 3.0), 2)) for a, b in sorted(pairs)]
    return kind, Network([NodeSpec(i) for i in ids], links)


def _connected(ids: list[str], pairs: set[tuple[str, str]]) -> bool:
    adj: dict[str, set[str]] = {i: set() for i in ids}
    for a, b in pairs:
        adj[a].add(b)
        adj[b].add(a)
    seen, todo = {ids[0]}, [ids[0]]
    while todo:
        for nb in adj[todo.pop()] - seen:
            seen.add(nb)
            todo.append(nb)
    return len(seen) == len(ids)


def _app(
    rng: random.Random, nodes: list[str], rate: float, run: str, planner: str
) -> tuple[str, dict[str, str]]:
    shape = rng.choice(("pipeline", "merge", "fork"))
    ev = "output: mso.sim.vertices:Ev"  # typed events: they decode as Ev, not as a mapping
    src = "{code: mso.sim.vertices:Source, params: {name: %s}, rate: %g, pinned: %s, " + ev + "}"
    snk = "{code: mso.sim.vertices:Sink, params: {run: '%s', name: %s}, pinned: %s}"
    op = "{code: mso.sim.vertices:Pass, cost: %g, " + ev + "}"
    # a stateful vertex (replicas: 1 by default) where it has one input, so its replay is
    # exact: its count must survive every failure the replication covers ("state")
    counter = "{code: mso.sim.vertices:Count, cost: %g, " + ev + "}"

    def pick() -> str:
        return rng.choice(nodes)

    pinned: dict[str, str] = {}
    lines = ["name: faults", f"planner: {planner}", "vertices:"]

    def source(v: str) -> None:
        pinned[v] = pick()
        lines.append(f"  {v}: " + src % (v, rate, pinned[v]))

    def sink(v: str) -> None:
        pinned[v] = pick()
        lines.append(f"  {v}: " + snk % (run, v, pinned[v]))

    def ops(*vs: str, count: str = "") -> None:
        for v in vs:
            code = counter if v == count else op
            lines.append(f"  {v}: " + code % round(rng.uniform(0.5, 10), 1))

    if shape == "pipeline":
        k = rng.randint(1, 3)
        mids = [f"p{i}" for i in range(1, k + 1)]
        source("src")
        ops(*mids, count="p1")
        sink("sink")
        path = ["src", *mids, "sink"]
        edges = list(itertools.pairwise(path))
    elif shape == "merge":
        source("s1")
        source("s2")
        ops("a", "b", "m", "c", count="c")
        sink("sink")
        edges = [("s1", "a"), ("a", "m"), ("s2", "b"), ("b", "m"), ("m", "c"), ("c", "sink")]
    else:
        source("src")
        ops("a", "j", "b", "c", count="a")
        sink("k1")
        sink("k2")
        edges = [("src", "a"), ("a", "j"), ("j", "b"), ("b", "k1"), ("j", "c"), ("c", "k2")]
    lines.append("edges: [" + ", ".join(f"[{a}, {b}]" for a, b in edges) + "]")
    return "\n".join(lines) + "\n", pinned


def generate(seed: int, settings: Settings | None = None) -> Schedule:
    """The world and the fault schedule of ``seed``."""
    cfg = settings or Settings()
    rng = random.Random(seed)
    kind, net = _topology(rng)
    ids = list(net.nodes)
    doc, pinned = _app(rng, ids, cfg.rate, str(seed), cfg.planner)
    app = loads_app(doc, file=f"faults-{seed}.yaml")
    chains = form_chains(app)
    movable = sorted(
        v for c in chains for v in c.vertices[1:-1] if v not in pinned
    )  # interior vertices: the only ones a relocation may move
    changes: list[Change] = []
    requests: list[tuple[float, str, m.Message]] = []
    faults: Counter[str] = Counter()
    t0, t1 = cfg.start_s, cfg.start_s + cfg.faults_s
    for _ in range(rng.randint(1, cfg.max_faults)):
        at = round(rng.uniform(t0, t1), 3)
        what = rng.choice((*KINDS, RESTART) if cfg.restarts else KINDS)
        if what == "crash":
            node = rng.choice(ids)  # overlapping crashes of one node are fine: a failed
            back = round(min(t1, at + rng.uniform(0.2, 3.0)), 3)  # node does not fail again
            changes += [NodeFailure(at, node), NodeRestart(back, node)]
        elif what == "partition":
            side = frozenset(rng.sample(ids, rng.randint(1, len(ids) - 1)))
            changes += [
                Partition(at, (side, frozenset(ids) - side)),
                Heal(round(min(t1, at + rng.uniform(0.3, 2.5)), 3)),
            ]
        elif what == "restart":
            changes += _restart(rng, ids, at, t1)
        elif what == "flap":
            a, b = rng.choice(sorted(net.links))
            link = net.links[(a, b)]
            up = round(at + rng.uniform(0.02, 0.3), 3)  # shorter than failure detection
            changes += [LinkChange(at, a, b, False, link), LinkChange(up, a, b, True, link)]
        elif what == "loss":
            p = round(rng.uniform(0.05, 0.3), 2)
            ends = rng.choice([None, *sorted(net.links)])
            changes += [LossChange(at, p, ends), LossChange(round(min(t1, at + 2.0), 3), 0.0)]
        elif what == "relocate":
            if not movable:
                continue
            v = rng.choice(movable)
            how = rng.choice(("upstream", "downstream", "to"))
            target = rng.choice(ids) if how == "to" else ""
            msg: m.Message = m.RelocateRequest("faults", v, "" if how == "to" else how, target)
            requests.append((at, rng.choice(ids), msg))
        else:
            chosen = sorted(rng.sample(range(len(chains)), rng.randint(1, len(chains))))
            everything = rng.random() < 0.3
            requests.append((at, rng.choice(ids), m.RemapRequest("faults", chosen, everything)))
        faults[what] += 1
    # the end of the fault phase: everything heals, every node is up, no loss
    changes += [Heal(t1), LossChange(t1, 0.0)]
    changes += [NodeRestart(t1, n) for n in ids]
    changes += [LinkChange(t1, a, b, True, spec) for (a, b), spec in sorted(net.links.items())]
    changes.sort(key=lambda c: c.at)
    return Schedule(seed, kind, net, doc, changes, requests, faults, cfg, pinned)


def _restart(rng: random.Random, ids: list[str], at: float, t1: float) -> list[Change]:
    """A node's daemon restarts (a new process, its spill store kept): quickly, before the
    others notice, or after a while; half the time while it is cut off from the rest (its
    sources' edges hold what they make, durably, across the restart), healed after."""
    node = rng.choice(ids)
    down = round(rng.uniform(0.05, 1.5), 3)
    cut_off = rng.random() < 0.5
    if not cut_off or at > t1 - 0.5:  # (each change strictly before the final heal)
        return [NodeFailure(at, node), NodeRestart(round(min(t1 - 0.01, at + down), 3), node)]
    cut = round(min(at + rng.uniform(0.3, 1.5), t1 - 0.3), 3)  # fails while cut off
    back = round(min(t1 - 0.2, cut + down), 3)
    others = frozenset(ids) - {node}
    return [
        Partition(at, (frozenset({node}), others)),
        NodeFailure(cut, node),
        NodeRestart(back, node),
        Heal(round(min(t1 - 0.1, back + rng.uniform(0.2, 2.0)), 3)),
    ]


def run(seed: int, settings: Settings | None = None) -> Result:
    """Play ``seed``'s schedule in virtual time and check the invariants."""
    sched = generate(seed, settings)
    token = str(seed)
    vertices.RUNS.pop(token, None)
    net = Network(
        list(sched.network.nodes.values()),
        [
            LinkSpec(s.a, s.b, s.bandwidth_mbps, s.delay_ms, s.loss)
            for s in sched.network.links.values()
        ],
    )
    scenario = Scenario(name=f"faults-{seed}", network=net, changes=list(sched.changes))
    sim = Simulation(net, seed=seed, manage=False)
    sim.trace = []
    if sched.settings.control_loss > 0:
        sim.drop = _control_loss(sim, seed, sched.settings)
    timeline = Timeline(scenario, network=net)
    log: list[str] = []
    violations: list[Violation] = []

    def request(at: float, node: str, msg: m.Message) -> Call:
        def do(s: Simulation) -> None:
            if node in s.killed:
                log.append(f"{s.now:012.6f} request via killed {node} skipped")
                return
            log.append(f"{s.now:012.6f} request via {node}: {msg!r}")
            s.request(node, msg, client=2)

        return (at, do)

    calls: list[Call] = []
    for at, node, msg in sched.requests:
        calls.append(request(at, node, msg))

    held = HeldFailed()
    holders = AppHolders()

    def deadlines(s: Simulation) -> None:
        violations.extend(check_procedures(s))
        violations.extend(held.check(s))

    calls += [(k * 0.5, deadlines) for k in range(1, int(sched.end / 0.5))]
    every = HOLDERS_EVERY_S
    calls += [(k * every, holders.check) for k in range(1, int(sched.end / every))]
    # and just after every failure and restart: a node back 2 ms before the last holder died
    # never got the app, a window the sampling alone missed (restart seed 8271)
    ups_downs = {c.at for c in sched.changes if isinstance(c, NodeFailure | NodeRestart)}
    calls += [(at, holders.check) for at in sorted(ups_downs)]
    sim.request("N1", m.DeployRequest(sched.app, f"faults-{seed}.yaml"))
    status_at = sched.end - 1.5  # a status round trip through every live node, before the end
    calls.append((status_at, _ask_status))
    try:
        drive(sim, timeline, sched.end, calls=calls)
    except Exception as exc:  # a node core that raises: the run stops there, that is the bug
        where = traceback.extract_tb(exc.__traceback__)[-1]
        violations.append(
            Violation("exception", f"at {sim.now:.6f}: {type(exc).__name__}: {exc} "
                      f"({Path(where.filename).name}:{where.lineno} {where.name})")
        )  # fmt: skip
    log += [f"{t:012.6f} timeline {what}" for t, what in timeline.played]
    log += [f"{t:012.6f} {node} <- {src} {kind}" for t, node, src, kind in sim.trace]
    log.sort()  # one order for deliveries, changes and requests, by virtual time then text
    records = vertices.RUNS.pop(token, [])
    if not any(v.invariant == "exception" for v in violations):
        violations += check(sim, sched, records, holders)
    unique = list(dict.fromkeys(violations))  # a periodic check may see one problem again
    again = repeats(records)
    return Result(seed, sched.topology, len(net.nodes), sched.faults, unique, log, again)


UNLOSSY = (m.Data, m.Ack, m.Heartbeat, m.StatusRequest, m.StatusReply)


def _control_loss(
    sim: Simulation, seed: int, cfg: Settings
) -> Callable[[str, str, m.Message], bool]:
    """Loses each control frame with probability ``cfg.control_loss`` after ``cfg.start_s``
    (drawn from a generator of its own: the schedule's draws stay those of the seed). Events
    and acks have their own loss and retransmission; beats and the status check are left."""
    rng = random.Random(f"control-loss/{seed}")

    def drop(node: str, dst: str, msg: m.Message) -> bool:
        if sim.now < cfg.start_s or isinstance(msg, UNLOSSY):
            return False
        return rng.random() < cfg.control_loss

    return drop


def _ask_status(sim: Simulation) -> None:
    """Ask the first live node for every node's status (checked by the invariants)."""
    first = next(n for n in sorted(sim.cores) if n not in sim.killed)
    sim.request(first, m.StatusRequest(req=0, everywhere=True), client=STATUS_CLIENT)


def summary(results: list[Result]) -> dict[str, Any]:
    """Seeds run, faults injected by kind, violations by invariant, and the failing seeds."""
    faults: Counter[str] = Counter()
    by_invariant: Counter[str] = Counter()
    failing: dict[int, list[str]] = {}
    for r in results:
        faults.update(r.faults)
        for v in r.violations:
            by_invariant[v.invariant] += 1
        if r.violations:
            failing[r.seed] = sorted({v.invariant for v in r.violations})
    return {
        "seeds": len(results),
        "faults": dict(sorted(faults.items())),
        "violations": dict(sorted(by_invariant.items())),
        "failing_seeds": failing,
    }
