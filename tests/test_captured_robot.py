"""A captured robot: it holds the overlay key (a member) but no operator key. On nodes started
with ``--operator-key`` it can neither stop an app, nor bring back one an operator undeployed,
nor command relocations, nor steer a vertex this node runs; each try changes nothing and is
counted in status. (What it can still do is listed in docs/security.md.)

The first tests run node cores in the simulator (the core's checks); the last runs two node
processes' drivers over TCP with a robot connected to one of them as a neighbour (the
transport's checks too, and an undeploy verified by the node it is relayed to)."""

from __future__ import annotations

import asyncio
from typing import Any

import msgspec

from mso.client import Client, overlay_key
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer
from mso.protocol.effects import Send
from mso.protocol.framing import HELLO_BYTES, FrameCodec
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app
from waits import patience

OPERATOR = Signer()
ROGUE = Signer()  # a key of the robot's own: no node knows it
APP = pipe_app(50).replace("pinned: N4", "pinned: N3")  # src on N1, mid on N2, sink on N3


def signed(sim: Simulation, *nodes: str) -> None:
    for n in nodes or tuple(sim.cores):
        sim.cores[n].authority = Authority.configure([OPERATOR.public_text()])


def overlay(granted_at: int = 1000) -> Simulation:
    """N1 - N2 - N3 (N9 out of reach), every node with the operator's key, ``pipe`` deployed
    by the operator."""
    net = Network(
        [NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3"), NodeSpec("N9")],
        [LinkSpec("N1", "N2", delay_ms=1.0), LinkSpec("N2", "N3", delay_ms=1.0)],
    )
    sim = Simulation(net)
    signed(sim)
    sim.request("N1", m.DeployRequest(OPERATOR.grant(APP, granted_at), "app.yaml"))
    sim.run_until(1.0)
    assert any(isinstance(r, m.DeployReply) and r.ok for _, _, r in sim.replies)
    return sim


def apps(sim: Simulation) -> dict[str, Any]:
    """Every node's apps, their placement and whether they run."""
    return {
        n: {a: (dict(d.placed), d.running, sorted(d.instances)) for a, d in c.apps.items()}
        for n, c in sim.cores.items()
    }


def sunk(sim: Simulation) -> int:
    return int(sim.cores["N3"].instances("pipe")["sink"].processed)


def robot(sim: Simulation, node: str, msg: m.Message, src: str = "N9") -> list[Any]:
    """The robot's message delivered to ``node`` (as a neighbour's; it may claim any source)."""
    effects = sim.cores[node].receive(src, msg, sim.now)
    sim.apply(node, effects)
    return effects


ATTACKS = [
    ("N2", "N1", m.StopApp("pipe"), "stop_app_unauthorized"),
    ("N3", "N2", ROGUE.undeploy("pipe", 5000), "stop_app_unauthorized"),
    # the operator's signature of another app's undeploy, put on this one
    ("N3", "N2", msgspec.structs.replace(OPERATOR.undeploy("demo", 5000), app="pipe"),
     "stop_app_unauthorized"),
    ("N1", "N2", m.RelocateRequest("pipe", "mid", target="N3"), "relocate_from_member"),
    ("N2", "N1", m.Switch("pipe", 0, "N3", 77), "switch_not_the_producer"),
    ("N1", "N2", m.Switch("pipe", 0, "N9", 77), "switch_to_an_unknown_node"),
    ("N2", "N1", m.Moved("pipe", "mid", "N1", 0), "moved_a_vertex_running_here"),
    ("N1", "N3", m.Moved("pipe", "sink", "N2"), "moved_a_pinned_vertex"),
    ("N1", "N2", m.DeployFailed("pipe", "stop it"), "deploy_failed_after_deployment"),
    ("N2", "N1", m.BuildChain("pipe", 0, ["mid"]), "build_not_of_the_chain"),
    ("N2", "N1", m.Marker("pipe", 0, 0, 77, "N2"), "marker_of_no_relocation"),
]  # fmt: skip


def test_a_captured_robot_cannot_stop_or_steer_a_running_app() -> None:
    sim = overlay()
    before, flowing = apps(sim), sunk(sim)
    for node, src, msg, reason in ATTACKS:
        core = sim.cores[node]
        counted = core.refusals.get(reason, 0)
        assert robot(sim, node, msg, src) == [], msg  # nothing done, nothing said
        assert core.refusals.get(reason, 0) == counted + 1, (msg, core.refusals)
    sim.run_until(sim.now + 1.0)
    assert apps(sim) == before  # every node: the same app, placement and instances
    assert sunk(sim) > flowing  # and events still flow to the sink
    total = sum(sum(c.status(sim.now)["refusals"].values()) for c in sim.cores.values())
    assert total >= len(ATTACKS)


def test_an_operators_undeploy_is_verified_by_every_node_and_revokes_the_grant() -> None:
    sim = overlay(granted_at=1000)
    old = OPERATOR.grant(APP, 1000)
    sim.request("N1", OPERATOR.undeploy("pipe", 2000))
    sim.run_until(sim.now + 1.0)
    assert all(not c.apps for c in sim.cores.values())
    for n in ("N1", "N2", "N3"):  # each checked the signature itself (N3's came through N2)
        assert sim.cores[n].authority.revoked["pipe"].at == 2000

    # the robot replays the app's announcement and a sync, as it heard them before
    for node in ("N2", "N3"):
        core = sim.cores[node]
        refused = core.refusals.get("document_revoked", 0)
        for msg in (
            m.AppAnnounce("pipe", "N1", old, 1),
            m.AppSync("pipe", "N1", old, 1, {"src": "N1", "mid": "N2", "sink": "N3"}),
        ):
            effects = robot(sim, node, msg)
            told = [e.said for e in effects if isinstance(e, Send) and e.dst == "N9"]
            assert told == [sim.cores[node].authority.revoked["pipe"]]  # told the undeploy
        assert core.refusals["document_revoked"] == refused + 2
    sim.run_until(sim.now + 0.5)
    assert all(not c.apps for c in sim.cores.values())  # nothing came back
    # nor does a deploy request carrying the old grant
    sim.request("N1", m.DeployRequest(old, "app.yaml"))
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and not reply.ok and "undeployed" in reply.error

    # the operator deploys it again: the captured undeploy, replayed, stops nothing
    sim.request("N1", m.DeployRequest(OPERATOR.grant(APP, 3000), "app.yaml"))
    sim.run_until(sim.now + 1.0)
    assert all(c.apps["pipe"].running for n, c in sim.cores.items() if n != "N9")
    flowing = sunk(sim)
    for node in ("N1", "N2", "N3"):
        robot(sim, node, OPERATOR.undeploy("pipe", 2000))
        assert sim.cores[node].refusals["undeploy_older_than_deployment"] == 1
    sim.run_until(sim.now + 0.5)
    assert all(c.apps["pipe"].running for n, c in sim.cores.items() if n != "N9")
    assert sunk(sim) > flowing


def test_a_node_that_restarted_hears_the_undeploy_when_it_comes_back() -> None:
    """A node down during the undeploy forgot nothing it never knew; the first neighbour
    that reaches it again tells it, so a replayed grant is refused there too."""
    sim = overlay()
    sim.kill("N3")
    sim.run_until(sim.now + 1.0)  # declared failed
    sim.request("N1", OPERATOR.undeploy("pipe", 2000))
    sim.run_until(sim.now + 0.5)
    sim.network.add_link(LinkSpec("N2", "N3", delay_ms=1.0))
    sim.revive("N3")
    signed(sim, "N3")
    assert "pipe" not in sim.cores["N3"].authority.revoked
    sim.run_until(sim.now + 1.0)
    assert sim.cores["N3"].authority.revoked["pipe"].at == 2000
    robot(sim, "N3", m.AppSync("pipe", "N1", OPERATOR.grant(APP, 1000), 1, {}))
    assert sim.cores["N3"].refusals["document_revoked"] == 1 and not sim.cores["N3"].apps


def test_an_open_overlay_still_takes_a_members_undeploy() -> None:
    """Without operator keys (development, the tests' emulator) membership is all there is."""
    net = Network([NodeSpec("N1"), NodeSpec("N2")], [LinkSpec("N1", "N2", delay_ms=1.0)])
    sim = Simulation(net)
    sim.request("N1", m.DeployRequest(APP.replace("pinned: N3", "pinned: N2"), "app.yaml"))
    sim.run_until(1.0)
    assert all(c.apps for c in sim.cores.values())
    robot(sim, "N2", m.StopApp("pipe"), src="N1")
    sim.run_until(sim.now + 0.5)
    assert not sim.cores["N2"].apps


# -- over TCP: two nodes and a robot connected to one of them as a neighbour ------------------
HOST = "127.0.0.1"
KEY = overlay_key("convoy")
TCP_APP = (
    "name: one\n"
    "vertices:\n"
    "  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, "
    "output: runtime_vertices:Num}\n"
    "  sink: {code: runtime_vertices:Recorder, pinned: N2}\n"
    "edges:\n"
    "  - [src, sink]\n"
)


async def status(port: int, node: str) -> dict[str, Any]:
    client = await Client(HOST, port, KEY).connect()
    try:
        reply = await client.call(m.StatusRequest())
        assert isinstance(reply, m.StatusReply)
        return reply.nodes[node]
    finally:
        await client.close()


async def until(check: Any, what: str, timeout: float = 20.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience(timeout)
    while not await check():
        assert loop.time() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


class Robot:
    """A member's connection to N2, speaking as a neighbour (``N7``) in any node's name."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer, self.codec = reader, writer, FrameCodec(KEY)

    @classmethod
    async def connect(cls, port: int) -> Robot:
        r = cls(*await asyncio.open_connection(HOST, port))
        r.writer.write(r.codec.hello())
        _, confirm = r.codec.feed(await r.reader.readexactly(HELLO_BYTES))
        r.writer.write(confirm)
        r.writer.write(r.codec.seal(m.wrap("N7", "N2", m.PeerHello("N7"))))
        return r

    async def send(self, msg: m.Message, dst: str = "N2", src: str = "N1") -> None:
        """To N2, or relayed by N2 to ``dst``."""
        self.writer.write(self.codec.seal(m.wrap(src, dst, msg)))
        await self.writer.drain()


def test_over_tcp_a_robot_neither_stops_nor_resurrects_an_app() -> None:
    async def run() -> None:
        drivers = {}
        for n in ("N1", "N2"):
            auth = Authority.configure([OPERATOR.public_text()])
            drivers[n] = NodeDriver(NodeCore(n), HOST, 0, KEY, authority=auth)
            await drivers[n].start()
        port = {n: d.transport.port for n, d in drivers.items()}
        for n, other in (("N1", "N2"), ("N2", "N1")):
            drivers[n].apply_links(
                m.LinkState(1, {other: [HOST, port[other], None, 0.0, 0.0]}, {other: [other, 1]})
            )
        bot = None
        try:
            operator = await Client(HOST, port["N1"], KEY, signer=OPERATOR).connect()
            reply = await operator.call(m.DeployRequest(TCP_APP, "one.yaml"), timeout=20)
            assert isinstance(reply, m.DeployReply) and reply.ok, reply
            placement = (await status(port["N2"], "N2"))["apps"]["one"]["placement"]
            old = drivers["N2"].core.apps["one"].document  # the grant as it travelled

            async def sunk() -> int:
                st = await status(port["N2"], "N2")
                return int(st["apps"]["one"]["vertices"]["sink"]["processed"])

            bot = await Robot.connect(port["N2"])
            for dst, msg in [
                ("N2", m.StopApp("one")),
                ("N1", m.StopApp("one")),  # relayed by N2 to N1
                ("N2", ROGUE.undeploy("one", 1 << 50)),
                ("N1", m.DeployFailed("one", "stop it")),  # to the origin
                ("N2", m.Moved("one", "sink", "N7", 0)),
                ("N1", m.Switch("one", 0, "N7", 1)),
                ("N1", m.RelocateRequest("one", "sink", target="N1")),
                ("N2", m.Shutdown()),
                ("N2", m.LinkState(1 << 20, {}, {})),
            ]:
                await bot.send(msg, dst)
            flowing = await sunk()
            want = {
                "N1": {
                    "stop_app_unauthorized": 1,
                    "deploy_failed_after_deployment": 1,
                    "switch_of_a_pinned_vertex": 1,
                    "relocate_from_member": 1,
                },
                "N2": {"stop_app_unauthorized": 2, "moved_a_pinned_vertex": 1},
            }

            async def all_counted() -> bool:
                for n, reasons in want.items():
                    got = (await status(port[n], n))["refusals"]
                    if any(got.get(r, 0) < k for r, k in reasons.items()):
                        return False
                return True

            await until(all_counted, "the robot's messages to be refused and counted")
            await until(lambda: _more(sunk, flowing), "events to go on flowing")
            for n in ("N1", "N2"):
                st = await status(port[n], n)
                assert st["apps"]["one"]["placement"] == placement and st["apps"]["one"]["running"]
                assert not drivers[n].stopped.is_set()
            # the three undeploys without authority, each refused by the node it reached
            assert drivers["N1"].authority.refused + drivers["N2"].authority.refused == 3
            assert set(drivers["N2"].view.routes()) == {"N1"}  # the LinkState was not taken

            # the operator undeploys through N1; N2 verifies the relayed undeploy itself
            await operator.call(m.StopApp("one"), timeout=10)

            async def gone() -> bool:
                return not (await status(port["N2"], "N2"))["apps"]

            await until(gone, "the undeploy to reach N2")
            assert "one" in drivers["N2"].authority.revoked
            # the robot replays the announcement and a sync of the undeployed app
            refused = drivers["N2"].authority.refused
            await bot.send(m.AppAnnounce("one", "N1", old, 1))
            await bot.send(m.AppSync("one", "N1", old, 1, placement))

            async def both_refused() -> bool:
                return drivers["N2"].authority.refused >= refused + 2

            await until(both_refused, "the replays to be refused")
            assert not (await status(port["N2"], "N2"))["apps"]
            assert not (await status(port["N1"], "N1"))["apps"]
            await operator.close()
        finally:
            if bot is not None:
                bot.writer.close()
            for d in drivers.values():
                await d.stop()

    asyncio.run(run())


async def _more(count: Any, than: int) -> bool:
    return bool(await count() > than)
