"""A control frame with no usable next hop waits for the routes to change; data frames do not."""

from __future__ import annotations

import asyncio

import pytest

from mso.client import overlay_key
from mso.net import forwarding
from mso.node import driver as d
from mso.node.core import NodeCore, Send
from mso.protocol import messages as m


def probe() -> m.Probe:
    return m.Probe("app", 0, 0, "N5", "N1", ["N5"], [1.0])


def waiting(driver: d.NodeDriver) -> list[m.Message]:
    """What waits for a route (the node's hello heartbeats wait too)."""
    got = [m.decode(m.unwrap(w.item[0]).body) for w in driver.transport.waiting]
    return [msg for msg in got if not isinstance(msg, m.Heartbeat)]


def links(version: int, routes: dict[str, list[object]]) -> m.LinkState:
    # N4 < N5, so N5 waits for N4 to connect and frames for N4 are held, not sent
    return m.LinkState(version, {"N4": ["127.0.0.1", 9, None, 0.0, 0.0]}, routes)


def test_control_frames_wait_for_a_route_and_data_frames_do_not() -> None:
    async def run() -> None:
        driver = d.NodeDriver(NodeCore("N5"), "127.0.0.1", 0, overlay_key("k"))
        # routes still point at N3, which is no longer a neighbour (it just died)
        driver.apply_links(links(1, {"N1": ["N3", 2]}))
        driver._apply([Send("N1", probe()), Send("N1", m.Ack("app", 0, 0, 7))])
        assert driver.counters.frames_unroutable == 1  # the ack: replay covers data
        assert waiting(driver) == [probe()] and not driver.transport.held
        # the routes change: the probe leaves toward N1 through N4
        driver.apply_links(links(2, {"N1": ["N4", 2]}))
        assert not driver.transport.waiting
        held = [m.decode(m.unwrap(f).body) for f, *_ in driver.transport.held["N4"]]
        assert [x for x in held if not isinstance(x, m.Heartbeat)] == [probe()]
        assert driver.counters.frames_unroutable == 1

    asyncio.run(run())


def test_a_frame_waits_for_a_route_only_so_long(monkeypatch: pytest.MonkeyPatch) -> None:
    async def run() -> None:
        driver = d.NodeDriver(NodeCore("N5"), "127.0.0.1", 0, overlay_key("k"))
        driver._apply([Send("N1", probe())])  # no route at all
        assert waiting(driver) == [probe()]
        await asyncio.sleep(0.06)
        driver.apply_links(links(1, {"N1": ["N4", 2]}))  # too late
        assert not driver.transport.waiting
        held = [m.decode(m.unwrap(f).body) for f, *_ in driver.transport.held.get("N4", [])]
        assert not [x for x in held if isinstance(x, m.Probe)]
        assert driver.counters.frames_unroutable == 1

    monkeypatch.setattr(forwarding, "ROUTE_WAIT_S", 0.05)
    asyncio.run(run())
