"""End-to-end origin: a message's originator signs it, so a relay cannot write another's name.

Links authenticated to node identities (:mod:`mso.protocol.identity`) say who the *neighbour*
is, not who wrote a frame it relays: any relay could put any node's name in an envelope's
``src`` and forge failure claims, moves or syncs in it. With identities, a node signs every
control and marker frame it originates (and a heartbeat to a node that is not its
neighbour): an :class:`Origin` in the envelope holds its certificate, the time, and its
signature over the envelope's source, destination, kind and body. A node that requires
identities takes a non-data frame whose source is not the neighbour it came from only when
that origin holds (:class:`Verifier`): the certificate is an operator's for that very source,
its key is not revoked, the time is within ``WINDOW_MS`` of this node's clock, and the
signature verifies. Frames from the neighbour itself are proved by the link.

A verified source still speaks only for itself (:func:`attribute`): a failure claim counts as
its sender's own (its ``detector`` is the sender, and the ``witness`` it names, whose word it
cannot show, is dropped), a heartbeat's piggybacked claims as the sender's own too, and a
heartbeat or a host's ``Moved`` must name its sender. A ``NodeUp`` (a node held failed is
back) is taken only from that node itself: a neighbour's announcement of it is not its word,
and its own beats, signed to every node it is not a neighbour of, bring it back (at a host
that is not its neighbour, within a rejoin round of the beats, ``REJOIN_EVERY``).

A member's "I hear it" (a ``Hears`` yes about a suspect) is the suspect's own word carried
back (:meth:`Verifier.hears`): the member asks the suspect on with the asker's challenge, the
receiving transport keeps the suspect's signed answer as it came (``Hears.proof``: the frame,
with its origin), and the asker's transport takes the member's yes with that proof only when
the proof is the suspect's, signed, a yes, to the very challenge; else the proof is stripped
and the core takes the yes as a member's word alone, which it sets aside.

Data frames (events and acks) are not signed — a signature per event would cost more than the
event — but tagged by a key only their two ends hold (:mod:`mso.protocol.dataseal`).

Sans-IO: bytes, keys and the time in; a frame or a verdict out.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Set

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from mso.protocol import messages as m
from mso.protocol.authority import KeyError_, certified_key
from mso.protocol.identity import Identity, NodeCert, parse_cert

ORIGIN_DOMAIN = b"mso origin\0"
WINDOW_MS = 600_000  # an origin's time may be this far from the receiver's clock (10 min)
MAX_CERTS = 1024  # verified certificates kept (their operator signature checked once)
SIGNED_KINDS = frozenset({m.CONTROL, m.MARKER, m.HEARTBEAT})


class Origin(msgspec.Struct, array_like=True, frozen=True):
    """Who wrote a frame, when, and its signature (``Envelope.origin``, msgpack-encoded)."""

    cert: bytes  # the originator's certificate (msgpack of a NodeCert)
    at: int  # the originator's clock, ms
    sig: bytes


_ORIGIN_DECODER = msgspec.msgpack.Decoder(Origin)
_ENCODER = msgspec.msgpack.Encoder()


def signed_bytes(env: m.Envelope, at: int) -> bytes:
    """What an origin signs: the envelope but its hop count, and the time."""
    head = _ENCODER.encode([env.src, env.dst, env.kind, at])
    return ORIGIN_DOMAIN + head + bytes(env.body)


def sign(identity: Identity, payload: bytes, wall_ms: int) -> bytes:
    """``payload`` (an envelope this node originates) with its origin."""
    env = m.unwrap(payload)
    sig = identity.private.sign(signed_bytes(env, wall_ms))
    env.origin = _ENCODER.encode(Origin(_ENCODER.encode(identity.cert), wall_ms, sig))
    return m.rewrap(env)


class Verifier:
    """Checks origins against the operator keys and revocations a node holds now (given on
    each call: a reload may change them); certificates whose operator signature held are
    kept (bounded), so a frame from a known originator costs one verification."""

    def __init__(self) -> None:
        self._certs: OrderedDict[bytes, tuple[NodeCert, Ed25519PublicKey]] = OrderedDict()
        # each node's latest certificate seen to hold (a link's proof, a verified origin): the
        # key its data frames' tags are checked with (mso.protocol.dataseal)
        self.by_node: OrderedDict[str, NodeCert] = OrderedDict()

    def learn(self, cert: NodeCert) -> None:
        """``cert`` held (its operator's signature checked, for the node it names)."""
        self.by_node[cert.node] = cert
        self.by_node.move_to_end(cert.node)
        while len(self.by_node) > MAX_CERTS:
            self.by_node.popitem(last=False)

    def _cert(
        self, raw: bytes, operators: Mapping[str, Ed25519PublicKey]
    ) -> tuple[NodeCert, Ed25519PublicKey] | str:
        held = self._certs.get(raw)
        if held is not None and operators.get(held[0].operator) is not None:
            self._certs.move_to_end(raw)
            return held
        try:
            cert = parse_cert(raw)
        except KeyError_ as exc:
            return str(exc)
        key = certified_key(cert, operators)
        if isinstance(key, str):
            return key
        self._certs[raw] = (cert, key)
        while len(self._certs) > MAX_CERTS:
            self._certs.popitem(last=False)
        return cert, key

    def check(
        self,
        env: m.Envelope,
        wall_ms: int,
        operators: Mapping[str, Ed25519PublicKey],
        revoked: Set[str] = frozenset(),
    ) -> str | None:
        """Why ``env``'s origin does not prove it was written by ``env.src`` (None: it does)."""
        if not env.origin:
            return "no origin signature"
        try:
            origin = _ORIGIN_DECODER.decode(env.origin)
        except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
            return "an origin that does not decode"
        if abs(origin.at - wall_ms) > WINDOW_MS:
            return f"an origin {(origin.at - wall_ms) / 1000:+.0f} s off this node's clock"
        held = self._cert(origin.cert, operators)
        if isinstance(held, str):
            return held
        cert, key = held
        if cert.node != env.src:
            return f"a certificate for {cert.node!r}, not {env.src!r}"
        if cert.key_id in revoked:
            return f"node key {cert.key_id} is revoked"
        try:
            key.verify(origin.sig, signed_bytes(env, origin.at))
        except InvalidSignature:
            return "an origin signature that does not verify"
        self.learn(cert)
        return None

    def admit(
        self,
        peer: str,
        env: m.Envelope,
        msg: m.Message,
        wall_ms: int,
        operators: Mapping[str, Ed25519PublicKey],
        revoked: Set[str] = frozenset(),
    ) -> m.Message | str:
        """``msg``, handed over by the proven neighbour ``peer``, as the word of its
        originator alone, or why it is refused: a non-data frame in another name than
        ``peer``'s must carry that node's origin (:meth:`check`), then :func:`attribute`."""
        if env.src != peer and env.kind != m.DATA:
            why = self.check(env, wall_ms, operators, revoked)
            if why is not None:
                return why
        return attribute(env.src, msg)

    def hears(
        self,
        src: str,
        env: m.Envelope,
        msg: m.Hears,
        wall_ms: int,
        operators: Mapping[str, Ed25519PublicKey],
        revoked: Set[str] = frozenset(),
    ) -> tuple[m.Hears, str | None]:
        """``msg`` (from ``src``, in the frame ``env``) with the proof it may carry, and why a
        proof it came with was stripped (None: none was): the suspect's own yes to a
        challenge gets its frame as its proof (checked where it is carried to); another's
        keeps its proof only when that is the suspect's own signed yes to the same
        challenge."""
        if src == msg.node:
            own = msg.yes and msg.nonce and env.origin and env.src == src
            proof = m.rewrap(env) if own else b""
            if len(proof) > m.MAX_PROOF:
                proof = b""
            return msgspec.structs.replace(msg, proof=proof), None
        if not msg.proof:
            return msg, None
        why = self._proof_refused(msg, wall_ms, operators, revoked)
        if why is None:
            return msg, None
        return msgspec.structs.replace(msg, proof=b""), why

    def _proof_refused(
        self,
        msg: m.Hears,
        wall_ms: int,
        operators: Mapping[str, Ed25519PublicKey],
        revoked: Set[str],
    ) -> str | None:
        try:
            env = m.unwrap(msg.proof)
            said = m.decode(env.body)
        except (msgspec.DecodeError, msgspec.ValidationError):
            return "a proof that does not decode"
        if env.src != msg.node or env.kind != m.CONTROL:
            return f"a proof from {env.src!r}, not {msg.node!r}'s own answer"
        if not (isinstance(said, m.Hears) and said.node == msg.node and said.yes):
            return f"a proof that is not {msg.node!r}'s yes"
        if not msg.nonce or said.nonce != msg.nonce:
            return "a proof of another challenge"
        return self.check(env, wall_ms, operators, revoked)


def attribute(src: str, msg: m.Message) -> m.Message | str:
    """``msg`` as the word of its verified sender ``src`` alone, or why it cannot be: a node
    speaks for itself, never in a third node's name."""
    if isinstance(msg, m.NodeDown):
        if msg.detector != src or msg.witness:
            return m.NodeDown(msg.node, src, msg.incarnation)
    elif isinstance(msg, m.Heartbeat):
        if msg.node != src:
            return f"a heartbeat of {msg.node!r} from {src!r}"
        if any(c.detector != src or c.witness for c in msg.news):
            msg.news = [m.NodeDown(c.node, src, c.incarnation) for c in msg.news]
    elif isinstance(msg, m.Moved) and msg.incarnation >= 0 and msg.node != src:
        return f"a host's Moved of {msg.vertex!r} to {msg.node!r} from {src!r}"
    elif isinstance(msg, m.NodeUp) and msg.node != src:  # its own signed beats say it is back
        return f"a NodeUp of {msg.node!r} from {src!r}: only {msg.node!r}'s own word"
    return msg
