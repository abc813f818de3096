"""A routing view kept as a table that something outside the node writes.

Both the static ``--peer`` view and the emulator-fed view are tables: the node does not compute
routes, it is told them (by its configuration, by the emulator controller; a kernel view will
read them from netlink). :class:`TableRoutes` holds the table and tells subscribers.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from mso.net.base import Counters, Neighbour, Route, RoutesChanged


class TableRoutes:
    """A :class:`~mso.net.base.RoutingView` whose neighbours and routes are set by
    :meth:`update`."""

    def __init__(self, node_id: str) -> None:
        self.node_id = node_id
        self.counters = Counters()
        self._routes: dict[str, Route] = {}
        self._neighbours: dict[str, Neighbour] = {}
        self._subscribers: list[Callable[[RoutesChanged], None]] = []

    def routes(self) -> Mapping[str, Route]:
        return self._routes

    def neighbours(self) -> Mapping[str, Neighbour]:
        return self._neighbours

    def next_hop(self, dst: str) -> str | None:
        route = self._routes.get(dst)
        return None if route is None else route[0]

    def detour(self, dst: str) -> str | None:
        """A table says nothing about what other nodes reach."""
        return None

    def subscribe(self, callback: Callable[[RoutesChanged], None]) -> Callable[[], None]:
        self._subscribers.append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers:
                self._subscribers.remove(callback)

        return unsubscribe

    def update(self, neighbours: Mapping[str, Neighbour], routes: Mapping[str, Route]) -> None:
        """Take a new table and tell every subscriber, even when nothing differs: a repeated
        table is still news to the core (probes and recoveries waiting for a route retry)."""
        self._neighbours = dict(neighbours)
        self._routes = {d: r for d, r in routes.items() if d != self.node_id}
        event = RoutesChanged(self._routes, self._neighbours)
        for callback in list(self._subscribers):
            callback(event)
