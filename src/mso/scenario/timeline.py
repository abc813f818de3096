"""One player for a scenario's timeline: scripted changes and mobility, sans-IO.

The emulator (an asyncio loop, real seconds) and the simulator (virtual seconds) both drive a
:class:`Timeline`: they ask when the next thing is due (``next_at``), wait until then their own
way, and call ``advance(t)``, which updates the link graph (the scenario's ``Network``) and
returns what the driver must carry out: the links that changed (push neighbours, routes after
the convergence delay), the nodes to kill and the nodes to restart. So a scenario means the
same in both, and a seeded fault schedule (``mso.sim.faults``) is just more changes.

The links in force are derived, never patched: the *radio* links (the scenario's, changed by
``up``/``down``/``loss`` and recomputed from positions at every mobility step) minus those of
failed nodes minus those a partition cuts. A restart or a heal therefore brings back exactly
the links the radio gives at that moment.

An operator (the emulator's console, ``mso emulator``) changes the same timeline now, through
:meth:`Timeline.apply`: a fail or restart, a link ``Cut`` (held whatever the radio does, until
healed) or a ``Move`` of a node (held: the node's mobility no longer moves it). A node that dies
outside the script (killed by hand, its battery empty) is a ``NodeFailure`` applied the same way,
so a later restart or heal never brings back links to a node that is gone.
"""

from __future__ import annotations

import heapq
import itertools
import math
from dataclasses import dataclass, replace

from mso.model.mobility import Trace, Tracks, tracks_for
from mso.model.network import LinkSpec, Network
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


@dataclass(frozen=True)
class LinksChanged:
    """Links that appeared or changed attributes (``added``) and links that went (``removed``);
    the network already shows them."""

    at: float
    added: tuple[LinkSpec, ...]
    removed: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class Crash:
    """Fail-stop ``node`` now (its links are already gone from the network)."""

    at: float
    node: str


@dataclass(frozen=True)
class Restart:
    """Start ``node`` again as a new process (its links are already back)."""

    at: float
    node: str


Action = LinksChanged | Crash | Restart


@dataclass(frozen=True)
class Cut:
    """An operator cuts the link ``a``-``b`` (``cut``) or heals it: a cut holds through mobility
    and scripted ``up`` changes until it is healed."""

    at: float
    a: str
    b: str
    cut: bool = True


@dataclass(frozen=True)
class Move:
    """An operator puts ``node`` at ``pos`` (metres): links follow if the scenario derives them
    from positions (``radio_range``); the node stays there (its mobility no longer moves it)."""

    at: float
    node: str
    pos: tuple[float, float]


OperatorChange = Change | Cut | Move


def _key(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


def _nodes_of(change: object) -> tuple[str, ...]:
    """The nodes a change names (checked before it is applied)."""
    if isinstance(change, NodeFailure | NodeRestart | Move):
        return (change.node,)
    if isinstance(change, Cut | LinkChange):
        return (change.a, change.b)
    return ()


class Timeline:
    """Plays a scenario's changes (and mobility) against its network, in time order."""

    def __init__(
        self,
        scenario: Scenario,
        *,
        changes: bool = True,
        mobility: bool = True,
        network: Network | None = None,
    ) -> None:
        self.scenario = scenario
        self.network = network or scenario.network
        self.radio: dict[tuple[str, str], LinkSpec] = {
            _key(a, b): spec for (a, b), spec in self.network.links.items()
        }
        self.template = scenario.link_template or LinkSpec("", "")
        self.dead: set[str] = set()
        self.groups: tuple[frozenset[str], ...] | None = None
        self.cuts: set[tuple[str, str]] = set()  # links an operator cut, until healed
        self.moved: dict[str, tuple[float, float]] = {}  # nodes an operator put somewhere
        self.loss: dict[tuple[str, str], float] = {}  # per-link loss set by the script
        self.played: list[tuple[float, str]] = []  # (time, what): a log of what was applied
        self._heap: list[tuple[float, int, Change]] = []
        self._n = itertools.count()
        for c in scenario.changes if changes else []:
            self.add(c)
        self._tracks: Tracks | None = None
        self._moves_until: float | None = None  # a trace ends; random waypoint does not
        self._next_move: float | None = None
        sc = scenario
        if mobility and sc.mobility is not None and sc.radio_range is not None:
            starts = {n: s.pos for n, s in self.network.nodes.items() if s.pos is not None}
            self._tracks = tracks_for(sc.mobility, starts)
            if isinstance(sc.mobility, Trace):
                self._moves_until = sc.mobility.end
            self._next_move = sc.mobility_step_s
        self.positions: dict[str, tuple[float, float]] = {}

    def apply(self, change: OperatorChange, why: str = "") -> list[Action]:
        """Apply one change now, at ``change.at`` (an operator's command, a node found dead,
        ``why`` noted in :attr:`played`): what the driver must carry out, as :meth:`advance`
        returns it."""
        played = len(self.played)
        actions = self._apply_now(change)
        if why and len(self.played) > played:
            at, what = self.played[-1]
            self.played[-1] = (at, f"{what} ({why})")
        return actions

    def _apply_now(self, change: OperatorChange) -> list[Action]:
        nodes = self.network.nodes
        for node in _nodes_of(change):
            if node not in nodes:
                raise ValueError(f"unknown node {node!r} (nodes: {', '.join(nodes)})")
        if isinstance(change, Cut):
            k = _key(change.a, change.b)
            if change.cut:
                self.cuts.add(k)
            else:
                self.cuts.discard(k)
            return self._sync(change.at, f"{'cut' if change.cut else 'heal'} {k[0]}-{k[1]}")
        if isinstance(change, Move):
            self.moved[change.node] = change.pos
            self.positions = {**self.positions, change.node: change.pos}
            if self.scenario.radio_range is not None:
                self._relink(self._all_positions(), self.scenario.radio_range)
            return self._sync(change.at, f"move {change.node}")
        return self._apply(change.at, change)

    def _all_positions(self) -> dict[str, tuple[float, float]]:
        """Every node's position now: the scenario's, moved by mobility, then by hand."""
        static = {n: s.pos for n, s in self.network.nodes.items() if s.pos is not None}
        return static | self.positions | self.moved

    def add(self, change: Change) -> None:
        """Schedule one more change (a fault schedule adds its own)."""
        heapq.heappush(self._heap, (change.at, next(self._n), change))

    def next_at(self) -> float | None:
        """When the next change or mobility step is due; None once nothing is left."""
        ats = [self._heap[0][0]] if self._heap else []
        if self._next_move is not None:
            ats.append(self._next_move)
        return min(ats) if ats else None

    def advance(self, t: float) -> list[Action]:
        """Apply everything due by ``t``, in time order (changes before a mobility step at the
        same time); return what the driver must do, in the order it must do it."""
        out: list[Action] = []
        for _ in range(1_000_000):  # bounded: each turn consumes one change or one step
            due_change = self._heap[0][0] if self._heap else None
            move = self._next_move
            if due_change is not None and due_change <= t and (move is None or due_change <= move):
                at, _, change = heapq.heappop(self._heap)
                out += self._apply(at, change)
            elif move is not None and move <= t and self._tracks is not None:
                assert self.scenario.radio_range is not None
                self.positions = self._tracks.positions(move) | self.moved
                self._relink(self.positions, self.scenario.radio_range)
                self._next_move = move + self.scenario.mobility_step_s
                if self._moves_until is not None and move >= self._moves_until:
                    self._next_move = None  # the trace is over: every node stays put
                out += self._sync(move, "mobility")
            else:
                break
        return out

    def _apply(self, at: float, change: Change) -> list[Action]:
        if isinstance(change, NodeFailure):
            if change.node in self.dead:
                return []
            self.dead.add(change.node)
            return [Crash(at, change.node), *self._sync(at, f"fail {change.node}")]
        if isinstance(change, NodeRestart):
            if change.node not in self.dead:
                return []
            self.dead.discard(change.node)
            return [*self._sync(at, f"restart {change.node}"), Restart(at, change.node)]
        if isinstance(change, Partition):
            self.groups = change.groups
            what = " | ".join(",".join(sorted(g)) for g in change.groups)
            return self._sync(at, f"partition {what}")
        if isinstance(change, Heal):
            self.groups = None
            return self._sync(at, "heal")
        if isinstance(change, LossChange):
            if change.ends is None:  # every link's, a link down now too: one that came
                # back up after the loss was lifted kept it (fault seed 74864: 26% loss on
                # a link all through the quiet phase)
                self.template = replace(self.template, loss=change.loss)
                for k in {*self.radio, *self.loss}:
                    self.loss[k] = change.loss
            else:
                self.loss[_key(*change.ends)] = change.loss
            self.radio = {k: self._with_loss(k, s) for k, s in self.radio.items()}
            return self._sync(at, f"loss {change.loss:g} {change.ends or 'all'}")
        assert isinstance(change, LinkChange)
        k = _key(change.a, change.b)
        if change.up:
            self.radio[k] = self._with_loss(k, change.link or LinkSpec(*k))
        else:
            self.radio.pop(k, None)
        return self._sync(at, f"{'up' if change.up else 'down'} {change.a}-{change.b}")

    def _with_loss(self, k: tuple[str, str], spec: LinkSpec) -> LinkSpec:
        loss = self.loss.get(k)
        return spec if loss is None or loss == spec.loss else replace(spec, loss=loss)

    def _relink(self, positions: dict[str, tuple[float, float]], radio_range: float) -> None:
        radio: dict[tuple[str, str], LinkSpec] = {}
        model = self.scenario.propagation
        for a, b in self.network.pairs_within(positions, radio_range):  # O(N x degree)
            k = _key(a, b)
            if model is not None:  # the link's loss and delay follow its length
                shaped = model.link(a, b, math.dist(positions[a], positions[b]), self.template)
                if shaped is not None:
                    radio[k] = self._with_loss(k, shaped)
                continue
            old = self.radio.get(k)
            spec = old or LinkSpec(
                a, b, self.template.bandwidth_mbps, self.template.delay_ms, self.template.loss
            )
            radio[k] = self._with_loss(k, spec)
        self.radio = radio

    def wanted(self) -> dict[tuple[str, str], LinkSpec]:
        """The links in force: radio links between live nodes on one side of any partition."""
        side: dict[str, int] = {}
        if self.groups is not None:
            for i, g in enumerate(self.groups):
                side.update(dict.fromkeys(g, i))
        rest = len(self.groups or ())
        return {
            k: spec
            for k, spec in self.radio.items()
            if k not in self.cuts
            and k[0] not in self.dead
            and k[1] not in self.dead
            and side.get(k[0], rest) == side.get(k[1], rest)
        }

    def _sync(self, at: float, what: str) -> list[Action]:
        """Make the network show the wanted links; report the difference if any."""
        want = self.wanted()
        have = {_key(a, b): spec for (a, b), spec in self.network.links.items()}
        removed = tuple(sorted(k for k in have if k not in want))
        added = tuple(spec for k, spec in sorted(want.items()) if have.get(k) != spec)
        for a, b in removed:
            self.network.remove_link(a, b)
        for spec in added:
            self.network.add_link(spec)
        if what != "mobility" or removed or added:  # a step that changes nothing is no news
            self.played.append((at, what))
        if not removed and not added:
            return []
        return [LinksChanged(at, added, removed)]
