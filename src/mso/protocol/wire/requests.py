"""What clients ask a node (relocate, remap, deploy, status), the emulator's control, and operator
authority's messages. Part of the wire's message union (:data:`mso.protocol.messages.Message`,
which re-exports every name: import them from there); each message tagged and laid out as every
other."""

from __future__ import annotations

from typing import Any

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class RelocateRequest(_Msg, tag="relocate"):
    """Move ``vertex`` upstream (onto its predecessor's node), downstream (onto its successor's
    next node) or to ``target``."""

    app: str
    vertex: str
    direction: str = ""
    target: str = ""
    # an operator's order, verified by every node a step of the move reaches (with operator
    # keys: mso.protocol.warrant): the signer's clock (ms), key id, signature, and a command
    # client's certificate
    at: int = 0
    key: str = ""
    sig: bytes = b""
    cert: bytes = b""


class RemapRequest(_Msg, tag="remap"):
    """Re-place chains along freshly probed routes (§3.4.2; several: §3.4.3, in dependency
    order). ``chains`` are chain indices; empty with ``everything`` remaps them all.
    ``within_s``: how long the client waits for the reply (0: not said); the remap ends
    before then, its moves so far told, if it has not finished."""

    app: str
    chains: list[int]
    everything: bool = False
    # an operator's order, verified by every node a step of the move reaches (with operator
    # keys: mso.protocol.warrant): the signer's clock (ms), key id, signature, and a command
    # client's certificate
    at: int = 0
    key: str = ""
    sig: bytes = b""
    cert: bytes = b""
    within_s: float = 0.0


class RemapReply(_Msg, tag="remap_reply"):
    app: str
    ok: bool
    moved: dict[str, str]
    elapsed_ms: float = 0.0
    error: str = ""


class RelocateReply(_Msg, tag="relocate_reply"):
    app: str
    vertex: str
    ok: bool
    node: str = ""
    elapsed_ms: float = 0.0
    error: str = ""


class DeployRequest(_Msg, tag="deploy"):
    """``within_s``: how long the client waits for the reply (0: not said); the node answers
    before then, refusing the deployment if it has not finished."""

    document: str
    file: str = "<app>"
    within_s: float = 0.0


class DeployReply(_Msg, tag="deploy_reply"):
    app: str
    ok: bool
    placement: dict[str, str]
    elapsed_ms: float
    error: str = ""


class StatusRequest(_Msg, tag="status"):
    """``everywhere``: the receiving node gathers every node's status before replying."""

    req: int = 0
    everywhere: bool = False


class StatusReply(_Msg, tag="status_reply"):
    req: int
    nodes: dict[str, Any]


class LinkState(_Msg, tag="links"):
    """From the emulator controller: current neighbours (address, link shape) and routes."""

    version: int
    neighbours: dict[str, list[Any]]  # node -> [host, port, bandwidth_mbps|None, delay_ms, loss]
    routes: dict[str, list[Any]]  # destination -> [next hop, hops]
    # the links the routes were computed on ([a, b] pairs), so that the node can route around
    # a relay whose daemon it holds failed: in user space the daemon is the relay
    links: list[list[str]] = msgspec.field(default_factory=list)


class Shutdown(_Msg, tag="shutdown"):
    pass


class RevokeNode(_Msg, tag="revoke_node"):
    """An operator withdraws a node key (its id: :mod:`mso.protocol.identity`): every node that
    hears it refuses that key on links and in origins from then on. The operator's signature
    covers the key id and its time (``at``/``key``/``sig``) and nothing of a connection, so
    every node it is passed on to verifies it itself (:mod:`mso.protocol.revocation`). Its
    echo, unsigned, answers the client."""

    node_key: str
    at: int = 0
    key: str = ""
    sig: bytes = b""


class Authorized(_Msg, tag="auth"):
    """A client command (``body``, an encoded message) signed with the Ed25519 key ``key``
    (its id) over the node's hello nonce of this connection and ``body``."""

    body: bytes
    key: str
    sig: bytes


class Refused(_Msg, tag="refused"):
    """The reply to a client command refused for want of authority, and why."""

    reason: str
