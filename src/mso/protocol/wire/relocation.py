"""Moves (§3.4, :mod:`mso.protocol.procedures.relocation`): prepare, switch with a marker, state
handover, and where vertices run. Part of the wire's message union
(:data:`mso.protocol.messages.Message`, which re-exports every name: import them from there);
each message tagged and laid out as every other."""

from __future__ import annotations

from typing import Any

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class Marker(_Msg, tag="marker"):
    """Sent down the old path after the producer switched an edge: every event before ``seq``
    went the old way. Travels as data so it never overtakes them."""

    app: str
    edge: int
    seq: int
    rid: int
    to: str  # where the vertex is going: its old instance hands over there


class Prepare(_Msg, tag="prepare"):
    """To the target node: create an instance of ``vertex`` that buffers until handover."""

    app: str
    vertex: str
    rid: int
    # a replacement after a failure, with the edges it must hear a Resume on before it runs
    restore: bool = False
    resumes: list[list[Any]] = msgspec.field(default_factory=list)  # [edge, producer?]
    # the coordinator's placement of the app and its versions: a node that hosted no part of
    # the app is not told of moves, so it learns the placement it will exchange events in here
    placed: dict[str, str] = msgspec.field(default_factory=dict)
    versions: dict[str, int] = msgspec.field(default_factory=dict)
    vanished: list[str] = msgspec.field(default_factory=list)
    # a restore: the nodes the coordinator knows hold the vertex's replicas (a target that
    # restarted since was never told, and would start the state afresh: seed 8029)
    replicas: list[str] = msgspec.field(default_factory=list)
    order: bytes = b""  # the operator's order the move carries out (mso.protocol.warrant)


class Unprepare(_Msg, tag="unprepare"):
    """To a relocation's target, from its coordinator: the move failed before any producer
    switched to the prepared instance, so drop it."""

    app: str
    vertex: str
    rid: int


class Moving(_Msg, tag="moving"):
    """To a move's old host, from its coordinator (with operator keys): ``vertex`` goes to
    ``to`` in move ``rid``; hand it over when that move's markers come. The host takes the
    markers of a move it holds such a warrant for, or coordinates itself, and no others."""

    app: str
    vertex: str
    rid: int
    to: str
    order: bytes = b""  # the operator's order the move carries out (mso.protocol.warrant)


class Prepared(_Msg, tag="prepared"):
    app: str
    vertex: str
    rid: int
    node: str
    error: str = ""
    no_app: bool = False  # refused because the node does not hold the app: sync it to it


class Switch(_Msg, tag="switch"):
    """To a producer's node: send ``edge`` to ``to`` from now on, and a marker the old way."""

    app: str
    edge: int
    to: str
    rid: int
    # where the coordinator moves the vertex from: the marker's way once another input of the
    # vertex, from this same node, has switched (the node's placement says ``to`` by then)
    source: str = ""
    order: bytes = b""  # the operator's order the move carries out (mso.protocol.warrant)


class Handover(_Msg, tag="handover"):
    """The old instance's state and channel positions, after every in-edge's marker."""

    app: str
    vertex: str
    rid: int
    state: bytes  # msgpack of get_state()
    # edge -> [next expected seq, acknowledged up to, superseded, expired, deadline missed,
    # the generation of its numbering (mso.protocol.channel)]
    inputs: dict[int, list[int]]
    # edge -> [next_seq, acked, [unacked events...], positions, generation, positions' gens]
    outputs: dict[int, list[Any]]
    processed: int
    emitted: int
    gate: list[Any] = msgspec.field(default_factory=list)  # pending chained-ack checkpoints
    parts: int = 0  # HandoverEvents sent ahead of it (the outputs' events past one frame)
    version: int = 0  # the move's version (the old host counted it)
    # input edge -> the provenance marks its consumer has of a merge's output (absent: unknown)
    marks: dict[int, dict[int, list[int]]] = msgspec.field(default_factory=dict)
    # output edge -> the marks its consumer has, for a replacement that still sends that
    # consumer only what is past them (mso.protocol.provenance): moved before it made
    # anything past them, the new host sends on what the consumer has too (seed 96201)
    lacks: dict[int, dict[int, list[int]]] = msgspec.field(default_factory=dict)
    # input edge -> the generations of the numberings those marks name (those not 0)
    markgens: dict[int, dict[int, int]] = msgspec.field(default_factory=dict)


class HandoverEvents(_Msg, tag="handover_events"):
    """Unacknowledged output events of a move, sent ahead of its :class:`Handover` in parts
    of about a megabyte when they would not fit one frame (a backlog that store and forward
    kept for a consumer out of reach)."""

    app: str
    vertex: str
    rid: int
    edge: int
    first: int  # the first event's sequence number
    events: list[bytes]


class Moved(_Msg, tag="moved"):
    """``vertex`` now runs on ``node``: told to the nodes that host part of the app (not to
    every node: :mod:`mso.protocol.procedures.placement`). Sent by ``node`` itself, it carries
    its incarnation, so news from an incarnation that has since restarted or reset is ignored;
    ``version`` counts the vertex's moves, so older news loses."""

    app: str
    vertex: str
    node: str
    incarnation: int = -1  # -1: sent by another node (an old host after its handover)
    version: int = 0  # 0: not counted (taken as today: the last word wins)


class HandoverDone(_Msg, tag="handover_done"):
    """To a move's coordinator: the vertex runs on ``node`` now, as its ``version``-th move."""

    app: str
    vertex: str
    rid: int
    node: str = ""
    version: int = 0


class PlacementQuery(_Msg, tag="where"):
    """Where do the vertices of ``app`` run, as you know it? From a node about to act on an
    app it hosts no part of (its view is not kept up to date: it asks first). With
    ``fetch``, from a node that holds none of it (a client's request there): a node that
    holds it sends the app first (``AppSync``), as only the nodes that take part hold it."""

    app: str
    qid: int
    fetch: bool = False


class PlacementReply(_Msg, tag="where_reply"):
    """The answer to :class:`PlacementQuery`: the sender's placement of ``app`` with each
    vertex's version (the asker keeps, per vertex, the highest)."""

    app: str
    qid: int
    placed: dict[str, str]
    versions: dict[str, int] = msgspec.field(default_factory=dict)
    vanished: list[str] = msgspec.field(default_factory=list)  # its instance went (a restart)
