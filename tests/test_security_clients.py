"""Client identities (issue 27, round three): on an overlay with node identities a client is
served only with its own operator-certified key (or the operator key itself); a read-only
client may not command; a command client signs what its connection carries with its own key;
a revoked client key is cut off."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
from click.testing import CliRunner
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from mso.cli import main
from mso.client import Refused, overlay_key, request
from mso.net.limits import Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.protocol import clients
from mso.protocol import messages as m
from mso.protocol.authority import Authority, Signer
from mso.protocol.framing import FrameCodec
from mso.protocol.identity import Identity, certify
from waits import answered

HOST = "127.0.0.1"
KEY = "client-test-key"
OPERATOR, ROGUE = Signer(), Signer()


def client(name: str, role: str = "command", operator: Signer = OPERATOR) -> clients.ClientIdentity:
    private = Ed25519PrivateKey.generate()
    cert = clients.certify(operator, name, private.public_key(), 1000, role)
    return clients.ClientIdentity(private, cert)


async def node() -> TcpTransport:
    """A node N1 with an identity and the operator key (so it requires identities) whose
    client handler answers every request it is handed with its type: what passed the gate."""
    private = Ed25519PrivateKey.generate()
    ident = Identity(private, certify(OPERATOR, "N1", private.public_key(), 1000))
    auth = Authority.configure([OPERATOR.public_text()])
    net = TcpTransport(
        "N1", HOST, 0, overlay_key(KEY), EmulatorRoutes("N1"), Limits(), auth, identity=ident
    )
    net.set_client_handler(lambda c, msg: net.reply(c, answer(msg)))
    await net.start()
    return net


def answer(msg: m.Message) -> m.Message:
    if isinstance(msg, m.StatusRequest):  # a status as a dashboard reads it: no node yet
        return m.StatusReply(msg.req, {})
    return m.Refused(f"got {type(msg).__name__}")


def test_a_client_proof_holds_for_its_connection_its_operator_and_an_unrevoked_key() -> None:
    ops = {OPERATOR.id: OPERATOR.public}
    a, b = FrameCodec(overlay_key(KEY)), FrameCodec(overlay_key(KEY), responder=True)
    b.feed(a.hello())
    a.feed(b.hello())
    me = client("alice")
    hello = me.hello("cli", a.hello(), a.peer_hello)
    said = clients.check(hello, b.peer_hello, b.hello(), ops)  # as the node sees it
    assert isinstance(said, clients.Admitted) and (said.name, said.role) == ("alice", "command")
    assert "operator-certified key" in str(clients.check(m.ClientHello("x"), b"", b"", ops))
    rogue = client("alice", operator=ROGUE).hello("cli", a.hello(), a.peer_hello)
    assert "no operator's" in str(clients.check(rogue, b.peer_hello, b.hello(), ops))
    revoked = {me.cert.key_id}
    assert "revoked" in str(clients.check(hello, b.peer_hello, b.hello(), ops, revoked))
    other = FrameCodec(overlay_key(KEY), responder=True)  # the same hello on another connection
    assert "does not verify" in str(clients.check(hello, a.hello(), other.hello(), ops))
    node_cert = certify(
        OPERATOR, "alice", me.private.public_key(), 1000
    )  # a node's, not a client's
    posing = m.ClientHello("cli", msgspec.msgpack.encode(node_cert), hello.sig)
    assert "not an mso client certificate" in str(
        clients.check(posing, b.peer_hello, b.hello(), ops)
    )
    assert clients.parse_cert(me.cert.text()) == me.cert
    reader = clients.Admitted("bob", "read", "k", me.private.public_key())
    assert "may only read" in clients.may(reader, m.RelocateRequest("a", "v", "upstream"))
    assert clients.may(reader, m.StatusRequest()) == ""
    assert clients.may(said, m.RelocateRequest("a", "v", "upstream")) == ""


def test_the_dashboard_reads_nodes_with_identities_with_the_operator_key(tmp_path: Path) -> None:
    """The dashboard's page is fed from a status session: with only the operator key
    ($MSO_SIGN) it is a client of nodes that require identities too."""
    from mso.dashboard.server import Dashboard

    op = tmp_path / "op.key"
    op.write_text(OPERATOR.private_text() + "\n")

    async def run() -> tuple[object, object]:
        net = await node()
        try:
            address = f"{HOST}:{net.port}"
            said: list[object] = []
            for sign in (str(op), ""):
                board = Dashboard([address], KEY, sign=sign)
                try:
                    said.append(await board._status())
                except Exception as exc:
                    said.append(str(exc))
                finally:
                    if board._session is not None:
                        await board._session.close()
            return said[0], said[1]
        finally:
            await net.close()

    signed, unsigned = asyncio.run(run())
    assert signed == {}
    assert "operator-certified key" in str(unsigned)


def test_keygen_makes_client_keys_that_load(tmp_path: Path) -> None:
    run = CliRunner().invoke
    assert run(main, ["keygen", str(tmp_path / "op.key")]).exit_code == 0
    out = run(main, ["keygen", "--client", "ops-laptop", "--read-only",
                     "--sign", str(tmp_path / "op.key"), str(tmp_path / "c.key")])  # fmt: skip
    assert out.exit_code == 0, out.output
    assert "read-only client" in out.output
    got = clients.ClientIdentity.load(tmp_path / "c.key")
    assert (got.cert.name, got.cert.role) == ("ops-laptop", "read")
    assert got.cert.key_id in out.output
    bad = run(main, ["keygen", "--read-only", str(tmp_path / "d.key")])
    assert bad.exit_code == 2 and "--client" in bad.output
    unsigned = run(main, ["keygen", "--client", "x", str(tmp_path / "e.key")])
    assert unsigned.exit_code == 2 and "--sign" in unsigned.output


def test_a_node_that_requires_identities_serves_certified_clients_only() -> None:
    """One node with an identity and the operator key, over TCP: a client without a
    certificate (or with one no operator signed) is refused every request, told why; a
    read-only client reads and may not relocate; a command client relocates with its own
    signature; the operator key is a client too; a revoked client is cut off."""

    async def run() -> dict[str, str]:
        net = await node()
        address = f"{HOST}:{net.port}"
        said: dict[str, str] = {}

        async def ask(what: str, msg: m.Message, **kw: object) -> None:
            try:
                reply = await request(address, msg, key=KEY, timeout=10, **kw)  # type: ignore[arg-type]
                said[what] = f"answered {type(reply).__name__}"
            except Refused as exc:
                said[what] = str(exc)

        reader, commander = client("reader", "read"), client("commander")
        relocate = m.RelocateRequest("app", "v", "upstream")
        try:
            await ask("none", m.StatusRequest(), identity=None)
            await ask("rogue", m.StatusRequest(), identity=client("x", operator=ROGUE))
            await ask("read status", m.StatusRequest(), identity=reader)
            await ask("read relocate", relocate, identity=reader)
            await ask("command relocate", relocate, identity=commander)
            await ask("operator status", m.StatusRequest(), signer=OPERATOR)
            await ask("command deploy", m.StopApp("app"), identity=commander)
            revoke = OPERATOR.revoke_node(commander.cert.key_id, 2000)
            await ask("revoke", revoke, signer=OPERATOR)
            await ask("revoked", m.StatusRequest(), identity=commander)
            said["client_refused"] = str(net.connection_counters.client_refused)
            return said
        finally:
            await net.close()

    said = asyncio.run(run())
    assert "serves only clients with an operator-certified key" in said["none"]
    assert "no operator's" in said["rogue"]
    assert said["read status"] == "answered StatusReply"
    assert "may only read" in said["read relocate"]
    assert "got RelocateRequest" in said["command relocate"]  # signed with its own key
    assert said["operator status"] == "answered StatusReply"
    assert "needs an operator's signature" in said["command deploy"]  # travels: operator only
    assert "revoked" in said["revoked"]
    assert said["client_refused"] == "3"  # none, rogue, revoked


def test_a_revoked_client_is_cut_off_on_its_open_connection() -> None:
    async def run() -> str:
        net = await node()
        address = f"{HOST}:{net.port}"
        from mso.client import connect

        me = client("laptop")
        kept = await connect(address, key=KEY, identity=me)
        try:
            assert isinstance(await kept.call(m.StatusRequest(), 10), m.StatusReply)
            revoke = OPERATOR.revoke_node(me.cert.key_id, 2000)
            await answered(lambda: request(address, revoke, key=KEY, signer=OPERATOR), 5, "revoke")
            try:
                await kept.call(m.StatusRequest(), 10)
            except Exception as exc:
                return type(exc).__name__
            return "answered"
        finally:
            await kept.close()
            await net.close()

    assert asyncio.run(run()) == "NodeUnreachable"
