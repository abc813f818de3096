"""The routing view the user-space emulator feeds: its controller pushes each node a
:class:`~mso.protocol.messages.LinkState` (neighbours with their address and link shape, and
routes) over a client connection whenever links change and after routes converge.

LinkStates carry a version so that one delayed behind a newer one cannot roll the table back.
A version may only grow by ``MAX_VERSION_STEP`` at a time: one pushed to the end of its range
(2^62) would otherwise make every later, genuine LinkState look old and cut the node off.
"""

from __future__ import annotations

from typing import Any

from mso.net.base import LinkShape, Neighbour, Route
from mso.net.routes import TableRoutes
from mso.protocol import messages as m


def neighbour_of(spec: list[Any]) -> Neighbour:
    """``[host, port, bandwidth_mbps | None, delay_ms, loss]`` as a LinkState carries it."""
    host, port, bandwidth, delay, loss = spec[:5]
    shape = LinkShape(None if bandwidth is None else float(bandwidth), float(delay), float(loss))
    return Neighbour(str(host), int(port), shape)


MAX_VERSION_STEP = 1 << 20


class EmulatorRoutes(TableRoutes):
    """A table replaced by every newer LinkState."""

    def __init__(self, node_id: str) -> None:
        super().__init__(node_id)
        self.version = -1
        self.versions_refused = 0  # LinkStates that tried to jump the version ahead
        self._given: dict[str, Route] = {}  # the emulator's routes, before avoiding anything
        self._links: set[tuple[str, str]] = set()
        self.avoided: frozenset[str] = frozenset()
        self.malformed = 0  # LinkStates whose entries do not parse

    def apply(self, state: m.LinkState) -> bool:
        """Take ``state`` if it is newer than the last one taken; True if taken."""
        if state.version <= self.version:
            return False
        if state.version - max(self.version, 0) > MAX_VERSION_STEP:
            self.versions_refused += 1
            return False
        try:
            routes: dict[str, Route] = {d: (str(r[0]), int(r[1])) for d, r in state.routes.items()}
            neighbours = {n: neighbour_of(s) for n, s in state.neighbours.items()}
            links = {(str(a), str(b)) for a, b, *_ in state.links}
        except (ValueError, TypeError, IndexError, OverflowError):  # (int(inf) overflows)
            self.malformed += 1  # not what the emulator sends: the table stays as it was
            return False
        self.version = state.version
        self._given = routes
        if links:
            self._links = links
        self.update(neighbours, self._around(routes))
        return True

    def avoid(self, nodes: frozenset[str]) -> None:
        """Relay nothing through ``nodes`` (the node holds their daemons failed): in user
        space the daemon is the relay, and the emulator, like a routing daemon on a live
        router, may keep routing through a node whose daemon died. Routes that went through
        one are recomputed on the emulator's links around it where there is a way around;
        routes to it stay (its return is heard that way)."""
        if nodes == self.avoided:
            return
        self.avoided = nodes
        self.update(dict(self._neighbours), self._around(self._given))

    def _around(self, routes: dict[str, Route]) -> dict[str, Route]:
        """``routes`` with every route whose next hop is avoided replaced by a shortest path
        on the known links that relays through no avoided node, where there is one."""
        bad = {d for d, (hop, _) in routes.items() if hop in self.avoided and hop != d}
        if not bad or not self._links:
            return routes
        adj: dict[str, set[str]] = {}
        for a, b in self._links:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
        first: dict[str, tuple[str, int]] = {}  # node -> (first hop, hops), breadth first
        frontier = [(n, n) for n in sorted(adj.get(self.node_id, ())) if n in self._neighbours]
        for n, _ in frontier:
            first[n] = (n, 1)
        while frontier:
            nxt: list[tuple[str, str]] = []
            for n, hop in frontier:
                if n in self.avoided:
                    continue  # reached, not relayed through
                for k in sorted(adj.get(n, ())):
                    if k != self.node_id and k not in first:
                        first[k] = (hop, first[n][1] + 1)
                        nxt.append((k, hop))
            frontier = nxt
        # with no way around it, the route stays: a node held failed may be alive after all
        # (a healed partition), and its return is heard that way
        return {d: first.get(d, r) if d in bad else r for d, r in routes.items()}
