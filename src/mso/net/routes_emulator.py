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
        except (ValueError, TypeError, IndexError, OverflowError):  # (int(inf) overflows)
            self.malformed += 1  # not what the emulator sends: the table stays as it was
            return False
        self.version = state.version
        self.update(neighbours, routes)
        return True
