"""The first message on a connection: a node's or a client's hello. Part of the wire's message
union (:data:`mso.protocol.messages.Message`, which re-exports every name: import them from
there); each message tagged and laid out as every other."""

from __future__ import annotations

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class PeerHello(_Msg, tag="hello"):
    """First message on a node-to-node connection: who is speaking; with node identities,
    its certificate and its signature over both hellos (:mod:`mso.protocol.identity`)."""

    node: str
    cert: bytes = b""
    sig: bytes = b""


class ClientHello(_Msg, tag="client"):
    """First message from a CLI or API client connection; with a client identity, its
    certificate and its signature over both hellos (:mod:`mso.protocol.clients`)."""

    name: str
    cert: bytes = b""
    sig: bytes = b""
