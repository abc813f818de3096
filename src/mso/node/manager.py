"""The node's management loop (paper §3.5): what the rules see, and what they ask for.

Each monitor period the node describes itself — its own monitor, what its neighbours said in
their heartbeats, the vertices it hosts with their measured rates and traffic, the chains that
touch it with their measured delay and route changes — as a :class:`~mso.management.Snapshot`,
and hands it to the :class:`~mso.management.RuleEngine`. The actions allowed by the engine's
guard are carried out by the same relocation and remap procedures a user triggers. Decisions
stay local: a node only moves the vertices it hosts and only remaps the chains whose head it
holds, so no two nodes act on the same thing.
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Any, Protocol

import msgspec

from mso.errors import MsoError
from mso.management import (
    ChainView,
    NodeView,
    Relocate,
    RuleEngine,
    RuleSettings,
    Snapshot,
    VertexView,
    load_policy,
)
from mso.management.engine import EngineStatus
from mso.model.network import PowerModel
from mso.node.monitor import WINDOW

if TYPE_CHECKING:
    from mso.management import Action
    from mso.node.monitor import Monitor
    from mso.protocol import messages as m
    from mso.protocol.procedures.base import Procedure
    from mso.protocol.state import Apps, AppState


class ManagementStatus(EngineStatus, frozen=True, kw_only=True):
    """The rule engine's status and the loop's own: whether it runs, what it did."""

    enabled: bool
    done: list[str]  # "time action", recent


class ManagedNode(Protocol):
    """What the management loop reads of its node (a view: it changes nothing)."""

    id: str
    capacity: float
    power: PowerModel
    monitor: Monitor
    routes: dict[str, tuple[str, int]]
    apps: Apps
    procedures: dict[int, Procedure]

    @property
    def failed(self) -> set[str]: ...

    @property
    def heard(self) -> dict[str, tuple[float, m.Figures]]: ...

    def route_hops(self) -> dict[str, int]: ...

    def relocation_target(self, dep: AppState, vertex: str, direction: str = "") -> str: ...


class _Rates:
    """Per-vertex rates over the last ``WINDOW`` samples of the instance's cumulative counters:
    a mean over a window, like the monitor's load, so a camera at 0.5 frames/s reads 0.5."""

    def __init__(self, now: float, count: int, bytes_in: int, bytes_out: int) -> None:
        self.samples: deque[tuple[float, int, int, int]] = deque(maxlen=WINDOW + 1)
        self.samples.append((now, count, bytes_in, bytes_out))
        self.rate = self.in_bps = self.out_bps = 0.0

    def update(self, now: float, count: int, bytes_in: int, bytes_out: int) -> None:
        if now <= self.samples[-1][0]:
            return
        self.samples.append((now, count, bytes_in, bytes_out))
        t0, c0, i0, o0 = self.samples[0]
        dt = now - t0
        self.rate, self.in_bps, self.out_bps = (
            (count - c0) / dt,
            (bytes_in - i0) / dt,
            (bytes_out - o0) / dt,
        )


class Manager:
    """Builds snapshots for the rule engine and carries out what it allows."""

    def __init__(
        self,
        core: ManagedNode,
        policy: Any = None,
        settings: RuleSettings | None = None,
        enabled: bool = True,
    ) -> None:
        self.core = core
        self.enabled = enabled
        self.engine = RuleEngine(load_policy(policy, where="node policy"), settings)
        self._rates: dict[tuple[str, str], _Rates] = {}
        # work this node moved to a neighbour recently: its load figure has not caught up yet
        self._sent: list[tuple[float, str, float]] = []  # (until, node, load added)
        self.done: list[str] = []  # actions carried out, most recent last (bounded)

    def app_policy(self, app: str, spec: Any, where: str) -> None:
        """Manage ``app`` by the policy its file names (MsoError if it cannot be loaded)."""
        self.engine.set_app_policy(app, None if spec is None else load_policy(spec, where=where))

    def forget(self, app: str) -> None:
        self.engine.forget(app)
        for key in [k for k in self._rates if k[0] == app]:
            del self._rates[key]

    # -- one evaluation ---------------------------------------------------------------------
    def tick(self, now: float) -> list[Action]:
        """One evaluation: the actions the rules and the guard allow, for the core to carry
        out with the same procedures a user triggers."""
        self._measure(now)
        if not self.enabled or not self._runs_any():
            return []
        snap = self.snapshot(now)
        if not snap.vertices and not snap.chains:
            return []
        return [a for a in self.engine.evaluate(snap) if self._taken(a, now)]

    def _runs_any(self) -> bool:
        """Whether the rules have anything to see here: a running app, not being recovered,
        that this node runs part of (the snapshot's vertices and chains come from those
        alone). Every node holds every app and most run none: the snapshot, with a hop
        count to every node and a pass over every app, was 12% of a 1,000-node second."""
        me = self.core.id
        return any(
            dep.running and dep.recovering is None and (dep.instances or me in dep.placed.values())
            for dep in self.core.apps.engaged_apps()
        )

    def _measure(self, now: float) -> None:
        for dep in self.core.apps.engaged_apps():
            for vid, instance in dep.instances.items():
                count = instance.emitted if instance.kind == "source" else instance.processed
                key = (dep.app.name, vid)
                r = self._rates.get(key)
                if r is None:
                    self._rates[key] = _Rates(now, count, instance.bytes_in, instance.bytes_out)
                else:
                    r.update(now, count, instance.bytes_in, instance.bytes_out)

    def snapshot(self, now: float) -> Snapshot:
        core = self.core
        mon = core.monitor
        nodes = {
            core.id: NodeView(
                core.id,
                core.capacity,
                core.power,
                mon.load,
                mon.drain_w,
                mon.remaining_j,
                mon.lifetime_s,
                now,
                core.route_hops(),
            )
        }
        self._sent = [s for s in self._sent if s[0] > now]
        for n, (at, fig) in core.heard.items():
            if n not in core.failed:
                nodes[n] = NodeView(
                    n,
                    fig.cpu,
                    PowerModel(*fig.power),
                    fig.load + sum(load for _, to, load in self._sent if to == n),
                    fig.drain_w,
                    fig.remaining_j,
                    fig.lifetime_s,
                    at,
                    fig.hops,
                )
        vertices: list[VertexView] = []
        chains: list[ChainView] = []
        app_nodes: dict[str, frozenset[str]] = {}
        routes = core.routes
        for dep in core.apps.values():
            if not dep.running or dep.recovering is not None:
                continue
            vertices += self._vertices(dep, now)
            chains += self._chains(dep)
            if dep.instances:
                hosts = set(dep.placed.values())
                hops = {routes[h][0] for h in hosts if h in routes}
                app_nodes[dep.app.name] = frozenset(hosts | hops)
        busy = frozenset(
            app for p in core.procedures.values() if (app := getattr(p, "app", None)) is not None
        )
        pinned_hosts = frozenset(
            node for dep in core.apps.values() for node in dep.layout.pinned.values()
        )
        return Snapshot(
            now,
            core.id,
            nodes,
            tuple(vertices),
            tuple(chains),
            busy,
            pinned_hosts,
            mon.last_start,
            app_nodes,
        )

    def _vertices(self, dep: AppState, now: float) -> list[VertexView]:
        core, lay = self.core, dep.layout
        out = []
        for vid, instance in sorted(dep.instances.items()):
            chain = next(c.index for c in lay.chains if vid in c.vertices)
            try:
                core.relocation_target(dep, vid)
                movable = True
            except MsoError:
                movable = False
            up = down = None
            state = 0
            if movable:
                up = _target(core, dep, vid, "upstream")
                down = _target(core, dep, vid, "downstream")
                state = instance.state_size  # measured by the executor, off the control plane
                movable = state >= 0
            r = self._rates.get((dep.app.name, vid))
            moved = dep.moved.get(vid)
            out.append(
                VertexView(
                    dep.app.name,
                    vid,
                    core.id,
                    chain,
                    float(dep.app.vertices[vid].cost),
                    r.rate if r else 0.0,
                    r.in_bps if r else 0.0,
                    r.out_bps if r else 0.0,
                    state,
                    up,
                    down,
                    movable,
                    moved[0] if moved else None,
                    moved[1] if moved else None,
                    vid in lay.pinned,
                )
            )
        return out

    def _chains(self, dep: AppState) -> list[ChainView]:
        core = self.core
        out: list[ChainView] = []
        if core.id not in dep.placed.values():  # (every node holds every app: most run none
            return out  # of it, and a chain scan per app per tick was 4% at 1,000 nodes)
        for c in dep.layout.chains:
            nodes = tuple(dep.placed[v] for v in c.vertices)
            if core.id not in nodes:
                continue
            coordinator = nodes[0] == core.id
            if coordinator and c.index in dep.chain_delay:
                delay: float | None = dep.chain_delay[c.index][0]
            else:
                delay = dep.delays.get(c.index)
            out.append(
                ChainView(
                    dep.app.name,
                    c.index,
                    c.vertices,
                    nodes,
                    delay,
                    dep.app.slo_ms,
                    dep.route_changed.get(c.index),
                    coordinator,
                    dep.placed_at.get(c.index),
                )
            )
        return out

    def _taken(self, action: Action, now: float) -> bool:
        """Whether ``action`` is still to be taken (its app runs and is not being recovered);
        if so, what it will change is noted: work sent to a neighbour, the log of actions."""
        core = self.core
        dep = core.apps.get(action.app)
        if dep is None or not dep.running or dep.recovering is not None:
            return False
        if isinstance(action, Relocate):
            r = self._rates.get((action.app, action.vertex))
            beat = core.heard.get(action.target)
            if r is not None and beat is not None:
                added = dep.app.vertices[action.vertex].cost * r.rate / 1e3 / beat[1].cpu
                self._sent.append((now + WINDOW + 1, action.target, added))
        self.done.append(f"{now:.1f} {action}")
        del self.done[:-50]
        return True

    def asked(self, action: Action) -> str:
        """Who asks for ``action``, in words: which rule, on this node, and why."""
        rule = self.engine.rule_of.get(action.key, "")
        if rule.startswith("policy "):
            who = f"the {rule.removeprefix('policy ')} policy on {self.core.id}"
        else:
            who = f"the {rule or 'management'} rule on {self.core.id}"
        return f"{who}: {action.reason}" if action.reason else who

    def status(self) -> ManagementStatus:
        """The engine's record with the loop's own fields (the wire shows them side by side)."""
        engine = msgspec.structs.asdict(self.engine.status())
        return ManagementStatus(**engine, enabled=self.enabled, done=list(self.done))


def _target(core: ManagedNode, dep: AppState, vid: str, direction: str) -> str | None:
    """One hop of a relocation (§3.4.1): the neighbour on the way to where an upstream or
    downstream relocation would take ``vid``. Moving a hop at a time keeps every move cheap to
    weigh (a neighbour's figures are known from its heartbeats) and easy to undo."""
    try:
        target = core.relocation_target(dep, vid, direction)
    except MsoError:
        return None
    route = core.routes.get(target)
    hop = route[0] if route is not None else None
    return hop if hop is not None and hop not in core.failed else None
