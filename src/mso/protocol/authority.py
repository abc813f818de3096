"""Operator authority, distinct from overlay membership.

The overlay key (:mod:`mso.protocol.framing`) makes a device a *member*: it may relay, host
vertices and take part in the procedures. Changing what runs needs more: commands that deploy,
undeploy, relocate, remap or shut a node down, and the emulator's LinkStates, must be signed
with an Ed25519 key whose public half the node was configured with: an *operator* key
(``mso node --operator-key``), or the key of the emulator that started the node (for its
LinkStates and Shutdowns). A captured robot holds the overlay key but no operator key: it can
neither deploy code, nor stop nodes, nor rewrite their routes.

Two signed forms:

- a command from a client is wrapped in :class:`~mso.protocol.messages.Authorized`, signed over
  the *node's* hello nonce of that connection and the command's bytes, so it cannot be replayed
  on another connection or to another node;
- an app document carries a *grant* as its last line (a YAML comment, so line numbers in error
  messages stay the same): the signature of the text before it and of its *generation* (the
  operator's clock, in ms, when it was signed). It travels verbatim in ``AppAnnounce`` and
  ``AppSync``, and every node verifies it before it loads the document;
- an undeploy carries the operator's signature of the app's name and the time it was made
  (``StopApp.at``/``key``/``sig``), with no connection in it, so every node it is relayed to
  verifies it, not only the first. It *revokes* every grant of that app made before it: a node
  that holds the revocation refuses the app's older documents (a captured robot replaying an
  undeployed app's announcement brings nothing back), and an undeploy older than the running
  deployment stops nothing.

Sans-IO: keys in, verdicts out. Without any key configured a node is in open mode: the overlay
key is all there is (development, the tests' emulator).
"""

from __future__ import annotations

import base64
import hashlib
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

from mso.protocol import messages as m

PUBLIC_PREFIX = "mso-ed25519-pub:"
PRIVATE_PREFIX = "mso-ed25519-key:"
GRANT = "\n# mso-grant: "
_CMD = b"mso-command-1"
_DOC = b"mso-document-2"
_UNDEPLOY = b"mso-undeploy-1"
_REVOKE_NODE = b"mso-revoke-node-1"
_ORDER = b"mso-order-1"
MAX_REVOKED = 4096  # apps whose undeploy a node remembers (the oldest is forgotten first)

# client commands that change an overlay: an operator's (or the node's emulator's) signature
OPERATOR_COMMANDS = (
    m.DeployRequest,
    m.StopApp,
    m.RelocateRequest,
    m.RemapRequest,
    m.Shutdown,
    m.RevokeNode,
)
# the emulator's own: only it (or an operator) may set a node's links and routes
EMULATOR_COMMANDS = (m.LinkState, m.Shutdown)
# what a command client (mso.protocol.clients) may sign with its own key: carried out by the
# node it asks on that connection (a deploy's grant, an undeploy, a revocation travel on)
CONNECTION_COMMANDS = (m.RelocateRequest, m.RemapRequest, m.Shutdown)
# peer messages that carry an app document (code to import): its grant is checked
DOCUMENT_MESSAGES = (m.AppAnnounce, m.AppSync)


class KeyError_(ValueError):
    """A key text or file that is not an mso Ed25519 key."""


def key_id(public: Ed25519PublicKey) -> str:
    raw = public.public_bytes_raw()
    return hashlib.blake2b(raw, digest_size=6).hexdigest()


def public_text(public: Ed25519PublicKey) -> str:
    return PUBLIC_PREFIX + base64.b64encode(public.public_bytes_raw()).decode()


def _text_or_file(text: str) -> str:
    """A key given inline, or the path of a file holding it."""
    t = text.strip()
    if t.startswith((PUBLIC_PREFIX, PRIVATE_PREFIX)):
        return t
    p = Path(t)
    try:
        if p.is_file() and p.stat().st_size < 4096:
            return p.read_text(encoding="utf-8").strip()
    except OSError:
        pass
    raise KeyError_(f"expected a key '{PUBLIC_PREFIX}...' or a file holding one, got {text!r}")


def parse_public(text: str) -> Ed25519PublicKey:
    t = _text_or_file(text)
    if t.startswith(PRIVATE_PREFIX):  # the public half of a private key file is fine too
        return parse_private(t).public_key()
    try:
        raw = base64.b64decode(t.removeprefix(PUBLIC_PREFIX), validate=True)
        return Ed25519PublicKey.from_public_bytes(raw)
    except ValueError:
        raise KeyError_(f"not an Ed25519 public key: {text!r}") from None


def parse_private(text: str) -> Ed25519PrivateKey:
    t = _text_or_file(text)
    if not t.startswith(PRIVATE_PREFIX):
        raise KeyError_("expected a private key file (made by `mso keygen`)")
    try:
        raw = base64.b64decode(t.removeprefix(PRIVATE_PREFIX), validate=True)
        return Ed25519PrivateKey.from_private_bytes(raw)
    except ValueError:
        raise KeyError_("not an Ed25519 private key") from None


class Signer:
    """Holds a private key: signs commands for one connection and app documents."""

    def __init__(self, private: Ed25519PrivateKey | None = None) -> None:
        self.private = private or Ed25519PrivateKey.generate()
        self.public = self.private.public_key()
        self.id = key_id(self.public)
        # what a client signs with it
        self.signs: tuple[type[m.Message], ...] = OPERATOR_COMMANDS + EMULATOR_COMMANDS

    @classmethod
    def load(cls, text: str) -> Signer:
        return cls(parse_private(text))

    def private_text(self) -> str:
        return PRIVATE_PREFIX + base64.b64encode(self.private.private_bytes_raw()).decode()

    def public_text(self) -> str:
        return public_text(self.public)

    def command(self, node_nonce: bytes, msg: m.Message) -> m.Authorized:
        body = m.encode(msg)
        sig = self.private.sign(_CMD + node_nonce + body)
        return m.Authorized(body=body, key=self.id, sig=sig)

    def grant(self, document: str, at_ms: int) -> str:
        """``document`` with its grant line appended (an earlier grant is replaced); ``at_ms``
        (the signer's clock) is its generation: an undeploy made later revokes it."""
        text = strip_grant(document)
        sig = self.private.sign(_grant_bytes(at_ms, text))
        return f"{text}{GRANT}{self.id} {at_ms} {base64.b64encode(sig).decode()}\n"

    def undeploy(self, app: str, at_ms: int) -> m.StopApp:
        """An undeploy of ``app`` every node verifies; it revokes the grants made before
        ``at_ms``."""
        sig = self.private.sign(_undeploy_bytes(app, at_ms))
        return m.StopApp(app, at=at_ms, key=self.id, sig=sig)

    def order(
        self, req: m.RelocateRequest | m.RemapRequest, at_ms: int, cert: bytes = b""
    ) -> m.RelocateRequest | m.RemapRequest:
        """``req`` as an *order* every node a step of the move reaches can verify (no
        connection in it: :mod:`mso.protocol.warrant`); ``cert``: a command client's
        certificate, for its key."""
        req = msgspec.structs.replace(req, at=at_ms, key=self.id, sig=b"", cert=cert)
        return msgspec.structs.replace(req, sig=self.private.sign(order_bytes(req)))

    def revoke_node(self, node_key: str, at_ms: int) -> m.RevokeNode:
        """A revocation of the node key ``node_key`` that every node verifies."""
        return m.RevokeNode(
            node_key, at_ms, self.id, self.private.sign(revoke_bytes(node_key, at_ms))
        )


class Certificate(Protocol):
    """An operator's word on a key (a node's :class:`~mso.protocol.identity.NodeCert`, a
    client's :class:`~mso.protocol.clients.ClientCert`)."""

    @property
    def operator(self) -> str: ...
    @property
    def sig(self) -> bytes: ...
    @property
    def key(self) -> bytes: ...
    def signed_bytes(self) -> bytes: ...


def certified_key(
    cert: Certificate, operators: Mapping[str, Ed25519PublicKey]
) -> Ed25519PublicKey | str:
    """The key ``cert`` certifies, or why not: signed by no operator's key, or the signature
    does not verify."""
    operator = operators.get(cert.operator)
    if operator is None:
        return f"a certificate signed by an unknown key {cert.operator}"
    try:
        operator.verify(cert.sig, cert.signed_bytes())
        return Ed25519PublicKey.from_public_bytes(cert.key)
    except (InvalidSignature, ValueError):
        return "a certificate whose signature does not verify"


def revoke_bytes(node_key: str, at_ms: int) -> bytes:
    """What an operator signs to revoke a node key."""
    return _REVOKE_NODE + str(at_ms).encode() + b"\n" + node_key.encode()


def order_bytes(req: m.RelocateRequest | m.RemapRequest) -> bytes:
    """What an order's signature covers: the request but its signature fields, and its time."""
    bare = msgspec.structs.replace(req, at=0, key="", sig=b"", cert=b"")
    return _ORDER + str(req.at).encode() + b"\n" + m.encode(bare)


def _grant_bytes(at_ms: int, text: str) -> bytes:
    return _DOC + str(at_ms).encode() + b"\n" + text.encode()


def _undeploy_bytes(app: str, at_ms: int) -> bytes:
    return _UNDEPLOY + str(at_ms).encode() + b"\n" + app.encode()


def strip_grant(document: str) -> str:
    text, sep, _ = document.rpartition(GRANT)
    return text if sep else document


def generation(document: str) -> int:
    """The generation of a document's grant (0 without a well-formed one)."""
    _, sep, grant = document.rpartition(GRANT)
    parts = grant.split()
    if not sep or len(parts) != 3 or not parts[1].isdigit() or len(parts[1]) > 18:
        return 0
    return int(parts[1])


class AuthorityStatus(msgspec.Struct, frozen=True, kw_only=True):
    """How a node checks commands, for status: open or signed, by which operator keys."""

    mode: str  # open | signed
    operators: list[str]  # key ids
    refused: int


@dataclass
class Authority:
    """What a node accepts: the operator keys and its emulator's key it was configured with."""

    operators: dict[str, Ed25519PublicKey] = field(default_factory=dict)
    emulator: Ed25519PublicKey | None = None
    refused: int = 0  # commands and documents refused for want of authority
    # app -> the operator's newest undeploy of it: grants made before it are revoked
    revoked: dict[str, m.StopApp] = field(default_factory=dict)
    # node keys (their ids, mso.protocol.identity) the operator withdrew
    revoked_nodes: frozenset[str] = frozenset()
    # a chain end's remap is no warrant for moving the chain's other vertices: it needs an
    # operator's order (mso.protocol.warrant; mso node --strict-moves)
    strict_moves: bool = False

    @classmethod
    def configure(cls, operators: list[str], emulator: str | None = None) -> Authority:
        auth = cls({}, parse_public(emulator) if emulator else None)
        for text in operators:
            pub = parse_public(text)
            auth.operators[key_id(pub)] = pub
        return auth

    @classmethod
    def from_env(cls, operators: list[str]) -> Authority:
        """Operator keys given, plus the emulator's key if an emulator started this node."""
        return cls.configure(operators, os.environ.get("MSO_EMULATOR_KEY") or None)

    @property
    def open(self) -> bool:
        return not self.operators and self.emulator is None

    @property
    def signed(self) -> bool:
        """Operator keys are configured: apps come and go only by an operator's signature."""
        return bool(self.operators)

    def status(self) -> AuthorityStatus:
        """For the driver's part of status (the key ids, never the keys)."""
        return AuthorityStatus(
            mode="open" if self.open else "signed",
            operators=sorted(self.operators),
            refused=self.refused,
        )

    def _signers(
        self, msg: m.Message, client: dict[str, Ed25519PublicKey]
    ) -> dict[str, Ed25519PublicKey] | None:
        """Who may sign ``msg`` (``client``: a command client's own key); None when it needs
        no signature on this node."""
        em = {key_id(self.emulator): self.emulator} if self.emulator is not None else {}
        own = client if isinstance(msg, CONNECTION_COMMANDS) else {}
        if isinstance(msg, EMULATOR_COMMANDS) and (em or self.operators):
            return {**self.operators, **em, **own}
        if isinstance(msg, OPERATOR_COMMANDS) and self.operators:
            return {**self.operators, **em, **own}
        return None

    @property
    def certifiers(self) -> dict[str, Ed25519PublicKey]:
        """Keys whose certificate of a client this node takes: an operator's, its emulator's."""
        em = {key_id(self.emulator): self.emulator} if self.emulator is not None else {}
        return {**self.operators, **em}

    def command(
        self,
        node_nonce: bytes,
        msg: m.Message,
        client: dict[str, Ed25519PublicKey] | None = None,
    ) -> m.Message | str:
        """The command a client may carry out, or why it is refused (``client``: the key of
        the command client on this connection, which may sign what the connection carries)."""
        client = client or {}
        inner = msg
        if isinstance(msg, m.Authorized):
            try:
                inner = m.decode(msg.body)
            except Exception:
                return self._refuse("a signed command that does not decode")
            if isinstance(inner, m.Authorized):
                return self._refuse("a signed command inside a signed command")
            signers = self._signers(inner, client)
            if signers is None:  # this node needs no signature for it: the command as it is
                return inner
            pub = signers.get(msg.key)
            if pub is None:
                return self._refuse(f"key {msg.key} has no authority on this node")
            try:
                pub.verify(msg.sig, _CMD + node_nonce + msg.body)
            except InvalidSignature:
                return self._refuse("bad signature (not made for this connection)")
        elif self._signers(msg, client) is not None:
            return self._refuse(
                f"{type(msg).__name__} needs an operator's signature on this node "
                "(give --sign KEYFILE or set $MSO_SIGN)"
            )
        if isinstance(inner, m.DeployRequest) and self.operators:
            why = self.document(inner.document)
            if why:
                return why
        return inner

    def document(self, document: str, app: str | None = None) -> str:
        """'' when ``document`` carries a valid operator grant (or none is needed) and, if
        the app's name is given, one its undeploy has not revoked."""
        if not self.operators:
            return ""
        text, sep, grant = document.rpartition(GRANT)
        if not sep:
            return self._refuse("the app document carries no operator grant")
        parts = grant.split()
        if len(parts) != 3 or not parts[1].isdigit() or len(parts[1]) > 18:
            return self._refuse("the app document's grant is not 'KEY GENERATION SIGNATURE'")
        kid, at, sig = parts
        pub = self.operators.get(kid)
        if pub is None:
            return self._refuse(f"the app document's grant is by key {kid}, not an operator's")
        try:
            pub.verify(base64.b64decode(sig, validate=True), _grant_bytes(int(at), text))
        except (InvalidSignature, ValueError):
            return self._refuse("the app document's grant does not match it")
        return self.revocation(app, document) if app is not None else ""

    def revocation(self, app: str, document: str) -> str:
        """'' unless an operator's undeploy of ``app`` revoked ``document``'s grant (the
        grant's signature is checked by :meth:`document`; this is the cheap part)."""
        stop = self.revoked.get(app) if self.operators else None
        if stop is None or generation(document) > stop.at:
            return ""
        return self._refuse(
            f"app {app!r} was undeployed by an operator at {stop.at} ms, after its grant was "
            "made: only a grant signed since brings it back"
        )

    def undeploy(self, msg: m.StopApp) -> str:
        """'' when ``msg`` carries an operator's signed undeploy (then its revocation is
        remembered), else why not. Open nodes need none."""
        if not self.operators or self.revoked.get(msg.app) == msg:  # (verified already)
            return ""
        if not msg.sig:
            return self._refuse(f"undeploying {msg.app!r} needs an operator's signed undeploy")
        pub = self.operators.get(msg.key)
        if pub is None:
            return self._refuse(f"the undeploy of {msg.app!r} is by key {msg.key}, no operator's")
        try:
            pub.verify(msg.sig, _undeploy_bytes(msg.app, msg.at))
        except InvalidSignature:
            return self._refuse(f"the undeploy of {msg.app!r} does not match its signature")
        known = self.revoked.pop(msg.app, None)
        self.revoked[msg.app] = msg if known is None or msg.at > known.at else known
        while len(self.revoked) > MAX_REVOKED:
            del self.revoked[next(iter(self.revoked))]
        return ""

    def _refuse(self, why: str) -> str:
        self.refused += 1
        return f"refused: {why}"
