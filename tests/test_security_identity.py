"""Node identities (issue 27, Build 2): a node's own Ed25519 key, certified by the operator,
proved on every link, so a member with the overlay key cannot take a neighbour's name on a
connection; a revoked key is refused. The choice against TLS 1.3: bench/identity.py."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.client import overlay_key
from mso.net.limits import Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer
from mso.protocol.framing import FrameCodec
from mso.protocol.identity import Identity, certify, check, parse_cert

HOST = "127.0.0.1"
KEY = overlay_key("k")
OPERATOR, ROGUE = Signer(), Signer()


def identity(node: str, operator: Signer = OPERATOR) -> Identity:
    private = Ed25519PrivateKey.generate()
    return Identity(private, certify(operator, node, private.public_key(), 1000))


def test_a_proof_holds_for_its_name_its_connection_and_an_unrevoked_key_only() -> None:
    ops = {OPERATOR.id: OPERATOR.public}
    me, other = identity("N1"), identity("N1", ROGUE)
    a, b = FrameCodec(KEY), FrameCodec(KEY, responder=True)
    b.feed(a.hello())
    a.feed(b.hello())
    mine, theirs = a.hello(), a.peer_hello
    cert = msgspec.msgpack.encode(me.cert)
    sig = me.prove(mine, theirs)
    assert check("N1", cert, sig, mine, theirs, ops) is None  # as the receiver sees it
    assert "not 'N2'" in (check("N2", cert, sig, mine, theirs, ops) or "")
    assert "unknown key" in (check("N1", msgspec.msgpack.encode(other.cert),
                                   other.prove(mine, theirs), mine, theirs, ops) or "")  # fmt: skip
    assert "revoked" in (check("N1", cert, sig, mine, theirs, ops, {me.cert.key_id}) or "")
    c = FrameCodec(KEY)  # the same proof replayed on another connection
    assert "does not verify" in (check("N1", cert, sig, c.hello(), theirs, ops) or "")
    assert "no node certificate" in (check("N1", b"", b"", mine, theirs, ops) or "")
    assert parse_cert(me.cert.text()) == me.cert


def test_identity_files_round_trip_and_must_match(tmp_path: Path) -> None:
    me = identity("N7")
    key = tmp_path / "n7.key"
    key.write_text(Signer(me.private).private_text() + "\n")
    key.with_name("n7.key.cert").write_text(me.cert.text() + "\n")
    assert Identity.load(key).cert == me.cert
    key.with_name("n7.key.cert").write_text(identity("N7").cert.text() + "\n")
    with pytest.raises(ValueError, match="another key"):
        Identity.load(key)


def test_links_are_taken_only_from_neighbours_that_prove_their_names() -> None:
    async def run() -> tuple[list[str], int, int]:
        auth = {n: Authority.configure([OPERATOR.public_text()]) for n in ("N1", "N2")}
        views = {n: EmulatorRoutes(n) for n in ("N1", "N2")}
        nets = {
            n: TcpTransport(n, HOST, 0, KEY, views[n], Limits(), auth[n], identity=identity(n))
            for n in ("N1", "N2")
        }
        got: list[str] = []
        nets["N2"].set_receiver(lambda src, msg: got.append(src))
        for n in nets:
            await nets[n].start()
        try:
            spec = lambda n: [HOST, nets[n].port, None, 0.0, 0.0]  # noqa: E731
            views["N1"].apply(m.LinkState(1, {"N2": spec("N2")}, {"N2": ["N2", 1]}))
            views["N2"].apply(m.LinkState(1, {"N1": spec("N1")}, {"N1": ["N1", 1]}))
            for _ in range(500):  # until both ends hold the verified link
                c1, c2 = nets["N1"].peers.get("N2"), nets["N2"].peers.get("N1")
                if c1 is not None and c2 is not None and c1.verified and c2.verified:
                    break
                await asyncio.sleep(0.01)
            nets["N1"].send("N2", m.wrap("N1", "N2", m.NodeUp("N1", 1)), m.CONTROL)
            # a member with the overlay key but no certificate of N1's says it is N1
            for cert_of in (None, identity("N1", ROGUE), identity("N3")):
                r, w = await asyncio.open_connection(HOST, nets["N2"].port)
                codec = FrameCodec(KEY)
                w.write(codec.hello())
                while not codec.ready:
                    w.write(codec.feed(await asyncio.wait_for(r.read(1 << 16), 5))[1])
                cert = b"" if cert_of is None else msgspec.msgpack.encode(cert_of.cert)
                sig = b"" if cert_of is None else cert_of.prove(codec.hello(), codec.peer_hello)
                w.write(codec.seal(m.wrap("N1", "N2", m.PeerHello("N1", cert, sig))))
                w.write(codec.seal(m.wrap("N1", "N2", m.NodeUp("N1", 2))))
                await asyncio.wait_for(r.read(), 5.0)  # closed by N2
                w.close()
            for _ in range(500):
                if got:
                    break
                await asyncio.sleep(0.01)
            refused = nets["N2"].connection_counters.identity_refused
            return got, refused, nets["N2"].peers["N1"].verified
        finally:
            for n in nets:
                await nets[n].close()

    got, refused, verified = asyncio.run(run())
    assert got == ["N1"] and verified  # the real N1's message, over its proven link only
    assert refused == 3


@pytest.mark.slow
def test_mso_nodes_link_with_their_identities_and_refuse_a_revoked_one(tmp_path: Path) -> None:
    """Three `mso node` processes on a line, each with its own key from `mso keygen --node`;
    N2 was told N3's key is revoked: N1 and N2 link, N3 stays outside, counted at N2."""
    import os
    import socket
    import subprocess
    import sys
    import time

    from mso.api import Overlay
    from mso.errors import MsoError
    from waits import patience

    def mso(*args: str) -> str:
        done = subprocess.run([sys.executable, "-m", "mso", *args], capture_output=True,
                              text=True, cwd=tmp_path, check=True)  # fmt: skip
        return done.stdout

    mso("keygen", "op.key")
    ids = {}
    for n in ("N1", "N2", "N3"):
        out = mso("keygen", "--node", n, "--sign", "op.key", f"{n}.key")
        ids[n] = out.split("node key id ")[1].split()[0]
    ports = []
    for _ in range(3):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    env = {k: v for k, v in os.environ.items() if k not in ("MSO_KEY", "MSO_ENCRYPT")}
    env["MSO_KEY"] = "identities"
    line = {"N1": ["N2"], "N2": ["N1", "N3"], "N3": ["N2"]}
    nodes = []
    for i, n in enumerate(("N1", "N2", "N3")):
        cmd = [sys.executable, "-m", "mso", "node", "--id", n, "--listen",
               f"127.0.0.1:{ports[i]}", "--no-manage", "--operator-key", "op.key.pub",
               "--identity", f"{n}.key"]  # fmt: skip
        for p in line[n]:
            cmd += ["--peer", f"{p}=127.0.0.1:{ports[int(p[1]) - 1]}"]
        if n == "N2":
            cmd += ["--revoke-node", ids["N3"]]
        nodes.append(subprocess.Popen(cmd, env=env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))  # fmt: skip
    try:
        # a client of nodes with identities holds a certified key: the operator's is one
        op = str(tmp_path / "op.key")
        n1, n2 = (Overlay(f"127.0.0.1:{p}", key="identities", timeout=10.0, sign=op)
                  for p in ports[:2])  # fmt: skip
        deadline = time.monotonic() + patience(60.0)
        while True:  # until N1 hears N2 and N2 has refused N3 (a loaded machine: seconds)
            try:
                refused = n2.status()["N2"]["connections"]["identity_refused"]
                if "N2" in n1.status(everywhere=True) and refused >= 1:
                    break
            except MsoError:
                pass
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert "N3" not in n1.status(everywhere=True)
    finally:
        for p in nodes:
            p.terminate()
        for p in nodes:
            p.wait(20)


def test_a_node_sends_nothing_but_its_hello_to_an_impostor_it_called() -> None:
    """N1 calls N2, but a member with the overlay key and no certificate of N2's answers at
    N2's address: it gets N1's proof and nothing N1 meant for N2, and is refused."""

    async def run() -> tuple[list[str], int]:
        got: list[str] = []
        done = asyncio.Event()

        async def impostor(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            codec = FrameCodec(KEY, responder=True)
            w.write(codec.hello())
            said = False
            while data := await r.read(1 << 16):
                payloads, flush = codec.feed(data)
                w.write(flush)
                got.extend(type(m.decode(m.unwrap(p).body)).__name__ for p in payloads)
                if codec.ready and not said:  # its own hello, with no proof
                    w.write(codec.seal(m.wrap("N2", "N1", m.PeerHello("N2"))))
                    said = True
            done.set()

        server = await asyncio.start_server(impostor, HOST, 0)
        port = server.sockets[0].getsockname()[1]
        view = EmulatorRoutes("N1")
        auth = Authority.configure([OPERATOR.public_text()])
        net = TcpTransport("N1", HOST, 0, KEY, view, Limits(), auth, identity=identity("N1"))
        await net.start()
        try:
            view.apply(m.LinkState(1, {"N2": [HOST, port, None, 0.0, 0.0]}, {"N2": ["N2", 1]}))
            net.send("N2", m.wrap("N1", "N2", m.NodeUp("N1", 1)), m.CONTROL)
            await asyncio.wait_for(done.wait(), 10.0)  # until N1 closed on it
            return got, net.connection_counters.identity_refused
        finally:
            await net.close()
            server.close()

    got, refused = asyncio.run(run())
    assert set(got) == {"PeerHello"} and refused >= 1  # (N1 calls again: the same each time)
