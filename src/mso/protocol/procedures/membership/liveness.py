"""Neighbour liveness: heartbeats in, the silent out (fail-stop detection, paper §3.4). Sans-IO.

Every node sends a heartbeat to each current neighbour every ``period_s`` and notes when it
last heard from each. It *watches* its neighbours: a watched node silent for ``dead_after_s``
is suspected, and membership asks a few others before declaring it
(:class:`mso.protocol.procedures.membership.Suspicion`). The silence clock runs from the last
time the node was heard (or from when it became a neighbour), whatever the routing view does
meanwhile: a neighbour whose routes are withdrawn stays watched while it is out of reach, so a
withdrawal never restarts the clock (babeld withdrawing a dead relay's routes once made
detection take 4.2 s instead of 0.5 s), and a view that keeps a dead node's routes does not
keep it alive either. A watched node that moves out of this node's range but stays reachable
through others is left to its new neighbours to watch. A node out of reach that nobody has
declared failed is only *unreachable* (``gone``): held with its incarnation, its instances
presumed running.

Heartbeats also carry the sender's monitored figures; the table of what neighbours last said
(``heard``) is what the management rules weigh a move toward a neighbour with.

It also keeps, per neighbour, the last ``GAP_SAMPLES`` heartbeat inter-arrival times (bounded),
shown in status under ``liveness``: how close a neighbour came to being declared failed is what
tells whether ``dead_after_s`` can be lowered, and whether vertex code delays the control plane.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Collection
from dataclasses import dataclass, field

import msgspec

from mso.protocol import messages as m

HEARTBEAT_S = 0.1
DEAD_AFTER_S = 0.5
GAP_SAMPLES = 2048  # heartbeat inter-arrivals kept per neighbour (about 200 s at 0.1 s)


def check_timing(heartbeat_s: float, dead_after_s: float) -> str | None:
    """Why a heartbeat period and failure timeout cannot work together (None if they can)."""
    for name, v in (("heartbeat", heartbeat_s), ("dead-after", dead_after_s)):
        if not math.isfinite(v) or v <= 0:
            return f"--{name}: expected a finite number of seconds > 0, got {v:g}"
    if dead_after_s <= heartbeat_s:
        return (
            f"--dead-after ({dead_after_s:g} s) must be longer than --heartbeat "
            f"({heartbeat_s:g} s): a live neighbour would be declared failed between beats"
        )
    return None


class InterArrival(msgspec.Struct, frozen=True, kw_only=True):
    """One neighbour's heartbeat inter-arrival figures (ms): how close it came to the window."""

    n: int
    p50_ms: float
    p99_ms: float
    max_ms: float  # since it became a neighbour
    recent_max_ms: float


class LivenessStatus(msgspec.Struct, frozen=True, kw_only=True):
    """The detector's settings and what it measured, shown under ``liveness`` in status."""

    heartbeat_s: float
    dead_after_s: float
    inter_arrival: dict[str, InterArrival]


@dataclass
class Gaps:
    """One neighbour's recent heartbeat inter-arrival times (s), bounded; and the largest."""

    last: float | None = None
    # the last GAP_SAMPLES gaps, in no order once full (a ring: ``count`` says where the
    # next goes); raw doubles, not a float object kept per beat per neighbour
    recent: array[float] = field(default_factory=lambda: array("d"))
    count: int = 0
    max_s: float = 0.0

    def summary(self) -> InterArrival:
        s = sorted(self.recent)
        return InterArrival(
            n=self.count,
            p50_ms=round(_pct(s, 50) * 1e3, 3),
            p99_ms=round(_pct(s, 99) * 1e3, 3),
            max_ms=round(self.max_s * 1e3, 3),
            recent_max_ms=round((s[-1] if s else 0.0) * 1e3, 3),
        )


def _pct(s: list[float], q: float) -> float:
    """Nearest-rank percentile of a sorted list (0 when empty)."""
    if not s:
        return 0.0
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]


@dataclass
class Liveness:
    period_s: float = HEARTBEAT_S
    dead_after_s: float = DEAD_AFTER_S
    neighbours: dict[str, float] = field(default_factory=dict)  # neighbour -> since
    # nodes whose silence this node judges: its neighbours, and those of its former
    # neighbours now out of reach (node -> since it was first watched)
    watched: dict[str, float] = field(default_factory=dict)
    last_heard: dict[str, float] = field(default_factory=dict)
    # each neighbour's figures as its last beat that carried them said (and when)
    heard: dict[str, tuple[float, m.Figures]] = field(default_factory=dict)
    # who is reachable: the nodes of the routing table last given (the core's, which it replaces
    # and never changes: kept, not copied -- an N-entry set per node was 32 KB of each node at
    # 1,000 nodes) but ``_unreached`` (failed then, or forgotten since), and ``_rejoined``
    _reach: Collection[str] = field(default_factory=frozenset)
    _unreached: set[str] = field(default_factory=set)
    _rejoined: set[str] = field(default_factory=set)
    gone: dict[str, float] = field(default_factory=dict)  # unreachable node -> since
    gaps: dict[str, Gaps] = field(default_factory=dict)  # neighbour -> heartbeat inter-arrivals
    # the neighbours whose last beat said they run an instance: whether this node's side of a
    # healed partition runs something (a node cut off resets when it hears one of them)
    busy: set[str] = field(default_factory=set)

    def reaches(self, node: str) -> bool:
        """Whether ``node`` was reachable in the routing view last given (and not failed)."""
        return node in self._rejoined or (node in self._reach and node not in self._unreached)

    def set_routes(
        self,
        now: float,
        reachable: Collection[str],
        neighbours: set[str],
        failed: Collection[str] = frozenset(),
    ) -> None:
        """The routing view changed: who is a neighbour, who is reachable at all (the nodes of
        ``reachable`` that are not ``failed``; kept as given, so a new collection each time). A
        watched node that became unreachable stays watched (its silence clock runs on); one
        still reachable through others is no longer this node's to watch."""
        unreached = {n for n in failed if n in reachable}
        for n in (*self._reach, *self._rejoined):
            if self.reaches(n) and (n not in reachable or n in unreached):
                self.gone.setdefault(n, now)
        for n in reachable:
            if n in unreached:
                continue
            if self.gone.pop(n, None) is not None and n in self.watched:
                # back in reach: silent only from now on, as its beats could not come before
                # (held silent since it left, it was suspected the instant its route came
                # back, before its first beat crossed a 100 ms link: both ends of a healed
                # pair declared each other and one reset)
                self.watched[n] = now
        self._reach, self._unreached, self._rejoined = reachable, unreached, set()
        self.set_neighbours(now, neighbours)
        for n in list(self.watched):
            if n not in neighbours and n in reachable and n not in unreached:
                del self.watched[n]

    def set_neighbours(self, now: float, neighbours: set[str]) -> None:
        for n in list(self.neighbours):
            if n not in neighbours:
                del self.neighbours[n]
                self.gaps.pop(n, None)  # a gap across a lost link is not a late beat
                self.busy.discard(n)
        for n in neighbours:
            self.neighbours.setdefault(n, now)
            self.watched.setdefault(n, now)

    def heard_from(self, node: str, now: float, beat: m.Heartbeat | None = None) -> None:
        self.last_heard[node] = now
        if beat is not None:
            if beat.figures is not None:
                self.heard[node] = (now, beat.figures)
            if beat.hosting:
                self.busy.add(node)
            else:
                self.busy.discard(node)
            gaps = self.gaps.get(node)  # (not setdefault: a Gaps made and dropped per beat)
            if gaps is None:
                gaps = self.gaps[node] = Gaps()
            if gaps.last is None:
                gaps.last = now
            else:  # a gap, noted here (every beat from a neighbour comes here: no call)
                gap = now - gaps.last
                if gaps.count < GAP_SAMPLES:
                    gaps.recent.append(gap)
                else:
                    gaps.recent[gaps.count % GAP_SAMPLES] = gap
                gaps.count += 1
                if gap > gaps.max_s:
                    gaps.max_s = gap
                gaps.last = now

    def silent(self, now: float, dead: set[str]) -> list[str]:
        """Watched nodes silent for longer than ``dead_after_s`` (sorted, deterministic):
        suspected. The clock runs from the last beat, or from when the node was first
        watched; losing a route does not restart it, a route back after an outage does."""
        heard, window = self.last_heard, self.dead_after_s  # (every beat: no sort, no call
        # per watched node but the look-up; the few found are sorted)
        out = []
        for n, since in self.watched.items():
            last = heard.get(n, since)
            if now - (last if last > since else since) > window and n not in dead:
                out.append(n)
        if len(out) > 1:
            out.sort()
        return out

    def unreachable(self, dead: set[str]) -> list[str]:
        """Nodes out of reach that nobody declared failed (sorted): unreachable, not failed."""
        if not self.gone:  # (on every beat: most of the time nobody is out of reach)
            return []
        return sorted(n for n in self.gone if n not in dead)

    def hears(self, node: str, now: float, within: float | None = None) -> bool:
        """Heard from ``node`` within the liveness window (or ``within``): it was alive then
        (fail-stop), the answer a suspecting node asks for."""
        last = self.last_heard.get(node)
        return last is not None and now - last <= (self.dead_after_s if within is None else within)

    def ago_ms(self, node: str, now: float) -> int:
        """How long ago ``node`` was last heard, in ms (-1: never)."""
        last = self.last_heard.get(node)
        return -1 if last is None else max(0, round((now - last) * 1e3))

    def vouched(self, node: str, at: float) -> None:
        """Someone heard ``node`` at ``at``: its silence clock runs from then (never later
        than that: a late answer does not restart it)."""
        if at > self.last_heard.get(node, float("-inf")):
            self.last_heard[node] = at

    def rejoin(self, node: str, now: float, reachable: bool, route: tuple[str, int] | None) -> None:
        """A node declared failed is back: watch it again from now."""
        self.last_heard[node] = now
        self.gaps.pop(node, None)
        self.busy.discard(node)
        if reachable:
            self._rejoined.add(node)
            self.gone.pop(node, None)
        else:  # out of reach right now: failed again unless heard or a route appears in time
            self.gone.setdefault(node, now)
            self.watched[node] = now
        if route is not None and route[0] == node:
            self.neighbours[node] = now
            self.watched[node] = now

    def forget(self, node: str) -> None:
        self.neighbours.pop(node, None)
        self.watched.pop(node, None)
        self.last_heard.pop(node, None)
        self.heard.pop(node, None)
        self.busy.discard(node)
        self._rejoined.discard(node)
        if node in self._reach:
            self._unreached.add(node)
        self.gaps.pop(node, None)

    def status(self) -> LivenessStatus:
        """For status: the settings and each neighbour's heartbeat inter-arrival figures."""
        return LivenessStatus(
            heartbeat_s=self.period_s,
            dead_after_s=self.dead_after_s,
            inter_arrival={n: g.summary() for n, g in sorted(self.gaps.items())},
        )
