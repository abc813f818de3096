"""The static and emulator-fed routing views: tables, versions, change events."""

from __future__ import annotations

from mso.net.base import LinkShape, Neighbour, RoutesChanged, RoutingView
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.routes_static import StaticRoutes
from mso.protocol import messages as m


def test_static_peers_are_one_hop_neighbours() -> None:
    peers = {"N2": Neighbour("127.0.0.1", 7002), "N1": Neighbour("127.0.0.1", 7001)}
    view = StaticRoutes("N1", peers)  # a node listed among its own peers is left out
    assert isinstance(view, RoutingView)
    assert dict(view.neighbours()) == {"N2": Neighbour("127.0.0.1", 7002)}
    assert dict(view.routes()) == {"N2": ("N2", 1)}
    assert view.next_hop("N2") == "N2" and view.next_hop("N3") is None
    assert not view.neighbours()["N2"].shape.shaped


def links(version: int, routes: dict[str, list[object]]) -> m.LinkState:
    return m.LinkState(
        version,
        {"N2": ["127.0.0.1", 7002, 2.0, 5, 0.1], "N3": ["127.0.0.1", 7003, None, 0.0, 0.0]},
        routes,
    )


def test_the_emulator_view_follows_newer_link_states_only() -> None:
    view = EmulatorRoutes("N1")
    assert isinstance(view, RoutingView)
    seen: list[RoutesChanged] = []
    view.subscribe(seen.append)
    assert view.apply(links(1, {"N4": ["N2", 2], "N2": ["N2", 1], "N1": ["N1", 0]}))
    assert dict(view.routes()) == {"N4": ("N2", 2), "N2": ("N2", 1)}  # never to itself
    assert view.neighbours()["N2"] == Neighbour("127.0.0.1", 7002, LinkShape(2.0, 5.0, 0.1))
    assert view.neighbours()["N3"].shape == LinkShape()
    assert view.next_hop("N4") == "N2"
    assert len(seen) == 1 and dict(seen[0].routes) == dict(view.routes())
    # a LinkState that arrives late cannot roll the table back
    assert not view.apply(links(0, {}))
    assert view.next_hop("N4") == "N2" and len(seen) == 1
    # an infinite hop count (a fuzzed frame once raised out of the handler) is malformed
    assert not view.apply(links(2, {"N4": ["N2", float("inf")]}))
    assert view.malformed == 1 and view.next_hop("N4") == "N2"


def test_every_taken_table_is_news_in_subscription_order() -> None:
    view = EmulatorRoutes("N1")
    order: list[str] = []
    view.subscribe(lambda _: order.append("transport"))
    unsubscribe = view.subscribe(lambda _: order.append("driver"))
    view.apply(links(1, {"N4": ["N2", 2]}))
    view.apply(links(2, {"N4": ["N2", 2]}))  # the same routes: still news
    assert order == ["transport", "driver"] * 2
    unsubscribe()
    view.apply(links(3, {"N4": ["N3", 2]}))
    assert order[-1] == "transport" and len(order) == 5


def test_the_emulator_view_relays_nothing_through_a_node_held_failed() -> None:
    """N1's neighbours are N2 and N3; N4 is behind both (N2 is the emulator's choice) and N5
    only behind N2. Once N1 holds N2's daemon failed, N4 is reached through N3; N5 still
    through N2 (there is no other way), N2 itself directly; held alive again, the emulator's routes
    come back."""
    view = EmulatorRoutes("N1")
    seen: list[RoutesChanged] = []
    view.subscribe(seen.append)
    routes = {"N2": ["N2", 1], "N3": ["N3", 1], "N4": ["N2", 2], "N5": ["N2", 2]}
    state = links(1, routes)
    state.links = [["N1", "N2"], ["N1", "N3"], ["N2", "N4"], ["N3", "N4"], ["N2", "N5"]]
    assert view.apply(state)
    assert view.next_hop("N4") == "N2"
    view.avoid(frozenset({"N2"}))
    # (N5 only behind N2: kept, as the node held failed may be alive after all)
    assert dict(view.routes()) == {
        "N2": ("N2", 1),
        "N3": ("N3", 1),
        "N4": ("N3", 2),
        "N5": ("N2", 2),
    }
    assert len(seen) == 2
    view.avoid(frozenset({"N2"}))  # no change, no event
    assert len(seen) == 2
    view.avoid(frozenset())
    assert view.next_hop("N4") == "N2" and view.next_hop("N5") == "N2"
