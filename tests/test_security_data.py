"""End-to-end integrity of the data plane (issue 27): with node identities every data frame
carries a tag by a key only its source and destination hold (X25519 between their certified
keys), so a relay that alters an app's events or acks, or injects its own in another node's
name, is detected at the destination: dropped and counted, never delivered."""

from __future__ import annotations

import asyncio

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.protocol import dataseal
from mso.protocol import messages as m
from test_captured_robot import overlay, robot, sunk
from test_security_origin import Received, link_line, proven_nodes
from waits import patience


def test_the_pair_key_is_the_two_ends_alone() -> None:
    keys = {n: Ed25519PrivateKey.generate() for n in ("A", "B", "C")}
    pub = {n: k.public_key().public_bytes_raw() for n, k in keys.items()}
    for k in keys.values():  # the X25519 key of a signing key: the same point, converted
        want = dataseal.x25519_private(k).public_key().public_bytes_raw()
        assert dataseal.x25519_public(k.public_key().public_bytes_raw()).public_bytes_raw() == want
    a, b, c = (dataseal.Pairs(keys[n], n) for n in ("A", "B", "C"))
    assert a.key("B", pub["B"]) == b.key("A", pub["A"])  # both ends derive it
    assert c.key("A", pub["A"]) != a.key("B", pub["B"])  # a third node holds another
    env = m.unwrap(m.wrap("A", "B", m.Data("app", 0, 1, 7, [b"event"])))
    env.origin = a.tag(env, pub["B"])
    assert b.holds(env, pub["A"])
    env.body = msgspec.Raw(m.encode(m.Data("app", 0, 1, 7, [b"other"])))
    assert not b.holds(env, pub["A"])  # altered on the way
    forged = m.unwrap(m.wrap("A", "B", m.Data("app", 0, 1, 8, [b"x"])))
    forged.origin = c.tag(m.unwrap(m.wrap("C", "B", m.Data("app", 0, 1, 8, [b"x"]))), pub["B"])
    assert not b.holds(forged, pub["A"])  # C's tag does not pass for A's


def test_over_tcp_a_relay_cannot_alter_or_inject_another_nodes_data() -> None:
    """N1 - N2 - N3, every link proven; N1's events reach N3 through N2. N2 (captured)
    alters one of N1's frames, injects events in N1's name (untagged, or tagged by itself),
    and sends events in its own name: N3 takes N1's and N2's own, refuses the rest, counted."""

    async def run() -> tuple[list[tuple[str, m.Message]], int, int]:
        names = ("N1", "N2", "N3")
        _, views, nets = proven_nodes(names)
        receive = Received()
        got, arrived = receive.got, receive.arrived

        heard = asyncio.Event()
        nets["N3"].set_receiver(receive)
        nets["N1"].set_receiver(lambda src, msg: heard.set())
        for n in names:
            await nets[n].start()
        try:
            link_line(views, nets)
            # the ends learn each other's certificates from a signed control frame each
            nets["N3"].send("N1", m.wrap("N3", "N1", m.PlacementQuery("pipe", 1)), m.CONTROL)
            nets["N1"].send("N3", m.wrap("N1", "N3", m.PlacementQuery("pipe", 2)), m.CONTROL)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            await asyncio.wait_for(heard.wait(), patience(10.0))
            got.clear()
            arrived.clear()
            genuine = m.Data("pipe", 0, 1, 0, [b"from N1"])
            nets["N1"].send("N3", m.wrap("N1", "N3", genuine), m.DATA)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            relay = nets["N2"].peers["N3"]
            assert relay.link is not None
            one = m.wrap("N1", "N3", m.Data("pipe", 0, 1, 1, [b"a"]))
            tagged = nets["N1"].trust.seal("N3", one)
            altered = m.unwrap(tagged)
            altered.body = msgspec.Raw(m.encode(m.Data("pipe", 0, 1, 1, [b"altered by N2"])))
            forgeries = [
                m.rewrap(altered),
                m.wrap("N1", "N3", m.Data("pipe", 0, 1, 2, [b"injected"])),  # untagged
                nets["N2"].trust.seal("N3", m.wrap("N1", "N3", m.Data("pipe", 0, 1, 3, [b"i"]))),
            ]
            for payload in forgeries:
                relay.link.send(payload, m.DATA)
            arrived.clear()  # and its own events, in its own name: proven by the link
            nets["N2"].send("N3", m.wrap("N2", "N3", m.Data("pipe", 1, 1, 0, [b"N2's"])), m.DATA)
            await asyncio.wait_for(arrived.wait(), patience(10.0))
            counters = nets["N3"].counters
            return got, counters.frames_data_refused, nets["N1"].counters.data_untagged
        finally:
            for n in names:
                await nets[n].close()

    got, refused, untagged = asyncio.run(run())
    assert got == [
        ("N1", m.Data("pipe", 0, 1, 0, [b"from N1"])),
        ("N2", m.Data("pipe", 1, 1, 0, [b"N2's"])),
    ]
    assert refused == 3 and untagged == 0


def test_a_node_hosting_nothing_of_an_app_cannot_send_or_ack_its_events() -> None:
    """With operator keys, an app's events and acks are taken only from a node that hosts
    part of it: N9, hosting nothing of ``pipe``, sends the sink events and acks mid's edge in
    its own name — refused, counted, nothing delivered or trimmed; the stream goes on whole."""
    sim = overlay()
    epoch = sim.cores["N3"].apps["pipe"].epoch
    sent = [
        ("N3", m.Data("pipe", 1, epoch, 0, [b"injected"])),
        ("N2", m.Ack("pipe", 1, epoch, 10**6)),
    ]
    for node, msg in sent:
        refused = sim.cores[node].refusals.get("data_not_from_a_member", 0)
        robot(sim, node, msg, src="N9")
        assert sim.cores[node].refusals.get("data_not_from_a_member", 0) == refused + 1
    flowing = sunk(sim)
    sim.run_until(sim.now + 1.0)
    stats = sim.cores["N3"].status(sim.now)["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert sunk(sim) >= flowing + 40 and stats["repeats"] == 0 and stats["out_of_order"] == 0
