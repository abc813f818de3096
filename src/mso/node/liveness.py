"""Neighbour liveness: heartbeats in, suspicions out (fail-stop detection, paper §3.4). Sans-IO.

Every node sends a heartbeat to each current neighbour every ``period_s`` and notes when it
last heard from each. A neighbour that the routing view still lists as a neighbour but that has
been silent for ``dead_after_s`` has failed: under the fail-stop assumption a live node keeps
talking, and a broken link (rather than a dead node) shows up in the routing view as a lost
neighbour, which is not a failure. The clock starts when a node becomes a neighbour, so a new
link is not suspected before its first heartbeat could arrive. A node the routing view stops
reaching at all (it drops every route to it, as a routing protocol does for a node that fell
silent) is failed too once it has stayed unreachable for ``dead_after_s``.

Heartbeats also carry the sender's monitored figures; the table of what neighbours last said
(``heard``) is what the management rules weigh a move toward a neighbour with.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mso.protocol import messages as m

HEARTBEAT_S = 0.1
DEAD_AFTER_S = 0.5


@dataclass
class Liveness:
    period_s: float = HEARTBEAT_S
    dead_after_s: float = DEAD_AFTER_S
    neighbours: dict[str, float] = field(default_factory=dict)  # neighbour -> since
    last_heard: dict[str, float] = field(default_factory=dict)
    heard: dict[str, tuple[float, m.Heartbeat]] = field(default_factory=dict)
    reachable: set[str] = field(default_factory=set)
    gone: dict[str, float] = field(default_factory=dict)  # unreachable node -> since

    def set_routes(self, now: float, reachable: set[str], neighbours: set[str]) -> None:
        """The routing view changed: who is a neighbour, who is reachable at all."""
        for n in self.reachable - reachable:
            self.gone.setdefault(n, now)
        for n in reachable:
            self.gone.pop(n, None)
        self.reachable = set(reachable)
        self.set_neighbours(now, neighbours)

    def set_neighbours(self, now: float, neighbours: set[str]) -> None:
        for n in list(self.neighbours):
            if n not in neighbours:
                del self.neighbours[n]
        for n in neighbours:
            self.neighbours.setdefault(n, now)

    def heard_from(self, node: str, now: float, beat: m.Heartbeat | None = None) -> None:
        self.last_heard[node] = now
        if beat is not None:
            self.heard[node] = (now, beat)

    def suspects(self, now: float, dead: set[str]) -> list[str]:
        """Neighbours silent for longer than ``dead_after_s`` (sorted, deterministic)."""
        out = []
        for n, since in sorted(self.neighbours.items()):
            if n in dead:
                continue
            last = max(since, self.last_heard.get(n, since))
            if now - last > self.dead_after_s:
                out.append(n)
        out += [n for n, t in self.gone.items() if n not in dead and now - t > self.dead_after_s]
        return sorted(set(out))

    def rejoin(self, node: str, now: float, reachable: bool, route: tuple[str, int] | None) -> None:
        """A node declared failed is back: watch it again from now."""
        self.last_heard[node] = now
        if reachable:
            self.reachable.add(node)
            self.gone.pop(node, None)
        else:  # out of reach right now: failed again unless a route appears in time
            self.gone.setdefault(node, now)
        if route is not None and route[0] == node:
            self.neighbours[node] = now

    def forget(self, node: str) -> None:
        self.neighbours.pop(node, None)
        self.last_heard.pop(node, None)
        self.heard.pop(node, None)
        self.gone.pop(node, None)
        self.reachable.discard(node)
