"""Client identities: a CLI, dashboard or API client's own key, certified by an operator.

On an overlay without node identities a client is whoever holds the overlay key: it may read
every node's status and tap every edge, and only the commands that change the overlay need an
operator's signature (:mod:`mso.protocol.authority`). A node that requires identities
(:mod:`mso.protocol.identity`) serves only *certified* clients: ``mso keygen --client NAME
--sign OPERATOR_KEY`` makes a key pair and a certificate, the operator's signature over the
client's name, its *role* and its public key. The client proves it in its
:class:`~mso.protocol.messages.ClientHello`, with a signature over both hellos of that very
connection (good for that connection only). The roles:

- ``read``: status, lookups, taps; every command that changes the overlay is refused;
- ``command``: as ``read``, and the commands a connection carries (relocate, remap, shut a
  node down) may be signed with the client's own key instead of the operator's. A deploy, an
  undeploy and a node revocation still need the operator's signature: every node checks
  those themselves, long after the client's connection.

A client holding the operator key needs no certificate of its own: it certifies a ``command``
client for itself (:func:`operator_client`). A client key is revoked like a node key
(``mso revoke-node KEY_ID``): its connections are closed and it is refused from then on.

Sans-IO: bytes and keys in, a verdict out.
"""

from __future__ import annotations

import base64
import functools
import hashlib
from collections.abc import Mapping, Set
from dataclasses import dataclass
from pathlib import Path

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from mso.protocol import messages as m
from mso.protocol.authority import (
    CONNECTION_COMMANDS,
    EMULATOR_COMMANDS,
    OPERATOR_COMMANDS,
    KeyError_,
    Signer,
    certified_key,
)
from mso.protocol.identity import load_key_and_cert

CERT_PREFIX = "mso-client-cert:"
CERT_DOMAIN = b"mso client certificate\0"
HELLO_DOMAIN = b"mso client\0"
ROLES = ("read", "command")
CHANGES = OPERATOR_COMMANDS + EMULATOR_COMMANDS + (m.Authorized,)


class ClientCert(msgspec.Struct, frozen=True, array_like=True):
    """An operator's word that ``key`` (raw Ed25519 public key) is client ``name``'s, in
    ``role``."""

    name: str
    role: str
    key: bytes
    issued: int  # the operator's clock, ms
    operator: str  # the operator key's id
    sig: bytes

    def signed_bytes(self) -> bytes:
        return CERT_DOMAIN + msgspec.msgpack.encode([self.name, self.role, self.key, self.issued])

    @property
    def key_id(self) -> str:
        """How a revocation names this client's key (as a node key's)."""
        return hashlib.blake2b(self.key, digest_size=6).hexdigest()

    def text(self) -> str:
        return CERT_PREFIX + base64.b64encode(msgspec.msgpack.encode(self)).decode()


def certify(
    operator: Signer, name: str, public: Ed25519PublicKey, issued_ms: int, role: str = "command"
) -> ClientCert:
    if role not in ROLES:
        raise KeyError_(f"a client's role is one of {', '.join(ROLES)}, not {role!r}")
    raw = public.public_bytes_raw()
    unsigned = ClientCert(name, role, raw, issued_ms, operator.id, b"")
    sig = operator.private.sign(unsigned.signed_bytes())
    return ClientCert(name, role, raw, issued_ms, operator.id, sig)


def parse_cert(data: str | bytes) -> ClientCert:
    """A certificate from its text (a file) or its bytes (a ClientHello)."""
    try:
        if isinstance(data, str):
            if not data.strip().startswith(CERT_PREFIX):
                raise ValueError
            data = base64.b64decode(data.strip().removeprefix(CERT_PREFIX), validate=True)
        return msgspec.msgpack.decode(data, type=ClientCert)
    except (ValueError, msgspec.DecodeError, msgspec.ValidationError):
        raise KeyError_("not an mso client certificate (made by `mso keygen --client`)") from None


@dataclass(frozen=True)
class ClientIdentity:
    """A client's key and its certificate."""

    private: Ed25519PrivateKey
    cert: ClientCert

    @classmethod
    def load(cls, path: str | Path) -> ClientIdentity:
        """The key file ``path`` and its certificate beside it (``path.cert``)."""
        return cls(*load_key_and_cert(path, parse_cert))

    @functools.cached_property
    def signer(self) -> Signer:
        """Its key as a signer of the commands a ``command`` client may sign itself."""
        signer = Signer(self.private)
        signer.signs = CONNECTION_COMMANDS if self.cert.role == "command" else ()
        return signer

    def hello(self, name: str, mine: bytes, theirs: bytes) -> m.ClientHello:
        """This connection's hello: the certificate, and the signature over both hellos
        (this side's first)."""
        sig = self.private.sign(HELLO_DOMAIN + mine + theirs)
        return m.ClientHello(name, msgspec.msgpack.encode(self.cert), sig)


@functools.lru_cache(maxsize=8)
def operator_client(operator: Signer) -> ClientIdentity:
    """The ``command`` client an operator key holder is: its own key, certified by itself."""
    return ClientIdentity(
        operator.private, certify(operator, f"operator-{operator.id}", operator.public, 0)
    )


@dataclass(frozen=True)
class Admitted:
    """A client whose proof held: its name, role and key."""

    name: str
    role: str
    key_id: str
    public: Ed25519PublicKey


def check(
    msg: m.ClientHello,
    theirs: bytes,
    mine: bytes,
    operators: Mapping[str, Ed25519PublicKey],
    revoked: Set[str] = frozenset(),
) -> Admitted | str:
    """The client a hello proves on the connection whose hellos are ``theirs`` (the client's)
    and ``mine``, or why it does not."""
    if not msg.cert:
        return (
            "this node serves only clients with an operator-certified key (make one with "
            "`mso keygen --client NAME --sign OPERATOR_KEY FILE`, give --client-key FILE or "
            "set $MSO_CLIENT_KEY; or sign with the operator key, --sign)"
        )
    try:
        cert = parse_cert(msg.cert)
    except KeyError_ as exc:
        return str(exc)
    if cert.operator not in operators:
        return f"client {cert.name!r}'s certificate is signed by key {cert.operator}, no operator's"
    if cert.role not in ROLES:
        return f"client {cert.name!r}'s certificate gives an unknown role {cert.role!r}"
    if cert.key_id in revoked:
        return f"client key {cert.key_id} ({cert.name!r}) is revoked"
    public = certified_key(cert, operators)
    if isinstance(public, str):
        return f"client {cert.name!r}'s certificate: {public}"
    try:
        public.verify(msg.sig, HELLO_DOMAIN + theirs + mine)
    except (InvalidSignature, ValueError):
        return f"client {cert.name!r}'s proof does not verify (not made for this connection)"
    return Admitted(cert.name, cert.role, cert.key_id, public)


def may(client: Admitted | str, msg: m.Message) -> str:
    """'' when ``client`` may ask ``msg`` of this node, else why not."""
    if isinstance(client, str):
        return f"refused: {client}"
    if client.role != "command" and isinstance(msg, CHANGES):
        return (
            f"refused: client {client.name!r} may only read (its certificate's role is "
            f"{client.role!r}): {type(msg).__name__} needs a command client"
        )
    return ""
