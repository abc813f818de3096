"""An outsider with no key cannot hold a node's connection slots (issue 27, item 5).

It used to: reopening each connection the moment the handshake deadline closed it, it held all
of them, and 0 of 31 legitimate status requests were answered. Now a connection still proving
the key takes a slot of a pending pool where a new connection is never refused: the oldest
pending connection of the source that weighs most (unknown, most slots, most failed
handshakes) makes room (:mod:`mso.net.admission`).
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
from pathlib import Path
from typing import Any

from mso.client import Client, overlay_key
from mso.errors import MsoError
from mso.net.admission import Admission
from mso.net.limits import ConnectionCounters, Limits
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from waits import patience

TESTS = Path(__file__).resolve().parent
HOST = "127.0.0.1"
KEY = overlay_key("k")
# small pools, so a few dozen attacking connections are many times what the node keeps; the
# handshake deadline is the machine's: on a loaded machine a client's handshake took over the
# second (reset, counted)
LIMITS = Limits(
    handshake_s=patience(1.0),
    sweep_s=0.05,
    max_connections=8,
    max_per_address=4,
    max_pending=8,
    max_pending_per_address=4,
)
SOURCES = ["127.0.0.2", "127.0.0.3", "127.0.0.4", "127.0.0.5"]  # the attacker's addresses


async def hold_a_slot(port: int, source: str, stop: asyncio.Event, opened: list[int]) -> None:
    """Open a connection, never prove a key, and reopen it the moment it is closed."""
    while not stop.is_set():
        try:
            r, w = await asyncio.open_connection(HOST, port, local_addr=(source, 0))
        except OSError:
            continue
        opened[0] += 1
        try:
            read = asyncio.ensure_future(r.read())
            await asyncio.wait([read, asyncio.ensure_future(stop.wait())], timeout=30.0,
                               return_when=asyncio.FIRST_COMPLETED)  # fmt: skip
            read.cancel()
        finally:
            w.close()


async def attack(port: int, bound_s: float) -> None:
    """The outsider, in a process of its own (as it would be on another machine: its 40
    reconnecting clients in the node's own loop took the node's time, and a member's handshake
    passed its deadline at load 19): says "open" once each connection was opened once, stops
    when its standard input closes (or after ``bound_s``), then prints how many it opened."""
    stop, opened = asyncio.Event(), [0]
    tasks = [
        asyncio.ensure_future(hold_a_slot(port, SOURCES[i % len(SOURCES)], stop, opened))
        for i in range(40)  # five times the pool
    ]
    while opened[0] < 40:
        await asyncio.sleep(0.01)  # the attacker's own pace, not a test's wait
    print("open", flush=True)
    loop = asyncio.get_running_loop()
    stdin = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(stdin), sys.stdin)
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stdin.read(), bound_s)
    stop.set()
    await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 30.0)
    print(opened[0], flush=True)


def test_31_status_requests_are_answered_while_an_outsider_reopens_every_slot() -> None:
    async def run() -> tuple[int, dict[str, Any], int]:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, KEY, limits=LIMITS)
        await driver.start()
        port = driver.transport.port
        code = f"import asyncio, test_security_slots as t; asyncio.run(t.attack({port}, 300.0))"
        attacker = await asyncio.create_subprocess_exec(
            sys.executable, "-c", code, cwd=TESTS,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert attacker.stdin is not None and attacker.stdout is not None
        try:  # every attacking connection is open once
            said = await asyncio.wait_for(attacker.stdout.readline(), patience(20.0))
            assert said == b"open\n", said
            answered = 0
            for _ in range(31):
                client = await Client(HOST, port, KEY).connect(patience(5.0))
                try:
                    reply = await client.call(m.StatusRequest(), patience(5.0))
                    answered += isinstance(reply, m.StatusReply)
                finally:
                    await client.close()
            attacker.stdin.close()
            opened = int(await asyncio.wait_for(attacker.stdout.readline(), patience(20.0)))
            reply = await (await Client(HOST, port, KEY).connect()).call(m.StatusRequest())
            assert isinstance(reply, m.StatusReply)
            return answered, reply.nodes["N1"]["connections"], opened
        finally:
            if attacker.returncode is None:
                attacker.kill()
            await attacker.wait()
            await driver.stop()

    answered, connections, opened = asyncio.run(run())
    assert answered == 31
    assert connections["evicted"] >= opened - 40 - 8  # the attacker's went, not ours
    assert connections["connections_refused"] == 0


class Conn:
    def __init__(self, address: str, opened: float) -> None:
        self.address, self.opened, self.aborted = address, opened, False

    def abort(self) -> None:
        self.aborted = True


def test_the_source_that_weighs_most_makes_room_and_a_failing_one_backs_off() -> None:
    lim = Limits(max_pending=4, max_pending_per_address=3, handshake_s=4.0, handshake_min_s=0.5)
    adm = Admission(lim, ConnectionCounters())
    member = Conn("10.0.0.1", 0.0)
    adm.introduced(member, 0.0)  # its address is known from now on
    attacker = [Conn("10.0.0.9", t) for t in (0.0, 0.1, 0.2)]
    for c in attacker:
        assert adm.admit(c, c.opened) == []
    assert adm.admit(Conn("10.0.0.9", 0.3), 0.3) == [attacker[0]]  # its own oldest, at its cap
    fresh = Conn("10.0.0.1", 0.4)
    assert adm.admit(fresh, 0.4) == []  # the pool has room for one more
    newcomer = Conn("10.0.0.5", 0.5)
    assert adm.admit(newcomer, 0.5) == [attacker[1]]  # pool full: the heaviest source's oldest
    assert adm.is_pending(fresh) and adm.is_pending(newcomer)
    # evictions and failed handshakes are strikes; they shorten a source's deadline, down to
    # a floor; known sources and sources without strikes keep theirs
    assert adm.deadline(newcomer, 0.5) == 0.5 + 4.0 and adm.deadline(fresh, 0.5) == 0.4 + 4.0
    assert 1.9 < adm.strikes("10.0.0.9", 0.5) <= 2  # its two evicted
    for _ in range(2):
        adm.failed(Conn("10.0.0.9", 0.0), 0.5)
    assert abs(adm.deadline(attacker[2], 0.5) - (0.2 + 4.0 / 5)) < 0.01
    for _ in range(20):
        adm.failed(Conn("10.0.0.9", 0.0), 0.5)
    assert adm.deadline(attacker[2], 0.5) == 0.2 + 0.5
    assert [c.address for c in adm.overdue(0.8)] == ["10.0.0.9"]
    assert abs(adm.strikes("10.0.0.9", 0.5 + 10.0) - adm.strikes("10.0.0.9", 0.5) / 2) < 1e-9


def test_members_are_bounded_per_address_once_introduced() -> None:
    async def run() -> ConnectionCounters:
        driver = NodeDriver(NodeCore("N1"), HOST, 0, KEY, limits=LIMITS)
        await driver.start()
        port = driver.transport.port
        try:
            clients = [await Client(HOST, port, KEY).connect() for _ in range(4)]
            for c in clients:
                assert isinstance(await c.call(m.StatusRequest()), m.StatusReply)
            fifth = await Client(HOST, port, KEY).connect()  # proves the key, then is closed
            try:
                await fifth.call(m.StatusRequest(), 2.0)
                raise AssertionError("a fifth member from one address was served")
            except MsoError:
                pass
            for c in clients:
                await c.close()
            return driver.transport.connection_counters
        finally:
            await driver.stop()

    counters = asyncio.run(run())
    assert counters.connections_refused == 1 and counters.evicted == 0
