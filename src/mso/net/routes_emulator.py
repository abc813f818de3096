"""The routing view the user-space emulator feeds: its controller pushes each node a
:class:`~mso.protocol.messages.LinkState` (neighbours with their address and link shape, and
routes) over a client connection whenever links change and after routes converge.

LinkStates carry a version so that one delayed behind a newer one cannot roll the table back.
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


class EmulatorRoutes(TableRoutes):
    """A table replaced by every newer LinkState."""

    def __init__(self, node_id: str) -> None:
        super().__init__(node_id)
        self.version = -1

    def apply(self, state: m.LinkState) -> bool:
        """Take ``state`` if it is newer than the last one taken; True if taken."""
        if state.version <= self.version:
            return False
        self.version = state.version
        routes: dict[str, Route] = {d: (str(r[0]), int(r[1])) for d, r in state.routes.items()}
        self.update({n: neighbour_of(s) for n, s in state.neighbours.items()}, routes)
        return True
