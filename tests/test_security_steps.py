"""A relocation's steps limited to who may coordinate them (issue 27): with operator keys a
node takes a ``Prepare``, ``Switch`` or ``Rewire`` only when the move traces to a decision it
can check (:mod:`mso.protocol.warrant`): its own, the vertex's host's (its rules), a restore
after a failure it holds itself, a chain end's remap, or an operator's order carried in the
step; an ``Unprepare`` only from the move's coordinator, a ``Handover`` (and the events sent
ahead of it) only from the node the vertex leaves, a ``Prepared`` or ``HandoverDone`` only
from the move's target. A captured member used to coordinate any move of an app it took part
in: switch a producer's edge to itself and be handed a vertex's state, prepare twins, rewire
a consumer's acks to itself.

In the simulator, whose sources are proven as with node identities (a captured robot speaks
only in its own name): the line N1 - N2 - N3 - N4 - N5 runs src -> a -> b -> c -> sink, one
vertex a node, every node with the operator's key. The robot is N2: it hosts ``a``, neither
``c`` nor an end of the chain. The last test runs node drivers over TCP with node identities."""

from __future__ import annotations

import asyncio
import itertools
from typing import Any

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.client import Client, overlay_key
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore
from mso.node.driver import NodeDriver
from mso.protocol import clients, warrant
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.sim.runner import Simulation
from test_captured_robot import OPERATOR, ROGUE, apps, robot, signed
from test_security_origin import identity
from waits import patience

LINE = """
name: line
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50,
        output: runtime_vertices:Num}
  a: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  b: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  c: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N5}
edges:
  - [src, a]
  - [a, b]
  - [b, c]
  - [c, sink]
"""
NODES = ("N1", "N2", "N3", "N4", "N5")
PLACED = {"src": "N1", "a": "N2", "b": "N3", "c": "N4", "sink": "N5"}
GRANTED = 1000  # the deployment's generation (the operator's clock, ms)


def line(n6: tuple[str, ...] = ()) -> Simulation:
    """The line with the app deployed (and N6 linked to the nodes ``n6`` names, if any)."""
    nodes = (*NODES, "N6") if n6 else NODES
    net = Network(
        [NodeSpec(n) for n in nodes],
        [LinkSpec(x, y, delay_ms=1.0) for x, y in itertools.pairwise(NODES)]
        + [LinkSpec(n, "N6", delay_ms=5.0) for n in n6],
    )
    sim = Simulation(net)
    signed(sim)
    sim.request("N1", m.DeployRequest(OPERATOR.grant(LINE, GRANTED), "app.yaml"))
    sim.run_until(1.0)
    assert sim.cores["N3"].apps["line"].placed == PLACED
    return sim


def sink(sim: Simulation) -> dict[str, Any]:
    st = sim.cores["N5"].status(sim.now)["apps"]["line"]["vertices"]["sink"]
    return {"processed": st["processed"], **st["stats"]}


def flows_on(sim: Simulation, before: int) -> None:
    """The sink got 40 more events in the next second (50 a second), none twice or out of
    order."""
    sim.run_until(sim.now + 1.0)
    got = sink(sim)
    assert got["processed"] >= before + 40 and got["repeats"] == 0, got
    assert got["out_of_order"] == 0, got


def order(req: m.RelocateRequest | m.RemapRequest, at: int = 2000) -> bytes:
    return warrant.carried(warrant.sign(OPERATOR, req, at))


# the captured N2's steps of moves of c (on N4: b on N3 feeds it, the sink on N5 takes it)
ATTACKS = [
    # b's output to N2: the marker would have N4 hand c's state over to N2
    ("N3", m.Switch("line", 2, "N2", 77)),
    # a twin of c prepared on N5, waiting for a handover
    ("N5", m.Prepare("line", "c", 78)),
    # the sink told c is replaced on N2: it would ack c's events there
    ("N5", m.Rewire("line", 3, "N2", 79, False)),
    # b told c is replaced on N2: it would replay and send its events there
    ("N3", m.Rewire("line", 2, "N2", 80, True)),
    # a restore of b, alive on N3, on N4: a second instance
    ("N4", m.Prepare("line", "b", 81, restore=True, resumes=[[1, True], [2, False]])),
]


def test_a_member_cannot_coordinate_a_move_of_a_vertex_it_neither_hosts_nor_ends() -> None:
    sim = line()
    before, flowing = apps(sim), sink(sim)["processed"]
    for node, msg in ATTACKS:
        core = sim.cores[node]
        counted = core.refusals.get("move_no_warrant", 0)
        robot(sim, node, msg, src="N2")
        assert core.refusals.get("move_no_warrant", 0) == counted + 1, (msg, core.refusals)
    sim.run_until(sim.now + 0.5)
    assert apps(sim) == before  # every node: the same placement and instances
    flows_on(sim, flowing)


def test_an_operators_order_carried_in_the_steps_moves_the_vertex_through_any_node() -> None:
    """N2 coordinates the operator's relocation of c to N3: N3 (target and b's producer
    node) takes the steps on the order they carry; the same request unsigned is refused
    there, and the client told."""
    sim = line()
    flowing = sink(sim)["processed"]
    sim.request("N2", m.RelocateRequest("line", "c", target="N3"))  # no order in it
    sim.run_until(sim.now + 0.5)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.RelocateReply) and not reply.ok and "warrant" in reply.error
    assert sim.cores["N3"].refusals["move_no_warrant"] == 1
    assert all(c.apps["line"].placed == PLACED for c in sim.cores.values())

    sim.request("N2", warrant.sign(OPERATOR, m.RelocateRequest("line", "c", target="N3"), 2000))
    sim.run_until(sim.now + 0.5)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert all(c.apps["line"].placed["c"] == "N3" for c in sim.cores.values())
    assert "c" in sim.cores["N3"].apps["line"].instances
    flows_on(sim, flowing)


def test_an_order_is_taken_for_its_own_move_once_and_only_if_it_verifies() -> None:
    """The operator moves c to N3 (order at 2000) and back to N4 (at 3000), both through N2.
    N2, captured, then replays the first order in a move's steps: refused as a replay; an
    order of another vertex, one older than the deployment and one by its own key too."""
    sim = line()
    to_n3 = warrant.sign(OPERATOR, m.RelocateRequest("line", "c", target="N3"), 2000)
    sim.request("N2", to_n3)
    sim.run_until(sim.now + 0.5)
    sim.request("N2", warrant.sign(OPERATOR, m.RelocateRequest("line", "c", target="N4"), 3000))
    sim.run_until(sim.now + 0.5)
    assert all(c.apps["line"].placed == PLACED for c in sim.cores.values())
    flowing = sink(sim)["processed"]
    first = warrant.carried(to_n3)
    for node, msg, why in [
        ("N3", m.Switch("line", 2, "N3", 90, order=first), "move_order_replayed"),
        ("N3", m.Prepare("line", "c", 91, order=first), "move_order_replayed"),
        ("N5", m.Prepare("line", "c", 92, order=order(m.RelocateRequest("line", "b"))),
         "move_order_of_another_move"),
        ("N5", m.Prepare("line", "c", 93, order=order(m.RelocateRequest("line", "c"), 500)),
         "move_order_older_than_deployment"),
        ("N5", m.Prepare("line", "c", 94, order=warrant.carried(
            warrant.sign(ROGUE, m.RelocateRequest("line", "c"), 4000))),
         "move_order_not_verified"),
        ("N5", m.Prepare("line", "c", 95, order=b"\xc1"), "move_order_malformed"),
    ]:  # fmt: skip
        core = sim.cores[node]
        counted = core.refusals.get(why, 0)
        robot(sim, node, msg, src="N2")
        assert core.refusals.get(why, 0) == counted + 1, (msg, core.refusals)
    sim.run_until(sim.now + 0.5)
    assert all(c.apps["line"].placed == PLACED for c in sim.cores.values())
    assert all(not c.apps["line"].awaiting for c in sim.cores.values())
    flows_on(sim, flowing)


def test_a_prepared_instance_is_dropped_or_handed_over_only_by_its_moves_own_nodes() -> None:
    """N3 is prepared for the operator's move of c (coordinated by N2, leaving N4): N5 can
    neither drop it (``Unprepare``) nor hand it a state or events of its own; the
    coordinator can drop it."""
    sim = line()
    core = sim.cores["N3"]
    prepare = m.Prepare("line", "c", 55, order=order(m.RelocateRequest("line", "c", "", "N3")))
    robot(sim, "N3", prepare, src="N2")
    sim.run_until(sim.now + 0.1)
    assert "c" in core.apps["line"].awaiting
    forged = m.Handover("line", "c", 55, b"\x80", {2: [0, 0]}, {3: [0, 0, [], {}]}, 0, 0)
    for msg, why in [
        (m.Unprepare("line", "c", 55), "unprepare_not_by_its_coordinator"),
        (m.HandoverEvents("line", "c", 55, 3, 0, [b"x"]), "handover_not_from_its_host"),
        (forged, "handover_not_from_its_host"),
    ]:
        counted = core.refusals.get(why, 0)
        robot(sim, "N3", msg, src="N5")
        assert core.refusals.get(why, 0) == counted + 1, (msg, core.refusals)
        assert "c" in core.apps["line"].awaiting and "c" not in core.apps["line"].instances
    robot(sim, "N3", m.Unprepare("line", "c", 55), src="N2")
    assert "c" not in core.apps["line"].awaiting


def test_a_coordinator_hears_a_moves_answers_only_from_its_target() -> None:
    sim = line()
    sim.request("N2", warrant.sign(OPERATOR, m.RelocateRequest("line", "c", target="N3"), 2000))
    coordinator = sim.cores["N2"]
    (rid,) = [p.pid for p in coordinator.open() if p.name == "relocation"]
    for msg, why in [
        (m.Prepared("line", "c", rid, "N3", "refused: no"), "prepared_not_by_its_target"),
        (m.HandoverDone("line", "c", rid, "N5"), "handover_done_not_by_its_target"),
    ]:
        robot(sim, "N2", msg, src="N5")
        assert coordinator.refusals.get(why) == 1, coordinator.refusals
    sim.run_until(sim.now + 0.5)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert all(c.apps["line"].placed["c"] == "N3" for c in sim.cores.values())


def test_a_prepares_view_moves_only_what_its_coordinator_may_tell() -> None:
    """N2 moves its own vertex a to N3 (its host's word: warranted), with a view saying c
    runs on N2 at a newer version: N3 takes the prepare, not the lie."""
    sim = line()
    core = sim.cores["N3"]
    lie = dict(PLACED, c="N2")
    robot(sim, "N3", m.Prepare("line", "a", 60, placed=lie, versions={"c": 9}), src="N2")
    dep = core.apps["line"]
    assert "a" in dep.awaiting  # the move itself is the host's to make
    assert dep.placed["c"] == "N4" and dep.versions.get("c", 0) == 0
    robot(sim, "N3", m.Unprepare("line", "a", 60), src="N2")


def test_an_order_verifies_by_an_operator_or_a_command_client_it_certified() -> None:
    ops = {OPERATOR.id: OPERATOR.public}
    req = m.RemapRequest("line", [0])
    assert warrant.verify(warrant.sign(OPERATOR, req, 5), ops) == ""
    private = Ed25519PrivateKey.generate()
    for role, revoked, ok in [
        ("command", frozenset[str](), True),
        ("read", frozenset[str](), False),
        ("command", None, False),  # its key revoked
    ]:
        cert = clients.certify(OPERATOR, "ops-laptop", private.public_key(), 1000, role)
        client = clients.ClientIdentity(private, cert)
        signed_req = warrant.sign(client.signer, req, 5, msgspec.msgpack.encode(cert))
        gone = revoked if revoked is not None else frozenset({cert.key_id})
        assert (warrant.verify(signed_req, ops, gone) == "") is ok, role
    # the signature covers the request: another chain is another order
    changed = msgspec.structs.replace(warrant.sign(OPERATOR, req, 5), chains=[1])
    assert warrant.verify(changed, ops) != ""


def test_a_restore_after_a_failure_every_node_holds_goes_through() -> None:
    """The decisions a node can check itself: c's node N4 dies (N6 links N3 and N5 around
    it), the recovery restores c on N6; every node takes every step, and the stream goes on
    with nothing twice."""
    sim = line(n6=("N3", "N5"))
    sim.kill("N4")
    sim.run_until(sim.now + 6.0)
    alive = [c for n, c in sim.cores.items() if n != "N4"]
    assert all(c.apps["line"].placed == dict(PLACED, c="N6") for c in alive)
    assert not any(k.startswith("move_") for c in alive for k in c.refusals)
    flows_on(sim, sink(sim)["processed"])


# -- over TCP, with node identities: a captured node's own, proven steps ---------------------
HOST = "127.0.0.1"
KEY = overlay_key("steps")
PIPE = (
    "name: pipe\n"
    "planner: paper\n"
    "vertices:\n"
    "  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, "
    "output: runtime_vertices:Num}\n"
    "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}\n"
    "  sink: {code: runtime_vertices:Recorder, pinned: N4}\n"
    "edges:\n"
    "  - [src, mid]\n"
    "  - [mid, sink]\n"
)


def test_over_tcp_a_captured_node_cannot_switch_an_edge_and_an_operators_order_can() -> None:
    """N1 - N2 - N3 - N4 with node identities, pipe src (N1) -> mid -> sink (N4). The captured
    N5, a proven neighbour of N1 hosting nothing, sends N1 a Switch of src's edge to itself
    in its own name: refused, counted, nothing moves; and mid's host a marker of that edge
    naming itself: held, mid handed to nobody. The operator then relocates mid through
    the node that neither hosts it nor an end of its chain, with the order its client signs:
    N1 and the target take the steps on it, and the stream goes on."""

    async def run() -> None:
        names = ("N1", "N2", "N3", "N4", "N5")
        drivers: dict[str, NodeDriver] = {}
        for n in names:
            auth = Authority.configure([OPERATOR.public_text()])
            core = NodeCore(n)
            ident = identity(n, OPERATOR)
            drivers[n] = NodeDriver(core, HOST, 0, KEY, authority=auth, identity=ident)
            await drivers[n].start()
        port = {n: d.transport.port for n, d in drivers.items()}
        links = {"N1": ["N2", "N5"], "N2": ["N1", "N3"], "N3": ["N2", "N4"], "N4": ["N3"]}
        links["N5"] = ["N1"]
        hops = {
            "N1": {"N2": ["N2", 1], "N3": ["N2", 2], "N4": ["N2", 3], "N5": ["N5", 1]},
            "N2": {"N1": ["N1", 1], "N3": ["N3", 1], "N4": ["N3", 2], "N5": ["N1", 2]},
            "N3": {"N2": ["N2", 1], "N4": ["N4", 1], "N1": ["N2", 2], "N5": ["N2", 3]},
            "N4": {"N3": ["N3", 1], "N2": ["N3", 2], "N1": ["N3", 3], "N5": ["N3", 4]},
            "N5": {"N1": ["N1", 1], "N2": ["N1", 2], "N3": ["N1", 3], "N4": ["N1", 4]},
        }
        for n in names:
            specs = {p: [HOST, port[p], None, 0.0, 0.0] for p in links[n]}
            drivers[n].apply_links(m.LinkState(1, specs, hops[n]))
        try:
            operator = await Client(HOST, port["N1"], KEY, signer=OPERATOR).connect()
            reply = await operator.call(m.DeployRequest(PIPE, "pipe.yaml"), patience(20))
            assert isinstance(reply, m.DeployReply) and reply.ok, reply
            await operator.close()
            placed = dict(reply.placement)
            mid = placed["mid"]
            assert mid in ("N2", "N3")
            other = "N3" if mid == "N2" else "N2"  # neither hosts mid nor an end of the chain
            app = ("N1", "N2", "N3", "N4")
            loop = asyncio.get_running_loop()

            async def until(check: Any, what: str) -> None:
                deadline = loop.time() + patience(20.0)
                while not check():  # polling: no event says it
                    assert loop.time() < deadline, f"timed out waiting for {what}"
                    await asyncio.sleep(0.05)

            def sunk() -> int:
                return int(drivers["N4"].core.instances("pipe")["sink"].processed)

            def refused(n: str, why: str) -> int:
                return drivers[n].core.refusals.get(why, 0)

            await until(lambda: sunk() > 20, "events at the sink")
            # the captured N5, in its own (proven) name: src's edge to N5
            captured = drivers["N5"].transport
            captured.send("N1", m.wrap("N5", "N1", m.Switch("pipe", 0, "N5", 7)), m.CONTROL)
            await until(lambda: refused("N1", "move_no_warrant") == 1, "the Switch refused")
            # a marker of src's edge naming N5, to mid's host (its own, signed, relayed by
            # N1): no move of mid is warranted there, so it waits and hands nothing over
            captured.send(mid, m.wrap("N5", mid, m.Marker("pipe", 0, 0, 9, "N5")), m.MARKER)
            await until(lambda: drivers[mid].core.relocator.leaving.held == 1, "the marker held")
            flowing = sunk()
            await until(lambda: sunk() > flowing + 20, "events to go on flowing")
            held = [d.core.apps["pipe"] for d in drivers.values() if "pipe" in d.core.apps]
            assert all(dep.placed == placed for dep in held)
            assert "mid" in drivers[mid].core.apps["pipe"].instances

            # the operator, through the node that neither hosts mid nor an end of its chain
            client = await Client(HOST, port[other], KEY, signer=OPERATOR).connect()
            reply = await client.call(m.RelocateRequest("pipe", "mid", target=other), patience(20))
            await client.close()
            assert isinstance(reply, m.RelocateReply) and reply.ok, reply
            await until(
                lambda: all(drivers[n].core.apps["pipe"].placed["mid"] == other for n in app),
                "the app's nodes to learn the move",
            )
            flowing = sunk()
            await until(lambda: sunk() > flowing + 20, "events to go on flowing after it")
            st = drivers["N4"].core.status(loop.time())["apps"]["pipe"]["vertices"]["sink"]
            stats = st["stats"]
            assert stats["repeats"] == 0 and stats["out_of_order"] == 0, stats
            assert not any(refused(n, "move_no_warrant") for n in names if n != "N1")
        finally:
            for d in drivers.values():
                await d.stop()

    asyncio.run(run())


# -- what a sync may tell (AppSync): any member may send one ---------------------------------
LIES = [
    ("N5", {"c": "N2"}),  # the sink would ack c's events to N2
    ("N4", {"sink": "N2"}),  # c would send its output to N2 (sink is pinned to N5)
    ("N3", {"c": "N2"}),  # b would send its output to N2
]


def sync(sim: Simulation, placed: dict[str, str]) -> m.AppSync:
    dep = sim.cores["N1"].apps["line"]
    return m.AppSync("line", dep.origin, dep.document, dep.epoch, dict(PLACED, **placed))


def test_a_sync_moves_nothing_its_sender_may_not_tell() -> None:
    """The captured N2 syncs nodes that hold the app, saying vertices run on N2 (its own,
    first-hand word): each keeps its view, as it would against a Moved from N2."""
    sim = line()
    flowing = sink(sim)["processed"]
    for node, lie in LIES:
        robot(sim, node, sync(sim, lie), src="N2")
        assert sim.cores[node].apps["line"].placed == PLACED, (node, lie)
    flows_on(sim, flowing)


def test_a_node_that_learns_an_app_from_a_sync_keeps_its_pinned_vertices_on_their_pins() -> None:
    """N6 (hosting nothing, so synced by nobody when it restarts) is synced first by the
    captured N2, placing c and the pinned sink on N2: the sink stays on its pin; c is placed
    on N2's word for now (a node with no view has nothing else), as hearsay, kept on a tie
    with one member's truth; the word of two other members puts c back on N4, and from then
    on N2's lie is weighed as any member's."""
    sim = line(n6=("N5",))
    sim.kill("N6")
    sim.run_until(sim.now + 2.0)
    sim.revive("N6")
    signed(sim, "N6")
    robot(sim, "N6", sync(sim, {"c": "N2", "sink": "N2"}), src="N2")
    dep = sim.cores["N6"].apps["line"]
    assert dep.placed == dict(PLACED, c="N2")
    assert set(dep.hearsay) == {"a", "b", "c"}
    robot(sim, "N6", sync(sim, {}), src="N5")  # the truth, from one member: a tie for c
    assert dep.placed == dict(PLACED, c="N2")
    robot(sim, "N6", sync(sim, {}), src="N1")  # and a second
    assert dep.placed == PLACED and not dep.hearsay
    robot(sim, "N6", sync(sim, {"c": "N2"}), src="N2")
    assert dep.placed == PLACED
