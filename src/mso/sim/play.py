"""Play a scenario in virtual time: the simulator's side of the shared timeline, and the report
``mso simulate`` prints.

:func:`drive` advances a :class:`~mso.sim.runner.Simulation` and a
:class:`~mso.scenario.timeline.Timeline` together (the emulator plays the same timeline on its
asyncio clock), so links, failures, restarts, partitions, loss and mobility mean the same thing
in both. :func:`simulate` deploys an app, drives the scenario and sums up what happened from the
nodes' own status (the figures ``mso status`` shows).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from mso.errors import MsoError
from mso.model.appfile import loads_app
from mso.node.monitor import MonitorStatus
from mso.protocol import messages as m
from mso.scenario.format import NodeFailure, Scenario
from mso.scenario.timeline import Action, Crash, Restart, Timeline
from mso.sim.runner import Simulation

Call = tuple[float, Callable[[Simulation], None]]
MAX_STEPS = 10_000_000  # bound on driver turns (each turn moves virtual time or plays a change)


def apply(sim: Simulation, actions: list[Action], convergence_s: float = 0.0) -> None:
    """Carry out a timeline's actions on the simulation. A node that fails and restarts at
    one instant restarts in place: the timeline has already put its links back, and a
    fail-stop's removing them would leave the new process cut off for good (seed 6086)."""
    for i, action in enumerate(actions):
        if isinstance(action, Crash):
            back = any(isinstance(a, Restart) and a.node == action.node for a in actions[i:])
            if action.node not in sim.killed and back:
                sim.crash(action.node)
            elif action.node not in sim.killed:
                sim.kill(action.node, convergence_s)
        elif isinstance(action, Restart):
            if action.node in sim.killed:
                sim.revive(action.node)
        else:
            sim.links_changed(convergence_s)


def drive(
    sim: Simulation,
    timeline: Timeline,
    until: float,
    *,
    convergence_s: float = 0.0,
    calls: list[Call] | None = None,
) -> None:
    """Run ``sim`` to virtual time ``until``, playing the timeline's changes at their times and
    each of ``calls`` (``(time, fn(sim))``, e.g. a client request or a sample) at its own."""
    pending = sorted(calls or [], key=lambda c: c[0])
    i = 0
    for _ in range(MAX_STEPS):
        due = timeline.next_at()
        t = until if due is None else min(due, until)
        if i < len(pending):
            t = min(t, pending[i][0])
        t = max(t, sim.now)
        sim.run_until(t)
        if due is not None and due <= t:
            apply(sim, timeline.advance(t), convergence_s)
        while i < len(pending) and pending[i][0] <= t:
            pending[i][1](sim)
            i += 1
        if t >= until and (due is None or due > until) and i >= len(pending):
            return
    raise MsoError(f"the simulation did not reach t={until:g} s in {MAX_STEPS} steps")


def simulate(
    scenario: Scenario,
    app_doc: str,
    app_file: str | Path,
    *,
    seed: int = 0,
    duration: float = 30.0,
    convergence_s: float = 0.0,
    via: str | None = None,
    manage: bool = True,
    policy: Any = None,
    series: bool = False,
) -> dict[str, Any]:
    """Deploy the app at t=0 on ``scenario`` in virtual time, play the scenario's timeline for
    ``duration`` seconds and report events, reconfigurations, energy and failures. ``policy``
    is the nodes' management policy (an app's own ``policy`` still wins); ``series`` adds, once
    a simulated second, the energy spent so far over all nodes and each chain's delay as its
    tail measures it (what a sweep plots)."""
    if duration <= 0:
        raise MsoError(f"--duration: expected a number of seconds > 0, got {duration:g}")
    app = loads_app(app_doc, file=str(app_file))  # errors name the file and line, exit 2
    origin = via or next(iter(scenario.network.nodes))
    if origin not in scenario.network.nodes:
        known = ", ".join(scenario.network.nodes)
        raise MsoError(f"--via: unknown node {origin!r} (nodes: {known})")
    sim = Simulation(scenario.network, seed=seed, manage=manage, policy=policy)
    timeline = Timeline(scenario, network=sim.network)
    sim.request(origin, m.DeployRequest(app_doc, str(app_file)))
    moves: list[tuple[float, str, str, str]] = []  # (time, vertex, from, to)
    last: dict[str, str] = {}

    def sample(s: Simulation) -> None:
        """Note every vertex whose node changed since the last sample (moves of any kind);
        stop a robot whose battery is empty (fail-stop), as the emulator's node does."""
        for n in sorted(s.cores):
            if n not in s.killed and s.cores[n].monitor.empty:
                failed = timeline.apply(NodeFailure(s.now, n), why="battery empty: fail-stop")
                apply(s, failed, convergence_s)
        placed = _placement(s, app.name)
        for v, n in placed.items():
            if v in last and last[v] != n:
                moves.append((s.now, v, last[v], n))
        last.update(placed)

    step = 0.05
    samples: list[Call] = [(k * step, sample) for k in range(1, int(duration / step) + 1)]
    seen: dict[str, list[float]] = {"t": [], "energy_j": [], "delay_ms": []}
    if series:
        samples += [(float(k), lambda s: _sample_series(s, seen)) for k in range(int(duration) + 1)]
        samples.sort(key=lambda c: c[0])
    drive(sim, timeline, duration, convergence_s=convergence_s, calls=samples)
    report = _report(sim, timeline, scenario, app.name, seed, duration, convergence_s, moves)
    if series:
        report["series"] = seen
    return report


def _sample_series(sim: Simulation, seen: dict[str, list[float]]) -> None:
    """The energy spent so far over every node, and the chains' delays measured now."""
    seen["t"].append(round(sim.now, 6))
    seen["energy_j"].append(round(sum(c.monitor.energy_j for c in sim.cores.values()), 6))
    for n, core in sim.cores.items():
        if n not in sim.killed:
            for dep in core.apps.values():
                seen["delay_ms"] += [round(ms, 3) for ms in dep.delays.values()]


def _placement(sim: Simulation, app: str) -> dict[str, str]:
    for n in sorted(sim.cores):
        dep = sim.cores[n].apps.get(app)
        if n not in sim.killed and dep is not None and dep.running:
            return dict(dep.placed)
    return {}


def _failures(sim: Simulation, rejoins: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One record per failure: the first declaration of a node, then none until it rejoins
    (every node records when it learned of a failure, and keyed by that time one failure of
    a 1,000-node run showed as 42, one per gossip round)."""
    back: dict[str, list[float]] = {}
    for r in rejoins:
        back.setdefault(r["node"], []).append(r["at"])
    records = sorted(
        (dict(f) for core in sim.cores.values() for f in core.failures), key=lambda f: f["at"]
    )
    kept: dict[str, float] = {}  # node -> when its current failure was first declared
    out = []
    for f in records:
        node, at = f["node"], f["at"]
        since = kept.get(node)
        if since is None or any(since < t <= at for t in back.get(node, [])):
            kept[node] = at
            out.append(f)
    return out


def _numbered(sim: Simulation, app: str) -> tuple[dict[str, int], dict[str, int]]:
    """Per edge: the events numbered on it (each number once, over every node and every
    process a restarted node had), and the numbers below the highest never used (skipped
    by a restart). A restarted source numbers on from the bound its old process saved; the
    highest number is not what it emitted (the convoy's laser: 1,145 for 170 events)."""
    runs: dict[str, list[tuple[int, int]]] = {}
    for core in [*sim.cores.values(), *(c for old in sim.retired.values() for c in old)]:
        dep = core.apps.get(app)
        if dep is None:
            continue
        for i, ch in dep.out.items():
            e = dep.app.edges[i]
            runs.setdefault(f"{e.src}->{e.dst}", []).append((ch.origin, ch.next_seq))
    numbered, skipped = {}, {}
    for edge, spans in runs.items():
        count, reached = 0, 0
        for first, end in sorted(spans):
            count += max(0, end - max(first, reached))
            reached = max(reached, end)
        numbered[edge], skipped[edge] = count, reached - count
    return numbered, skipped


def _report(
    sim: Simulation,
    timeline: Timeline,
    scenario: Scenario,
    app: str,
    seed: int,
    duration: float,
    convergence_s: float,
    moves: list[tuple[float, str, str, str]],
) -> dict[str, Any]:
    live = [n for n in sim.cores if n not in sim.killed]
    status = {n: sim.cores[n].status(sim.now) for n in live}
    deploy = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    reply = deploy[0] if deploy else None
    sent, skipped = _numbered(sim, app)
    delivered: dict[str, int] = {}
    dropped: dict[str, int] = {}  # edge -> events its bound and QoS gave up (counted)
    recoveries: dict[tuple[Any, ...], dict[str, Any]] = {}
    vertices: dict[str, dict[str, Any]] = {}
    for n, st in status.items():
        a = st["apps"].get(app)
        if a is None:
            continue
        for e, c in a["edges"].items():
            delivered[e] = max(delivered.get(e, 0), c["delivered"])
        for e, k in a["given_up"].items():
            dropped[e] = max(dropped.get(e, 0), k)
        for rec in a["recoveries"]:
            recoveries[(rec.get("at"), tuple(rec.get("failed", ())))] = rec
        for v, vs in a["vertices"].items():
            vertices[v] = {"node": n, "kind": vs["kind"], "processed": vs["processed"]}
            vertices[v]["emitted"] = vs["emitted"]
    sources = sorted(v for v, d in vertices.items() if d["kind"] == "source")
    sinks = sorted(v for v, d in vertices.items() if d["kind"] == "sink")
    edges = [e.split("->") for e in sent.keys() | delivered.keys()]
    events = {
        "emitted": {  # what entered the network: numbered on the source's edges
            s: max((sent[e] for e in sent if e.split("->")[0] == s), default=0)
            for s in sources
        },
        # numbers never used: a source's restarted daemon numbers on from the bound its old
        # process saved (events that process numbered are in ``emitted``, even if lost)
        "skipped": {
            s: k for s in sources
            if (k := max((skipped[e] for e in skipped if e.split("->")[0] == s), default=0))
        },
        "delivered": {k: sum(delivered.get(f"{a}->{b}", 0) for a, b in edges if b == k)
        for k in sinks},
        "given_up": sum(dropped.values()),
        "frames_lost_on_links": sim.lost,
    }  # fmt: skip
    rejoins: dict[tuple[str, int], dict[str, Any]] = {}
    decisions: list[str] = []
    for n in sorted(sim.cores):
        core = sim.cores[n]
        for r in core.rejoins:
            rejoins.setdefault((r["node"], r["incarnation"]), dict(r))
        if n in status:
            decisions += [f"{n}: {d}" for d in status[n]["management"]["done"]]
    failed = _failures(sim, list(rejoins.values()))
    energy = {}
    for n in sim.cores:
        mon = (  # a killed node answers no status: its monitor is read in place
            msgspec.convert(status[n]["monitor"], MonitorStatus)
            if n in status
            else sim.cores[n].monitor.status()
        )
        energy[n] = {
            "alive": n in status,
            "incarnation": sim.cores[n].incarnation,
            "energy_j": mon.energy_j,
            "drain_w": mon.drain_w,
            "battery_fraction": mon.battery_fraction,
            "bytes_sent": sim.bytes[n][0],
            "bytes_received": sim.bytes[n][1],
            "battery_empty": sim.cores[n].monitor.empty,
        }
    requests = [r for _, _, r in sim.replies if isinstance(r, m.RelocateReply | m.RemapReply)]
    episodes = _episodes(sim, timeline, moves, failed)
    return {
        "scenario": scenario.name,
        "app": app,
        "seed": seed,
        "duration_s": duration,
        "convergence_s": convergence_s,
        "deploy": {
            "ok": bool(reply and reply.ok),
            "elapsed_ms": reply.elapsed_ms if reply else None,
            "error": (reply.error if reply else "no reply from the deploying node"),
            "placement": dict(reply.placement) if reply else {},
        },
        "events": events,
        "reconfigurations": {
            "moves": [{"at": round(t, 3), "vertex": v, "from": a, "to": b} for t, v, a, b in moves],
            "management": decisions,
            "requests": len(requests),
            "recoveries": sorted(recoveries.values(), key=lambda r: r.get("at") or 0.0),
            "rejoins": sorted(rejoins.values(), key=lambda r: r["at"]),
            "episodes": episodes,
        },
        "failures": failed,
        "messages": sim.census.messages_json(),
        "energy": energy,
        "placement": _placement(sim, app),
        "timeline": [[round(t, 3), what] for t, what in timeline.played],
        "alive": live,
    }


def _episodes(
    sim: Simulation,
    timeline: Timeline,
    moves: list[tuple[float, str, str, str]],
    failures: list[dict[str, Any]],
) -> list[dict[str, Any]]:
    """Each burst of control messages (the deployment, a move, a remap, a failure's detection
    and recovery, a rejoin: :mod:`mso.sim.census`) with what it cost and what set it off: the
    scenario's changes since the burst before, the vertex moves and failures seen during it.
    Each failure record gets its episode's ``control_messages`` and ``nodes_involved`` too."""
    out: list[dict[str, Any]] = []
    before = -1.0
    bursts = sim.census.episodes(cuts=[t for t, _ in timeline.played])
    for i, ep in enumerate(bursts):
        # a move is sampled up to one sample period after its messages; a change or a failure
        # belongs to the burst it sets off, which may begin a detection window later
        until = bursts[i + 1].since if i + 1 < len(bursts) else float("inf")
        record = ep.to_json()
        record["changes"] = [w for t, w in timeline.played if before < t <= ep.until]
        record["moves"] = [
            {"at": round(t, 3), "vertex": v, "from": a, "to": b}
            for t, v, a, b in moves
            if ep.since <= t < until
        ]
        record["failures"] = sorted({f["node"] for f in failures if ep.since <= f["at"] < until})
        for f in failures:
            if ep.since <= f["at"] < until:
                f["control_messages"] = ep.control_messages
                f["nodes_involved"] = len(ep.nodes_involved)
        out.append(record)
        before = ep.until
    return out


__all__ = ["Call", "apply", "drive", "simulate"]
