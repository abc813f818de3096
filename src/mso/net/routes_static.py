"""The routing view of ``mso node --peer N=HOST:PORT ...``: every peer is a neighbour one hop
away, and nothing else is reachable. It never changes, so it suits a fixed testbed or a pair
of laptops; a mobile network needs the emulator's view or (later) the kernel's."""

from __future__ import annotations

from collections.abc import Mapping

from mso.net.base import Neighbour
from mso.net.routes import TableRoutes


class StaticRoutes(TableRoutes):
    """Peers given once, each a one-hop route."""

    def __init__(self, node_id: str, peers: Mapping[str, Neighbour]) -> None:
        super().__init__(node_id)
        # set before anyone subscribes: the driver reads the initial table when it starts
        self._neighbours = {n: p for n, p in peers.items() if n != node_id}
        self._routes = {n: (n, 1) for n in self._neighbours}
