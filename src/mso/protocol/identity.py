"""Node identities: each node's own Ed25519 key, certified by an operator; proved on each link.

With one overlay key, any member can say it is any node: on a connection it could claim a
neighbour's name and be sent what was meant for that neighbour. A node given an identity
(``mso keygen --node NAME --sign OPERATOR_KEY``) holds its own key pair and a certificate, the
operator's signature over the node's name, its public key and when it was issued. On every
link each side proves its name in its :class:`~mso.protocol.messages.PeerHello`: its
certificate and its signature, with its own key, over both hellos of that very connection (so
a proof is good for that connection only). A node with operator keys and an identity takes a
link only from a node whose proof holds: an operator it trusts signed the certificate, for
the name the node gives, with a key not revoked (``revoked_nodes``: key ids the operator
withdrew, e.g. of a captured robot), and the signature covers this connection's hellos.

Sans-IO: bytes and keys in, a verdict out. Measured against TLS 1.3: ``bench/identity.py``.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Callable, Mapping, Set
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TypeVar

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from mso.protocol.authority import KeyError_, Signer, certified_key, parse_private

CERT_PREFIX = "mso-node-cert:"
CERT_DOMAIN = b"mso node certificate\0"
LINK_DOMAIN = b"mso link\0"


class NodeCert(msgspec.Struct, frozen=True, array_like=True):
    """An operator's word that ``key`` (raw Ed25519 public key) is node ``node``'s."""

    node: str
    key: bytes
    issued: int  # the operator's clock, ms
    operator: str  # the operator key's id
    sig: bytes

    def signed_bytes(self) -> bytes:
        return CERT_DOMAIN + msgspec.msgpack.encode([self.node, self.key, self.issued])

    @property
    def key_id(self) -> str:
        """How a revocation names this node's key."""
        return hashlib.blake2b(self.key, digest_size=6).hexdigest()

    def text(self) -> str:
        return CERT_PREFIX + base64.b64encode(msgspec.msgpack.encode(self)).decode()


def certify(operator: Signer, node: str, public: Ed25519PublicKey, issued_ms: int) -> NodeCert:
    unsigned = NodeCert(node, public.public_bytes_raw(), issued_ms, operator.id, b"")
    return NodeCert(
        node, unsigned.key, issued_ms, operator.id, operator.private.sign(unsigned.signed_bytes())
    )


def parse_cert(data: str | bytes) -> NodeCert:
    """A certificate from its text (a file) or its bytes (a PeerHello)."""
    try:
        if isinstance(data, str):
            if not data.strip().startswith(CERT_PREFIX):
                raise ValueError
            data = base64.b64decode(data.strip().removeprefix(CERT_PREFIX), validate=True)
        return msgspec.msgpack.decode(data, type=NodeCert)
    except (ValueError, msgspec.DecodeError, msgspec.ValidationError):
        raise KeyError_("not an mso node certificate (made by `mso keygen --node`)") from None


class _Cert(Protocol):
    @property
    def key(self) -> bytes: ...


C = TypeVar("C", bound=_Cert)


def load_key_and_cert(path: str | Path, parse: Callable[[str], C]) -> tuple[Ed25519PrivateKey, C]:
    """The private key in the file ``path`` and its certificate beside it (``path.cert``,
    read by ``parse``), which must certify that key: a node's or a client's."""
    p = Path(path)
    try:
        private = parse_private(p.read_text(encoding="utf-8"))
        cert = parse(p.with_name(p.name + ".cert").read_text(encoding="utf-8"))
    except OSError as exc:
        raise KeyError_(f"{exc.filename}: {exc.strerror}") from None
    if private.public_key().public_bytes_raw() != cert.key:
        raise KeyError_(f"{p}.cert certifies another key than {p}'s")
    return private, cert


@dataclass(frozen=True)
class Identity:
    """This node's key and its certificate."""

    private: Ed25519PrivateKey
    cert: NodeCert

    @classmethod
    def load(cls, path: str | Path) -> Identity:
        """The key file ``path`` and its certificate beside it (``path.cert``)."""
        return cls(*load_key_and_cert(path, parse_cert))

    @property
    def node(self) -> str:
        return self.cert.node

    def prove(self, mine: bytes, theirs: bytes) -> bytes:
        """This connection's proof: the signature over both hellos, this side's first."""
        return self.private.sign(LINK_DOMAIN + mine + theirs)


def check(
    node: str,
    cert_bytes: bytes,
    sig: bytes,
    theirs: bytes,
    mine: bytes,
    operators: Mapping[str, Ed25519PublicKey],
    revoked: Set[str] = frozenset(),
) -> str | None:
    """Why a peer's proof that it is ``node`` on the connection whose hellos are ``theirs``
    and ``mine`` does not hold, or None when it does."""
    if not cert_bytes:
        return "no node certificate"
    try:
        cert = parse_cert(cert_bytes)
    except KeyError_ as exc:
        return str(exc)
    if cert.node != node:
        return f"a certificate for {cert.node!r}, not {node!r}"
    if cert.key_id in revoked:
        return f"node key {cert.key_id} is revoked"
    key = certified_key(cert, operators)
    if isinstance(key, str):
        return key
    try:
        key.verify(sig, LINK_DOMAIN + theirs + mine)
    except (InvalidSignature, ValueError):
        return "a signature that does not verify"
    return None
