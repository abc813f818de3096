"""Operator-announced revocation of node keys: one signed word that reaches every node.

``--revoke-node`` withdraws a captured robot's key on the nodes whose configuration says so;
the others still take it. ``mso revoke-node KEYID --sign OPERATOR_KEY`` instead sends a
:class:`~mso.protocol.messages.RevokeNode` signed by the operator over the key id and its time,
with nothing of a connection in it, so every node verifies it itself: the node the client asks
passes it to each of its proven neighbours, each of them to theirs (a node passes on only what
is new to it, so it floods once), and every node tells the revocations it holds to a neighbour
each time a link to it is proven, so a node away (or restarted) when it was announced learns
it when it is back. A node holds at most ``MAX_HELD`` (the oldest forgotten first).

Sans-IO: keys in, verdicts out.
"""

from __future__ import annotations

from collections.abc import Mapping

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from mso.protocol import messages as m
from mso.protocol.authority import revoke_bytes

MAX_HELD = 4096  # revocations a node holds
MAX_KEY_ID = 64  # a key id is 12 hex digits; anything much longer is not one


class Revocations:
    """The operator's announced revocations this node holds, oldest first."""

    def __init__(self) -> None:
        self.held: dict[str, m.RevokeNode] = {}

    def take(self, msg: m.RevokeNode, operators: Mapping[str, Ed25519PublicKey]) -> str | None:
        """None when ``msg`` is a new revocation an operator signed (now held); '' when it is
        held already; else why it is refused."""
        if msg.node_key in self.held:
            return ""
        if not operators:
            return "no operator keys on this node: nothing to revoke"
        if not msg.node_key or len(msg.node_key) > MAX_KEY_ID:
            return "not a node key id"
        pub = operators.get(msg.key)
        if pub is None:
            return f"the revocation of {msg.node_key} is by key {msg.key!r}, no operator's"
        try:
            pub.verify(msg.sig, revoke_bytes(msg.node_key, msg.at))
        except InvalidSignature:
            return f"the revocation of {msg.node_key} does not match its signature"
        self.held[msg.node_key] = msg
        while len(self.held) > MAX_HELD:
            del self.held[next(iter(self.held))]
        return None

    def keys(self) -> frozenset[str]:
        return frozenset(self.held)

    def latest(self, n: int) -> list[m.RevokeNode]:
        """The ``n`` newest, to tell a neighbour whose link is proven."""
        return list(self.held.values())[-n:]
