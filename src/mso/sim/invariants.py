"""What must hold once a fault schedule is over and the network has been quiet for a while.

Each check reads what the nodes themselves report (``NodeCore.status``, the same figures as
``mso status``) plus what the recording sinks of :mod:`mso.sim.vertices` received. A violation
names its invariant, so a benchmark can count them by kind and a failing seed says what broke:

- ``deploy``: the app was deployed (before any fault);
- ``status``: every live node answers status, locally and through one everywhere-request;
- ``membership``: no live node still holds another failed once all are back and linked;
- ``hosted-once``: every vertex runs exactly once over the live nodes;
- ``placement``: every live node knows the app, the ones that host part of it (who are told of
  its moves; the others ask before they act on it) all agree on its placement, and each vertex
  is placed on a live node that hosts it (unless every node was down at one moment: an app lives
  in its nodes' memory only, so then it is gone from all of them, and no node may know it);
- ``dangling-edge``: both ends of every edge have its channel where the placement says;
- ``parked``: no chain is still parked;
- ``duplicate`` / ``reorder``: a sink instance got an event of a stream twice, or after a later
  one (never allowed);
- ``lost``: a sink instance missed events in the middle of a stream, with no fault to blame (no
  node was declared failed, nothing was parked: only flaps, loss, relocations and remaps);
- ``stalled``: once quiet, a sink does not follow its sources' current streams;
- ``delivered-once``: every event a source emitted reaches each sink below it exactly once
  (within bounds): over a sink's instances, each stream is whole from its first event to the
  last delivered, whatever the faults (partitions and heals, failures, restarts). The only loss
  allowed is the newest events of a stream whose source's node died (what its edges had in
  memory, in flight to a consumer in reach), and, when an edge's bound or QoS gave some up,
  what it counted (``given_up``). Within one instance no event twice (``duplicate``); across a
  sink's restore the replay may repeat what it processed but had not acknowledged. Streams
  through a merge that was restored or moved are checked too (its outputs carry their
  provenance: mso.protocol.provenance);
- ``held-failed``: a live node held failed by another while the two have routes to each other
  (it is heard) for longer than ``HEARD_GRACE_S`` — unreachable is not failed, and a node
  declared failed that is heard again rejoins or resets within a few beats (checked
  periodically during the run by :class:`HeldFailed`);
- ``state``: the count a stateful vertex (``Count``, replicated) stamps on each event went back
  at a sink more often than the nodes declared its state restarted (``state_restarted``: no
  usable replica, e.g. a producer died with it), or skipped numbers with no fault to blame;
- ``deadline`` / ``illegal-transition``: a procedure outlived its deadline, or the core counted
  an illegal state transition (when the core reports these);
- ``exception``: a node core raised (the run stops there; recorded by ``mso.sim.faults``).
"""

from __future__ import annotations

import itertools
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from mso.protocol import messages as m
from mso.scenario.format import NodeFailure, NodeRestart
from mso.sim.runner import Simulation
from mso.sim.schedule import Schedule
from mso.sim.vertices import SinkRecord

APP = "faults"
STATUS_CLIENT = 3  # the client id the fault run asks status with
DEADLINE_SLACK_S = 1e-3  # a procedure's own expiry timer fires at its deadline
# how long a node may hold a live node it has routes with failed: a heal's rejoin beat comes
# every REJOIN_EVERY heartbeat periods (1 s), then a reset and a sync
HEARD_GRACE_S = 2.0


@dataclass(frozen=True)
class Violation:
    invariant: str
    detail: str

    def __str__(self) -> str:
        return f"{self.invariant}: {self.detail}"


def check_procedures(sim: Simulation) -> list[Violation]:
    """Every open procedure is still within its deadline; no illegal transition was counted.
    A no-op until the core reports ``open_procedures(now)``."""
    out: list[Violation] = []
    for n, core in sorted(sim.cores.items()):
        if n in sim.killed:
            continue
        opened = getattr(core, "open_procedures", None)
        if callable(opened):
            for p in opened(sim.now):
                deadline = (
                    p.get("deadline") if isinstance(p, dict) else getattr(p, "deadline", None)
                )
                if deadline is not None and deadline + DEADLINE_SLACK_S < sim.now:
                    out.append(Violation("deadline", f"{n} at {sim.now:.3f}: {p!r}"))
        illegal = getattr(core, "illegal_transitions", 0)
        if illegal:
            out.append(Violation("illegal-transition", f"{n} counted {illegal}"))
    return out


@dataclass
class AppHolders:
    """Whether the app went with the nodes that held it: at some moment no live node held
    it, and every node that held it at the moment before had failed since (not dropped it:
    a live node that loses the app is a finding). Nothing persists an app across a restart
    of every node that holds it; a node that restarted meanwhile but was cut off from them
    never got it (seed 19231: a 3-node line, every holder down at once though one node was
    back). Only the nodes that take part in it count (issue 24.1): one that holds it idle
    lets it go by design (``NodeCore.takes_part``)."""

    app: str = APP
    holders: set[str] = field(default_factory=set)
    gone_at: float | None = None

    def check(self, sim: Simulation) -> None:
        now = {
            n
            for n, c in sim.cores.items()
            if n not in sim.killed and self.app in c.apps and c.takes_part(c.apps[self.app])
        }
        if not now and self.holders and self.holders <= sim.killed and self.gone_at is None:
            self.gone_at = sim.now
        self.holders = now


@dataclass
class HeldFailed:
    """ "No node held failed while it is heard", checked at moments of the run: each pair
    (holder, held) with the held node live and routes both ways, since when it was seen so."""

    since: dict[tuple[str, str], float] = field(default_factory=dict)

    def check(self, sim: Simulation) -> list[Violation]:
        out: list[Violation] = []
        seen: dict[tuple[str, str], float] = {}
        for a, core in sorted(sim.cores.items()):
            if a in sim.killed:
                continue
            for b in sorted(core.failed):
                if b in sim.killed or not _joined(sim, a, b):
                    continue
                at = seen[(a, b)] = self.since.get((a, b), sim.now)
                if sim.now - at > HEARD_GRACE_S:
                    out.append(
                        Violation("held-failed", f"{a} holds {b} failed since {at:.3f} though "
                                  f"they reach each other (at {sim.now:.3f})")
                    )  # fmt: skip
        self.since = seen
        return out


def _joined(sim: Simulation, a: str, b: str) -> bool:
    """``a`` and ``b`` have routes to each other (what they send arrives: b is heard)."""
    lost = sim.lost_routes
    return (
        (a, b) not in lost
        and (b, a) not in lost
        and sim.network.route(a, b) is not None
        and sim.network.route(b, a) is not None
    )


def check(
    sim: Simulation,
    sched: Schedule,
    records: list[SinkRecord],
    holders: AppHolders | None = None,
) -> list[Violation]:
    """Check the invariants at the end of a quiet period."""
    out: list[Violation] = []
    now = sim.now
    live = sorted(n for n in sim.cores if n not in sim.killed)
    deploys = [r for _, c, r in sim.replies if isinstance(r, m.DeployReply)]
    if not deploys or not deploys[0].ok:
        err = deploys[0].error if deploys else "no reply"
        return [Violation("deploy", f"the app was not deployed: {err}")]
    status: dict[str, dict[str, Any]] = {}
    for n in live:
        try:
            status[n] = sim.cores[n].status(now)
        except Exception as exc:  # a node that cannot say how it is: that is the finding
            out.append(Violation("status", f"{n}: {type(exc).__name__}: {exc}"))
    replies = [r for _, c, r in sim.replies if c == STATUS_CLIENT and isinstance(r, m.StatusReply)]
    if not replies:
        out.append(Violation("status", "no reply to a status request for every node"))
    elif missing := set(live) - set(replies[-1].nodes):
        out.append(Violation("status", f"no status from {sorted(missing)} via {live[0]}"))
    for n, st in status.items():
        if st.get("failed_nodes"):
            out.append(Violation("membership", f"{n} still holds {st['failed_nodes']} failed"))
    out += check_procedures(sim)
    apps = {n: st["apps"].get(APP) for n, st in status.items()}
    missing_app = sorted(n for n, a in apps.items() if a is None)
    known = {n: a for n, a in apps.items() if a is not None}
    gone = holders is not None and holders.gone_at is not None
    if not known and (gone or _everyone_failed(sched)):
        return out  # the app went with the last node that held it: nothing left to check
    if not known:
        if missing_app:
            out.append(Violation("placement", f"{missing_app} do not know the app"))
        return out
    members = {n: a for n, a in known.items() if a["vertices"]} or known
    # issue 24.1: the nodes that take part in the app hold it (its vertices' nodes, by the
    # view of the nodes that host part of it); the others need not
    taking_part = {x for a in members.values() for x in a["placement"].values()}
    taking_part |= {r for a in members.values() for x in a["replication"].values()
                    for r in x["replicas"]}  # fmt: skip
    if unaware := sorted(set(missing_app) & taking_part):
        out.append(Violation("placement", f"{unaware} take part in the app but do not know it"))
    origins = {a["origin"] for a in known.values()}
    if idle := sorted(set(known) - taking_part - origins):
        out.append(Violation("holding", f"{idle} hold the app but take no part in it"))
    placements = {tuple(sorted(a["placement"].items())) for a in members.values()}
    if len(placements) > 1:
        out.append(Violation("placement", f"nodes disagree: {sorted(placements)}"))
    ref_node = min(members)
    placed: dict[str, str] = known[ref_node]["placement"]
    hosts: dict[str, list[str]] = {}
    for n, a in known.items():
        for v in a["vertices"]:
            hosts.setdefault(v, []).append(n)
    vertices = list(known[ref_node]["chains"] and {v for c in known[ref_node]["chains"] for v in c})
    for v in sorted(vertices):
        where = hosts.get(v, [])
        if len(where) != 1:
            out.append(Violation("hosted-once", f"{v} runs on {where or 'no node'}"))
        if placed.get(v) not in known:
            out.append(Violation("placement", f"{v} placed on {placed.get(v)}, not a live node"))
        elif v not in known[placed[v]]["vertices"]:
            out.append(Violation("placement", f"{v} placed on {placed[v]}, which does not host it"))
    for n, a in known.items():
        if a["parked"]:
            out.append(Violation("parked", f"{n}: {a['parked']}"))
    for chain in known[ref_node]["chains"]:
        for src, dst in itertools.pairwise(chain):
            name = f"{src}->{dst}"
            for end in (src, dst):
                node = placed.get(end)
                if node in known and name not in known[node]["edges"]:
                    out.append(Violation("dangling-edge", f"{name}: no channel on {node} ({end})"))
    out += _events(sim, sched, records, known, status)
    out += _delivered_once(sim, records, known)
    return out


def _delivered_once(
    sim: Simulation, records: list[SinkRecord], known: dict[str, dict[str, Any]]
) -> list[Violation]:
    """Every emitted event delivered (see ``delivered-once`` in the module docstring): a
    stream seen at a sink is whole from 0 up to the newest event it got."""
    if any(sum(a["given_up"].values()) for a in known.values()):
        return []  # a bound or QoS gave events up, counted: gaps are expected there
    if not any(APP in c.apps for c in sim.cores.values()):
        return []
    seen: dict[tuple[str, str, float], set[int]] = {}
    for rec in records:  # over a sink's instances (a restored sink is a new one)
        for (src, born), s in rec.streams.items():
            seen.setdefault((rec.vertex, src, born), set()).update(s.seen)
    out: list[Violation] = []
    for (sink, src, born), got in sorted(seen.items()):
        missing = max(got) + 1 - len(got)
        if missing:
            holes = sorted(set(range(max(got) + 1)) - got)
            out.append(
                Violation(
                    "delivered-once",
                    f"{sink} from {src}@{born:g}: {missing} of 0..{max(got)} never delivered "
                    f"(first {holes[:5]})",
                )
            )
    return out


def repeats(records: list[SinkRecord]) -> int:
    """Events a sink got in two of its instances: the replay to a sink restored after its own
    node's crash or reset repeats what it processed but had not acknowledged (allowed,
    counted: its position is not kept with its effects)."""
    seen: dict[tuple[str, str, float], Counter[int]] = {}
    for rec in records:
        for (src, born), s in rec.streams.items():
            seen.setdefault((rec.vertex, src, born), Counter()).update(s.seen)
    return sum(1 for c in seen.values() for n in c.values() if n > 1)


def _everyone_failed(sched: Schedule) -> bool:
    """Every node was down at one moment of the schedule (restarts at an instant counted
    before failures at it, so a node back at the moment another fails never counts)."""
    down: set[str] = set()
    changes = sorted(
        (c for c in sched.changes if isinstance(c, NodeFailure | NodeRestart)), key=lambda c: c.at
    )
    for _, group in itertools.groupby(changes, key=lambda c: c.at):
        now = list(group)
        down -= {c.node for c in now if isinstance(c, NodeRestart)}
        down |= {c.node for c in now if isinstance(c, NodeFailure)}
        if down >= set(sched.network.nodes):
            return True
    return False


def _events(
    sim: Simulation,
    sched: Schedule,
    records: list[SinkRecord],
    known: dict[str, dict[str, Any]],
    status: dict[str, dict[str, Any]],
) -> list[Violation]:
    out: list[Violation] = []
    failures = any(core.failures or core.rejoins for core in sim.cores.values())
    parked = any(sum(a["given_up"].values()) for a in known.values())
    blamed = failures or parked or sched.faults["crash"] or sched.faults["partition"]
    for rec in records:
        for (src, born), s in sorted(rec.streams.items()):
            what = f"{rec.vertex} from {src}@{born:g}"
            if s.duplicates:
                out.append(Violation("duplicate", f"{what}: {s.duplicates} events twice"))
            if s.reordered:
                out.append(Violation("reorder", f"{what}: {s.reordered} events out of order"))
            if s.missing and not blamed:
                out.append(Violation("lost", f"{what}: {s.missing} missing in {s.first}..{s.last}"))
    declared = sum(1 for _, _, h in sim.happened if h.what == "state_restarted")
    for rec in records:
        if rec.regressions > declared:
            out.append(
                Violation(
                    "state",
                    f"{rec.vertex}: the count went back {rec.regressions} times, "
                    f"{declared} state restarts declared",
                )
            )
        if rec.skips and not blamed:
            out.append(Violation("state", f"{rec.vertex}: {rec.skips} counts skipped"))
    # liveness: the newest instance of each sink follows every source's current stream
    sources: dict[str, tuple[float, int]] = {}
    for a in known.values():
        for v, vs in a["vertices"].items():
            stats = vs.get("stats")
            if vs["kind"] == "source" and isinstance(stats, dict) and stats.get("born") is not None:
                sources[v] = (float(stats["born"]), int(stats["emitted"]))
    newest: dict[str, SinkRecord] = {}
    for rec in records:
        newest[rec.vertex] = rec
    slack = int(sched.settings.rate) + 5  # a second of events may still be on the way
    for sink, rec in sorted(newest.items()):
        for src, (born, emitted) in sorted(sources.items()):
            stream = rec.streams.get((src, born))
            got = -1 if stream is None else stream.last
            if got < emitted - 1 - slack:
                out.append(
                    Violation("stalled", f"{sink} has {src}@{born:g} up to {got} of {emitted}")
                )
    return out
