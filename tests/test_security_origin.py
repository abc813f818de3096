"""End-to-end origin (issue 27, Build 2): with node identities, what a node originates carries
its signature, so a relay cannot write another node's name as a message's source, and a node
speaks only for itself (a failure claim is its own, never a witness's it cannot show)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.client import overlay_key
from mso.net.limits import Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.protocol import messages as m
from mso.protocol import origin
from mso.protocol.authority import Authority, Signer
from mso.protocol.identity import Identity, certify
from waits import patience

HOST = "127.0.0.1"
KEY = overlay_key("k")
OPERATOR, ROGUE = Signer(), Signer()
OPS = {OPERATOR.id: OPERATOR.public}


def identity(node: str, operator: Signer = OPERATOR) -> Identity:
    private = Ed25519PrivateKey.generate()
    return Identity(private, certify(operator, node, private.public_key(), 1000))


def proven_nodes(
    names: tuple[str, ...],
) -> tuple[dict[str, Identity], dict[str, EmulatorRoutes], dict[str, TcpTransport]]:
    """Transports for ``names``, each with its identity and the operator's key (not started;
    called on the loop)."""
    ids = {n: identity(n) for n in names}
    views = {n: EmulatorRoutes(n) for n in names}
    auth = {n: Authority.configure([OPERATOR.public_text()]) for n in names}
    nets = {
        n: TcpTransport(n, HOST, 0, KEY, views[n], Limits(), auth[n], identity=ids[n])
        for n in names
    }
    return ids, views, nets


class Received:
    """A transport's receiver for a test: what arrived, in order, and an event set on each."""

    def __init__(self) -> None:
        self.got: list[tuple[str, m.Message]] = []
        self.arrived = asyncio.Event()

    def __call__(self, src: str, msg: m.Message) -> None:
        self.got.append((src, msg))
        self.arrived.set()


def link_line(views: dict[str, EmulatorRoutes], nets: dict[str, TcpTransport]) -> None:
    """N1 - N2 - N3 in the transports' views (started: their ports are known)."""

    def spec(n: str) -> list[object]:
        return [HOST, nets[n].port, None, 0.0, 0.0]

    views["N1"].apply(m.LinkState(1, {"N2": spec("N2")}, {"N2": ["N2", 1], "N3": ["N2", 2]}))
    links = {"N1": spec("N1"), "N3": spec("N3")}
    views["N2"].apply(m.LinkState(1, links, {"N1": ["N1", 1], "N3": ["N3", 1]}))
    views["N3"].apply(m.LinkState(1, {"N2": spec("N2")}, {"N2": ["N2", 1], "N1": ["N2", 2]}))


def now_ms() -> int:
    return time.time_ns() // 1_000_000


def test_an_origin_proves_its_source_and_nothing_else() -> None:
    n1, n2 = identity("N1"), identity("N2")
    claim = m.wrap("N1", "N3", m.NodeDown("N4", "N1", 5))
    signed = origin.sign(n1, claim, now_ms())
    v = origin.Verifier()
    assert v.check(m.unwrap(signed), now_ms(), OPS) is None
    assert v.check(m.unwrap(claim), now_ms(), OPS) == "no origin signature"
    env = m.unwrap(signed)  # a relay alters the body, the destination, the source
    env.body = msgspec.Raw(m.encode(m.NodeDown("N5", "N1", 5)))
    assert "does not verify" in (v.check(env, now_ms(), OPS) or "")
    env = m.unwrap(signed)
    env.dst = "N6"
    assert "does not verify" in (v.check(env, now_ms(), OPS) or "")
    env = m.unwrap(signed)
    env.ttl = 3  # the hop count is not signed: relays count it down
    assert v.check(env, now_ms(), OPS) is None
    forged = m.unwrap(origin.sign(n2, m.wrap("N1", "N3", m.NodeDown("N4", "N1")), now_ms()))
    assert "a certificate for 'N2', not 'N1'" in (v.check(forged, now_ms(), OPS) or "")
    rogue = origin.sign(identity("N1", ROGUE), claim, now_ms())
    assert "unknown key" in (v.check(m.unwrap(rogue), now_ms(), OPS) or "")
    revoked = {n1.cert.key_id}
    assert "revoked" in (v.check(m.unwrap(signed), now_ms(), OPS, revoked) or "")
    stale = origin.sign(n1, claim, now_ms() - origin.WINDOW_MS - 1000)
    assert "off this node's clock" in (v.check(m.unwrap(stale), now_ms(), OPS) or "")
    env = m.unwrap(signed)
    env.origin = b"\x91" * 100_000  # nested deep, or not an origin at all
    assert "does not decode" in (v.check(env, now_ms(), OPS) or "")
    assert v.check(m.unwrap(signed), now_ms(), {}) is not None  # the operator withdrawn
    assert m.unwrap(m.rewrap(m.unwrap(signed))).origin == m.unwrap(signed).origin


def test_a_node_speaks_only_for_itself() -> None:
    said = origin.attribute("N2", m.NodeDown("N4", "N1", 7, witness="N5"))
    assert said == m.NodeDown("N4", "N2", 7)  # its own claim, without a witness it cannot show
    beat = m.Heartbeat("N2", 1, news=[m.NodeDown("N4", "N1", 7, "N5")])
    said = origin.attribute("N2", beat)
    assert isinstance(said, m.Heartbeat) and said.news == [m.NodeDown("N4", "N2", 7)]
    assert "heartbeat of 'N1'" in str(origin.attribute("N2", m.Heartbeat("N1", 1)))
    assert "Moved" in str(origin.attribute("N2", m.Moved("a", "v", "N1", incarnation=9)))
    relayed_news = m.Moved("a", "v", "N1", incarnation=-1)  # an old host's word after handover
    assert origin.attribute("N2", relayed_news) == relayed_news
    own = m.NodeDown("N4", "N2", 7)
    assert origin.attribute("N2", own) is own


def test_only_a_node_itself_says_it_is_back() -> None:
    """A captured member announcing a dead node back (NodeUp) would have its vertices' hosts
    treat it as alive; with identities only the node's own word (its signed beat) does."""
    assert "only 'N4'" in str(origin.attribute("N2", m.NodeUp("N4", 9)))
    own = m.NodeUp("N2", 9)
    assert origin.attribute("N2", own) is own


def test_over_tcp_a_relay_cannot_forge_or_alter_another_nodes_claims() -> None:
    """N1 - N2 - N3, every link proven. N1's signed claim reaches N3 through N2 as N1's; N2
    (captured) writing N1's name on a claim of its own, unsigned or signed by itself, or
    altering N1's signed claim, gets nothing taken and each counted; its claim in its own
    name naming another detector and a witness is taken as its own, witness dropped."""

    async def run() -> tuple[list[tuple[str, m.Message]], int]:
        names = ("N1", "N2", "N3")
        ids, views, nets = proven_nodes(names)
        receive = Received()
        got, arrived = receive.got, receive.arrived

        nets["N3"].set_receiver(receive)
        for n in names:
            await nets[n].start()
        try:
            link_line(views, nets)
            # the genuine claim: N1 originates it, N2 relays it
            nets["N1"].send("N3", m.wrap("N1", "N3", m.NodeDown("N4", "N1", 1)), m.CONTROL)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            relay = nets["N2"].peers["N3"]
            assert relay.link is not None
            genuine = origin.sign(
                ids["N1"], m.wrap("N1", "N3", m.NodeDown("N4", "N1", 2)), now_ms()
            )
            altered = m.unwrap(genuine)
            altered.body = msgspec.Raw(m.encode(m.NodeDown("N5", "N1", 2)))
            forgeries = [
                m.wrap("N1", "N3", m.NodeDown("N5", "N1", 3)),  # unsigned, in N1's name
                origin.sign(ids["N2"], m.wrap("N1", "N3", m.NodeDown("N5", "N1")), now_ms()),
                m.rewrap(altered),
            ]
            for payload in forgeries:
                relay.link.send(payload, m.CONTROL)
            # and in its own name, naming another detector and a witness
            arrived.clear()
            nets["N2"].send("N3", m.wrap("N2", "N3", m.NodeDown("N5", "N1", 4, "N4")), m.CONTROL)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            return got, nets["N3"].counters.frames_origin_refused
        finally:
            for n in names:
                await nets[n].close()

    got, refused = asyncio.run(run())
    assert got == [("N1", m.NodeDown("N4", "N1", 1)), ("N2", m.NodeDown("N5", "N2", 4))]
    assert refused == 3


def test_a_revocation_verifies_on_its_own_and_is_held_once() -> None:
    from mso.protocol.revocation import Revocations

    held = Revocations()
    good = OPERATOR.revoke_node("a1b2c3d4e5f6", 5)
    assert held.take(m.RevokeNode("a1b2c3d4e5f6"), OPS) is not None  # unsigned
    assert "no operator's" in str(held.take(ROGUE.revoke_node("a1b2c3d4e5f6", 5), OPS))
    forged = m.RevokeNode("ffffffffffff", good.at, good.key, good.sig)  # another key's id
    assert "does not match" in str(held.take(forged, OPS))
    assert held.take(good, {}) == "no operator keys on this node: nothing to revoke"
    assert held.take(good, OPS) is None and held.keys() == {"a1b2c3d4e5f6"}
    assert held.take(good, OPS) == ""  # held already: not passed on again


def test_over_tcp_an_operator_revocation_reaches_every_node_and_cuts_the_revoked_one() -> None:
    """N1 - N2 - N3, every link proven. An operator's revocation of N3's key, sent to N1 by a
    client, reaches N2 through N1, which closes its link to N3 and refuses it from then on;
    a member's unsigned revocation is refused by a node and goes nowhere. A node that links
    later (N4 to N2) is told the revocations N2 holds once its link is proven."""
    from mso.client import Client

    async def run() -> tuple[set[str], set[str], set[str], int, int, bool]:
        names = ("N1", "N2", "N3", "N4")
        ids, views, nets = proven_nodes(names)
        for n in names:
            await nets[n].start()

        def spec(n: str) -> list[object]:
            return [HOST, nets[n].port, None, 0.0, 0.0]

        async def until(what: Callable[[], bool]) -> None:
            for _ in range(int(patience(10.0) / 0.01)):  # polling: no event says it
                if what():
                    return
                await asyncio.sleep(0.01)
            raise AssertionError("not in time")

        def proven(a: str, b: str) -> bool:
            ca, cb = nets[a].peers.get(b), nets[b].peers.get(a)
            return ca is not None and cb is not None and ca.verified and cb.verified

        try:
            line = {"N1": ["N2"], "N2": ["N1", "N3"], "N3": ["N2"]}
            for n, ns in line.items():
                views[n].apply(m.LinkState(1, {p: spec(p) for p in ns}, {p: [p, 1] for p in ns}))
            await until(lambda: proven("N1", "N2") and proven("N2", "N3"))
            # a member (N2, on its own proven link) passes an unsigned revocation of N1's key
            member_link = nets["N2"].peers["N3"]
            member_link.send_message("N3", m.RevokeNode(ids["N1"].cert.key_id))
            client = Client(HOST, nets["N1"].port, KEY, "op", signer=OPERATOR)
            await client.connect()
            reply = await client.call(m.RevokeNode(ids["N3"].cert.key_id), patience(10.0))
            await client.close()
            assert reply == m.RevokeNode(ids["N3"].cert.key_id)
            await until(lambda: "N3" not in nets["N2"].peers)
            refused = nets["N2"].connection_counters.identity_refused
            views["N4"].apply(m.LinkState(2, {"N2": spec("N2")}, {"N2": ["N2", 1]}))
            views["N2"].apply(
                m.LinkState(
                    2,
                    {"N1": spec("N1"), "N3": spec("N3"), "N4": spec("N4")},
                    {"N1": ["N1", 1], "N3": ["N3", 1], "N4": ["N4", 1]},
                )
            )
            await until(lambda: bool(nets["N4"].trust.revocations.keys()))
            return (
                nets["N1"].trust.revocations.keys(),
                nets["N2"].trust.revocations.keys(),
                nets["N4"].trust.revocations.keys(),
                refused,
                nets["N3"].authority.refused,
                proven("N2", "N3"),
            )
        finally:
            for n in names:
                await nets[n].close()

    n1, n2, n4, refused, n3_refused, linked = asyncio.run(run())
    assert len(n1) == 1 and n1 == n2 == n4  # N3's key, everywhere; N1's never
    assert refused >= 1 and not linked  # N2 cut N3 and refuses it since
    assert n3_refused >= 1  # the member's unsigned revocation, refused at N3


def test_what_a_neighbour_can_make_a_node_check_is_budgeted() -> None:
    """Each check is a signature's verification (about 120 us): a neighbour handing over
    frames in others' names gets at most CHECKS_PER_S of them checked a second (a second's
    burst), so its flood cannot hold the loop past a neighbour's liveness window; its own
    frames, proved by the link, are not checked and not budgeted."""
    from mso.net.base import Counters
    from mso.net.limits import ConnectionCounters
    from mso.net.trust import CHECK_BYTES, CHECKS_PER_S, Trust

    counters = Counters()
    trust = Trust(identity("N1"), Authority.configure([OPERATOR.public_text()]), counters,
                  ConnectionCounters())  # fmt: skip
    forged = m.unwrap(m.wrap("N5", "N1", m.NodeDown("N4", "N5")))
    own = m.unwrap(m.wrap("N2", "N1", m.NodeDown("N4", "N2")))
    for _ in range(2000):
        assert trust.origin("N2", forged, m.NodeDown("N4", "N5"), 0.0) is None
    assert counters.frames_origin_refused == CHECKS_PER_S  # checked: the burst
    assert counters.frames_dropped_rate == 2000 - CHECKS_PER_S  # past it: dropped unchecked
    assert trust.origin("N2", own, m.NodeDown("N4", "N2"), 0.0) == m.NodeDown("N4", "N2")
    trust.origin("N3", forged, m.NodeDown("N4", "N5"), 0.0)  # another neighbour: its own
    assert counters.frames_origin_refused == CHECKS_PER_S + 1
    trust.origin("N2", forged, m.NodeDown("N4", "N5"), 0.1)  # refilled at CHECKS_PER_S
    assert counters.frames_origin_refused == CHECKS_PER_S + 2
    # a check hashes the whole frame: a big one takes a check per CHECK_BYTES it holds, so a
    # flood of 8 MiB frames (18 ms to check each) gets no more of the loop than small ones
    big = m.ChainPlaced("ghost", 0, {"k": "x" * (8 << 20)})
    bulk = m.unwrap(m.wrap("N5", "N1", big))
    refused = counters.frames_origin_refused
    for _ in range(20):
        trust.origin("N4", bulk, big, 0.0)  # a fresh neighbour: a whole burst
    per_frame = 1 + len(bulk.body) // CHECK_BYTES
    assert counters.frames_origin_refused - refused == CHECKS_PER_S // per_frame == 3


def test_over_tcp_a_neighbour_cannot_have_a_relay_speak_in_the_relays_name() -> None:
    """N1 - N2 - N3, every link proven. N1 (captured) hands N2 frames written in N2's name for
    N3: relayed, N3 would take them as N2's own word, proven by N2's link (a claim, a host's
    Moved, an event). N2 refuses its own name from a neighbour, counted; N1's frames in its
    own name still pass."""

    async def run() -> tuple[list[tuple[str, m.Message]], int]:
        names = ("N1", "N2", "N3")
        _, views, nets = proven_nodes(names)
        got: list[tuple[str, m.Message]] = []
        first, arrived = asyncio.Event(), asyncio.Event()

        def receive(src: str, msg: m.Message) -> None:
            got.append((src, msg))
            if isinstance(msg, m.NodeDown):
                (arrived if msg.node == "N9" else first).set()

        nets["N3"].set_receiver(receive)
        for n in names:
            await nets[n].start()
        try:
            link_line(views, nets)
            nets["N1"].send("N3", m.wrap("N1", "N3", m.NodeDown("N8", "N1", 1)), m.CONTROL)
            await asyncio.wait_for(first.wait(), patience(10.0))  # the links are up
            relay = nets["N1"].peers["N2"]
            assert relay.link is not None
            for msg in (m.NodeDown("N4", "N2", 1), m.Moved("pipe", "mid", "N2", 1, 9)):
                relay.link.send(m.wrap("N2", "N3", msg), m.CONTROL)
            relay.link.send(m.wrap("N2", "N3", m.Data("pipe", 1, 1, 0, [b"x"])), m.DATA)
            nets["N1"].send("N3", m.wrap("N1", "N3", m.NodeDown("N9", "N1", 1)), m.CONTROL)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            return got, nets["N2"].counters.frames_origin_refused
        finally:
            for n in names:
                await nets[n].close()

    got, refused = asyncio.run(run())
    assert got == [("N1", m.NodeDown("N8", "N1", 1)), ("N1", m.NodeDown("N9", "N1", 1))]
    assert refused == 3
