"""An mso app between ROS 2 nodes, on emulated node processes: an rmw_zenoh-style talker on
/chatter -> mso.ros2:Subscriber (N1) -> an operator (upper-case) -> mso.ros2:Publisher (N2)
-> an rmw_zenoh-style listener on /loud, all through one Zenoh router on 127.0.0.1."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from mso.emu.controller import Emulator
from mso.scenario import loads_scenario
from ros2_helpers import (
    Listener,
    attachment,
    cdr_string,
    chatter_key,
    free_port,
    ros_peer,
    router,
    tokens,
    wait_for,
)

TESTS = Path(__file__).resolve().parent
LINE = """
name: ros2line
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


def app(endpoint: str) -> str:
    fmt = "mso.ros2.types:std_msgs__msg__String"
    return f"""
name: ros2pipe
vertices:
  chatter: {{code: "mso.ros2:Subscriber", pinned: N1, output: "{fmt}",
            params: {{topic: /chatter, type: std_msgs/msg/String, router: "{endpoint}"}}}}
  shout: {{code: "ros2_vertices:shout", output: "{fmt}"}}
  loud: {{code: "mso.ros2:Publisher", pinned: N2,
         params: {{topic: /loud, type: std_msgs/msg/String, router: "{endpoint}"}}}}
edges: [[chatter, shout], [shout, loud]]
"""


@pytest.fixture(autouse=True)
def node_pythonpath(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Node processes import the test operator from this directory."""
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    yield


def test_talker_to_mso_to_listener_on_node_processes() -> None:
    port = free_port()
    r = router(port)
    peer = ros_peer(port)
    listener = Listener(peer, chatter_key(topic="loud"))
    talker = peer.declare_publisher(chatter_key())

    async def run() -> dict[str, object]:
        emu = Emulator(loads_scenario(LINE), allow_code=("ros2_vertices",))
        await emu.start()
        try:
            reply = await emu.deploy(app(f"tcp/127.0.0.1:{port}"), "ros2.yaml", "N1")
            assert reply.ok, reply.error
            ready = await asyncio.to_thread(
                wait_for,
                lambda: sum("/MS/" in t or "/MP/" in t for t in tokens(peer)) == 2,
                20.0,
            )
            # each token is declared after its entity, so the graph showing both means the
            # router routes the talker to the Subscriber and the Publisher to the listener
            assert ready, tokens(peer)
            for i in range(20):  # one at a time: the Subscriber keeps the last 10 only
                talker.put(cdr_string(f"hello world {i}"), attachment=attachment(i + 1, bytes(16)))
                came = await asyncio.to_thread(wait_for, lambda n=i + 1: len(listener.texts()) == n)
                assert came, (i, listener.texts())
            return await emu.status()
        finally:
            await emu.stop()

    try:
        status = asyncio.run(run())
    finally:
        talker.undeclare()
        peer.close()
        r.close()
    assert listener.texts() == [f"HELLO WORLD {i}" for i in range(20)], status
    assert [g[1] for g in listener.got] == list(range(1, 21)) and listener.bad == 0
    vertices = status["N1"]["apps"]["ros2pipe"]["vertices"]  # type: ignore[index]
    assert vertices["chatter"]["stats"]["received"] == 20
    assert vertices["chatter"]["errors"] == 0
