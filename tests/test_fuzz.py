"""Fuzzing the wire: the frame decoder, the message decoder and every message handler.

Random bytes, truncations, absurd lengths, and valid frames with the wrong meaning (a
relocation of a vertex that is not there, a marker out of order, a handover nobody asked for):
nothing raises out of a decoder or a node, buffers stay bounded, and what a node refuses is
counted. ``bench/fuzz.py`` runs a million frames against a node process and reports its RSS.
"""

from __future__ import annotations

import contextlib
import random
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.node.core import NodeCore
from mso.protocol import messages as m
from mso.protocol import wirefuzz
from mso.protocol.framing import TAG_BYTES, FrameCodec, FramingError, psk_from_text
from mso.protocol.procedures.relocation.new_host import _numbering
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

KEY = psk_from_text("fuzz")
MAX_FRAME = 4096


def confirmed_pair() -> tuple[FrameCodec, FrameCodec]:
    a, b = FrameCodec(KEY, max_frame=MAX_FRAME), FrameCodec(KEY, max_frame=MAX_FRAME)
    _, fb = b.feed(a.hello())
    _, fa = a.feed(b.hello())
    a.feed(fb)
    b.feed(fa)
    return a, b


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=300), max_size=8), st.booleans())
def test_frame_decoder_random_bytes(chunks: list[bytes], after_handshake: bool) -> None:
    if after_handshake:
        _, b = confirmed_pair()
    else:
        b = FrameCodec(KEY, max_frame=MAX_FRAME)
    try:
        for chunk in chunks:
            b.feed(chunk)
            assert len(b._buf) <= 4 + TAG_BYTES + MAX_FRAME  # never more than one frame held
    except FramingError:
        pass  # the stream is not ours: the connection is closed
    assert b.accepted == 0  # nothing forged was delivered


@settings(max_examples=200, deadline=None)
@given(st.randoms(use_true_random=False), st.integers(1, 20))
def test_frame_decoder_truncated_flipped_and_oversized(rng: random.Random, n: int) -> None:
    a, b = confirmed_pair()
    stream = bytearray()
    sent = []
    for _ in range(n):
        p = wirefuzz.payload(rng, "N2", "N1")[:MAX_FRAME]
        sent.append(p)
        stream += a.seal(p)
    kind = rng.randrange(4)
    if kind == 1:  # flip one bit somewhere
        stream[rng.randrange(len(stream))] ^= 1 << rng.randrange(8)
    elif kind == 2:  # an absurd length
        stream[0:4] = rng.choice([b"\xff\xff\xff\xff", b"\x00\x00\x00\x00", b"\x7f\x00\x00\x00"])
    got: list[bytes] = []
    try:
        pos = 0
        while pos < len(stream):  # split at random points
            step = rng.randint(1, 200)
            got += b.feed(bytes(stream[pos : pos + step]))[0]
            pos += step
    except FramingError:
        assert kind == 2 or kind == 1
    if kind in (0, 3):
        assert got == sent
    assert all(p in sent for p in got)  # whatever arrived was sent, nothing made up
    assert b.accepted + b.rejected <= n


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_message_decoder_random_bytes(data: bytes) -> None:
    for decode in (m.decode, m.unwrap):
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
            decode(data)


@pytest.mark.parametrize("hops", [0, -3, 65, 10**6])
def test_figures_claiming_an_impossible_route_length_do_not_decode(hops: int) -> None:
    """The rules' estimate charges relays by the hop counts neighbours report: a count no
    route can have is refused with the frame, not believed."""
    power = (0.0, 0.0, 0.0, 0.0)
    good = m.Figures(1.0, 0.0, 0.0, None, None, power, {"N1": 1, "N3": 64})
    assert m.decode(m.encode(m.Heartbeat("N2", figures=good))) == m.Heartbeat("N2", figures=good)
    bad = m.Figures(1.0, 0.0, 0.0, None, None, power, {"N1": hops})
    with pytest.raises(msgspec.ValidationError, match=r"Expected `int` (>= 1|<= 64)"):
        m.decode(m.encode(m.Heartbeat("N2", figures=bad)))


APP = pipe_app(50).replace("pinned: N4", "pinned: N3")


@pytest.fixture(scope="module")
def running() -> Simulation:
    return deployed()


@pytest.fixture(scope="module")
def untouched() -> Simulation:
    """A deployment no fuzzing has disturbed (the refusals below change nothing)."""
    return deployed()


def deployed() -> Simulation:
    net = Network(
        [NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3"), NodeSpec("N9")],  # N9: no links
        [LinkSpec("N1", "N2", delay_ms=1.0), LinkSpec("N2", "N3", delay_ms=1.0)],
    )
    sim = Simulation(net)
    sim.request("N1", m.DeployRequest(APP, "app.yaml"))
    sim.run_until(1.0)
    assert any(isinstance(r, m.DeployReply) and r.ok for _, _, r in sim.replies)
    return sim


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(rng=st.randoms(use_true_random=False))
def test_every_handler_survives_messages_of_wrong_meaning(
    rng: random.Random, running: Simulation, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Into a running deployment: 40 well-typed messages of random meaning per example, to
    every node, as neighbours' messages and as clients' requests. Nothing raises; what a node
    refuses is counted; its buffers stay bounded; it still answers status."""
    monkeypatch.setattr(NodeCore, "strict", False)  # count, as the daemon does, not raise
    sim = running
    for _ in range(40):
        node = rng.choice(sorted(sim.cores))
        core = sim.cores[node]
        msg = wirefuzz.message(rng)
        if rng.random() < 0.2:
            effects = core.request(rng.randrange(5), msg, sim.now)
        else:
            effects = core.receive(rng.choice(["N1", "N2", "N3", "N9"]), msg, sim.now)
        sim.apply(node, effects)
    sim.run_until(sim.now + 0.5)
    for core in sim.cores.values():
        assert len(core.early) <= core.early.limits.total
        msgspec.json.encode(core.status(sim.now))  # still reports
        # a handler that raised cost that message only, counted (handler_errors) in status
        assert core.status(sim.now)["handler_errors"] == core.handler_errors


def counted(core: NodeCore) -> int:
    return core.dropped_messages + core.handler_errors + core.illegal_transitions


def test_a_node_process_path_counts_and_lives_on() -> None:
    """Through the real transport and driver (no operator key: open mode, so client commands
    are carried out too, except Shutdown): 3,000 fuzzed frames from a neighbour and from a
    client. Nothing raises out of a handler into the connection, and the node answers."""
    import asyncio

    from mso.client import overlay_key
    from mso.node.driver import NodeDriver

    key = overlay_key("fuzz")
    rng = random.Random(7)
    types = tuple(
        t for t in wirefuzz.MESSAGE_TYPES if t not in (m.Shutdown, m.ClientHello, m.PeerHello)
    )

    async def member(port: int, hello: m.Message, src: str) -> tuple[Any, Any, FrameCodec]:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        codec = FrameCodec(key)
        writer.write(codec.hello())
        while not codec.confirmed:
            writer.write(codec.feed(await reader.read(1 << 16))[1])
        writer.write(codec.seal(m.wrap(src, "N1", hello)))
        return reader, writer, codec

    async def run() -> dict[str, Any]:
        driver = NodeDriver(NodeCore("N1"), "127.0.0.1", 0, key)
        await driver.start()
        port = driver.transport.port
        try:
            peer = await member(port, m.PeerHello("N2"), "N2")
            client = await member(port, m.ClientHello("fuzz"), "client")
            for i in range(3000):
                _, writer, codec = peer if i % 10 else client
                src = "N2" if i % 10 else "client"
                writer.write(codec.seal(m.wrap(src, "N1", wirefuzz.message(rng, types))))
                if i % 100 == 0:
                    await writer.drain()
            for _, writer, _ in (peer, client):
                await writer.drain()
            # the fuzzing client's own connection still answers, after all it sent
            reader, writer, codec = client
            writer.write(codec.seal(m.wrap("client", "N1", m.StatusRequest(req=424242))))
            reply = None
            while reply is None:
                data = await asyncio.wait_for(reader.read(1 << 16), 30)
                assert data, "the node closed the fuzzing client's connection"
                for p in codec.feed(data)[0]:
                    with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                        msg = m.decode(m.unwrap(p).body)
                        if isinstance(msg, m.StatusReply) and msg.req == 424242:
                            reply = msg
            for _, w, _ in (peer, client):
                w.close()
            return dict(reply.nodes["N1"])
        finally:
            await driver.stop()

    NodeCore.strict = False
    try:
        st = asyncio.run(run())
    finally:
        NodeCore.strict = True
    assert st["traffic"]["frames_failed"] == 0
    assert st["node"] == "N1"


# Messages of a wrong meaning into a running deployment (``pipe``: src on N1, mid on N2, sink
# pinned to N3; N1 its origin), each refused: nothing done, counted (dropped_messages, and by
# reason in ``refusals``), and no handler raises (``handler_errors`` stays as it was).
WRONG_MEANING = [
    pytest.param("N2", "N1", m.Data("pipe", 0, 999, 0, [b"x"]), id="data of an old epoch"),
    pytest.param("N2", "N3", m.Ack("pipe", 42, 0, 5), id="ack for an edge not there"),
    pytest.param("N2", "N1", m.Switch("pipe", 99, "N3", 1), id="switch of an edge not there"),
    pytest.param("N2", "N1", m.Switch("pipe", -1, "N3", 1), id="switch of a negative edge"),
    pytest.param("N2", "N1", m.Switch("pipe", 1, "N1", 1), id="switch of a pinned vertex"),
    pytest.param("N1", "N3", m.Switch("pipe", 0, "N2", 1), id="switch to where it runs"),
    pytest.param("N2", "N1", m.RelocateRequest("pipe", "ghost", "upstream"),
                 id="relocate a vertex not there"),
    pytest.param("N2", "N1", m.Marker("pipe", 99, 5, 1, "N3"), id="marker of an edge not there"),
    pytest.param("N2", "N1", m.Marker("pipe", 0, 5, 1, "N2"), id="marker moving to its host"),
    pytest.param("N2", "N3", m.Prepared("pipe", "mid", 777, "N3"), id="prepared for no relocation"),
    pytest.param("N2", "N1", m.Handover("pipe", "mid", 777, b"", {}, {}, 0, 0),
                 id="handover nobody asked for"),
    pytest.param("N2", "N1", m.HandoverDone("pipe", "mid", 777), id="handover done of nothing"),
    pytest.param("N2", "N3", m.ProbeReply("pipe", 0, 9, [], []), id="probe reply for no probe"),
    pytest.param("N2", "N3", m.ProbeReply("pipe", -1, 9, [], []), id="remap probe reply, no remap"),
    pytest.param("N2", "N3", m.ChainBuilt("pipe", 99), id="chain built of a chain not there"),
    pytest.param("N1", "N3", m.ChainBuilt("pipe", 0), id="chain built after the deployment"),
    pytest.param("N1", "N3", m.DeployFailed("pipe", "no"), id="deploy failed of a running app"),
    pytest.param("N2", "N1", m.ChainPartReady("pipe", 0, "N3"), id="part ready for no build"),
    pytest.param("N2", "N1", m.StartApp("pipe"), id="start of a running app"),
    pytest.param("N2", "N1", m.Resume("pipe", 0, 5, True, 0), id="resume for no replacement"),
    pytest.param("N2", "N1", m.Resume("pipe", 7, 5, True, 0), id="resume of an edge not there"),
    pytest.param("N2", "N1", m.ChainPlaced("pipe", 99, {}), id="chain placed out of range"),
    pytest.param("N2", "N1", m.ChainPlaced("pipe", -5, {}), id="chain placed negative"),
    pytest.param("N2", "N1", m.ChainPlaced("pipe", 0, {"src": "N9"}), id="chain placed again"),
    pytest.param("N2", "N1", m.BuildChain("pipe", 99, ["ghost"]), id="build of no chain"),
    pytest.param("N2", "N1", m.BuildChain("pipe", 0, ["ghost"]), id="build of a ghost vertex"),
    pytest.param("N2", "N1", m.BuildChain("pipe", 0, ["mid"]), id="build of a running app"),
    pytest.param("N2", "N1", m.Prepare("pipe", "src", 5, True, [[1]]), id="resumes not pairs"),
    pytest.param("N2", "N1", m.Prepare("pipe", "src", 5, True, [["x", "y"]]),
                 id="resumes not numbers"),
    pytest.param("N2", "N1", m.Prepare("pipe", "src", 5, True, [[99, True]]),
                 id="resumes of an edge not there"),
    pytest.param("N2", "N1", m.Prepare("pipe", "src", 5, True, [[1, True]]),
                 id="resumes of another vertex's edge"),
    pytest.param("N2", "N1", m.Moved("pipe", "ghost", "N1"), id="moved a vertex not there"),
    pytest.param("N2", "N1", m.Moved("pipe", "sink", "N1"), id="moved a pinned vertex"),
    pytest.param("N2", "N1", m.Rewire("pipe", 1, "N1", 5, True), id="rewire to a pinned vertex"),
    pytest.param("N2", "N1", m.Rewire("pipe", 9, "N1", 5, True), id="rewire of no edge"),
    pytest.param("N2", "N1", m.Unprepare("pipe", "mid", 777), id="unprepare of nothing"),
    pytest.param("N1", "N2", m.Moving("pipe", "mid", 5, "N3"), id="moving of a vertex not here"),
    pytest.param("N1", "N2", m.Moving("pipe", "src", 5, "N1"), id="moving to its host"),
    pytest.param("N2", "N1", m.Moved("ghost-app", "mid", "N1"), id="moved of no app"),
    pytest.param("N2", "N3", m.ChainDelay("pipe", 0, float("nan")), id="chain delay NaN"),
    pytest.param("N2", "N3", m.ChainDelay("pipe", 5, 1.0), id="chain delay of no chain"),
    pytest.param("N2", "N1", m.Hears("N3", 777, True), id="hears for no suspicion"),
    pytest.param("N2", "N1", m.Hears("N3", 777, False), id="hears no for no suspicion"),
]  # fmt: skip


@pytest.mark.parametrize(("node", "src", "msg"), WRONG_MEANING)
def test_a_refused_message_is_counted(
    node: str, src: str, msg: m.Message, untouched: Simulation, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(NodeCore, "strict", True)  # a handler that raises fails the test
    core = untouched.cores[node]
    before, errors, placed = counted(core), core.handler_errors, dict(core.placement("pipe"))
    assert core.receive(src, msg, untouched.now) == []  # nothing done
    assert counted(core) == before + 1 and core.handler_errors == errors
    assert core.placement("pipe") == placed and core.apps["pipe"].running
    status = core.status(untouched.now)
    assert status["dropped_messages"] == core.dropped_messages
    if not isinstance(msg, m.Data | m.Ack):  # (the data plane counts its drops as it did)
        assert sum(status["refusals"].values()) >= 1


def test_a_handed_over_numbering_of_the_wrong_shape_is_refused_not_taken() -> None:
    """A handover's output entry names its generation and its positions' after the
    positions (``Handover.outputs``); an entry of any other shape is refused whole
    (``handover_malformed``), never half taken nor a crash. Four fields: an older node's."""
    assert _numbering([7, {1: 1 << 50}]) == (7, {1: 1 << 50})
    for bad in (
        [7],
        [7, {1: 2}, 0],
        ["7", {}],
        [True, {}],
        [7, [1, 2]],
        [7, {"1": 2}],
        [7, {1: 2.5}],
    ):
        assert _numbering(bad) is None, bad
