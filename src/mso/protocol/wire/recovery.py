"""Recovery after a failure (:mod:`mso.protocol.procedures.restore`) and chain replication:
rewiring an edge, resuming it, snapshots and their replicas. Part of the wire's message union
(:data:`mso.protocol.messages.Message`, which re-exports every name: import them from there);
each message tagged and laid out as every other."""

from __future__ import annotations

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class Rewire(_Msg, tag="rewire"):
    """After a failure: the edge's other end now runs on ``to``. The receiver is the edge's
    producer (it replays its unacknowledged events there) or its consumer."""

    app: str
    edge: int
    to: str
    rid: int
    producer: bool
    order: bytes = b""  # the operator's order the move carries out (mso.protocol.warrant)
    # the version of the vertex the coordinator restores (its view's; -1: not said): an end
    # that knows a later one, on a live node, refuses to follow a restore of a stale view
    version: int = -1


class Resume(_Msg, tag="resume"):
    """To a replacement instance: where the edge stands. From the producer: the first event it
    will replay (``start``) and the output positions of the last ack it got; from the consumer:
    the next sequence number it expects and, where exact, its own output positions there
    (``Restorer._outputs_at_start``)."""

    app: str
    edge: int
    rid: int
    producer: bool
    start: int
    positions: dict[int, int] = msgspec.field(default_factory=dict)
    # from a producer that retains the edge's events for a replica (chain replication): the
    # first one it replays (-1: none retained, it replays from ``start``)
    retained: int = -1
    # from the consumer of a merge: the provenance of the last event it has from each of the
    # merge's inputs (mso.protocol.provenance; None: it does not know)
    marks: dict[int, list[int]] | None = None
    # from a producer restored with its consumer: it numbers the edge anew, not as the marks
    # of the lost consumer's consumers knew it
    fresh: bool = False
    # from a merge to its forwarder: the merge's inputs numbered anew at its restore (their
    # producers lost with it), whose marks kept downstream name another numbering
    renumbered: list[int] = msgspec.field(default_factory=list)
    # from a merge restored since: the first number of the edge it made itself (-1: none).
    # From there on its outputs interleave its inputs anew, unlike the lost instance's: a
    # consumer's snapshot counted past it counted other events under those numbers (44712)
    remade: int = -1
    # from a consumer: ``start`` is past its own consumers' marks, not a position it held
    # (Restorer._start_past); a producer that numbers from its acks' positions says so back
    unheld: bool = False
    # the generation of the edge's numbering ``start`` is a number of (0: the deployment's;
    # mso.protocol.channel), and of each of ``positions`` (omitted for 0)
    gen: int = 0
    gens: dict[int, int] = msgspec.field(default_factory=dict)
    # from a consumer, with ``marks``: the generations of the numberings they name (not 0)
    markgens: dict[int, int] = msgspec.field(default_factory=dict)
    # from a producer: every event from ``start`` on is new (made since its restore by a
    # source, or of such events only) and no ack since numbered what it made of them: an
    # instance fed by it makes none of what its lost instance made (``OutChannel.new_from``)
    new: bool = False


class Replicate(_Msg, tag="replicate"):
    """A snapshot of ``vertex``'s state, aligned: taken when it had processed exactly
    ``inputs`` (edge -> events) and produced ``outputs`` (edge -> [acked, the events not yet
    acknowledged]). From its host to a replica (``rid`` 0, answered by ``ReplicaAck``), or from
    a replica to the replacement of a failed host that fetched it (``rid``: the restore)."""

    app: str
    vertex: str
    k: int  # the snapshot's number: a replica keeps the newest
    state: bytes
    inputs: dict[int, int]
    outputs: dict[int, tuple[int, list[bytes]]]
    processed: int = 0
    emitted: int = 0
    rid: int = 0
    # a forwarder's: what it had processed of the merge's inputs (mso.protocol.provenance)
    marks: dict[int, list[int]] | None = None
    # the generations of the numberings those marks are of (mso.protocol.channel; not 0)
    markgens: dict[int, int] = msgspec.field(default_factory=dict)
    # the vertex's placement version at the host that took it (its moves counted, as
    # ``Moved``'s): a replica weighs a later host's replica set against its copy's
    version: int = 0


class ReplicaAck(_Msg, tag="replica_ack"):
    """From a replica to the host: snapshot ``k`` of ``vertex`` is held."""

    app: str
    vertex: str
    k: int


class Release(_Msg, tag="release"):
    """To an edge's producer, from its consumer's host: a replica holds the consumer's state
    as of event ``upto``; the events before it need not be retained any more."""

    app: str
    edge: int
    upto: int


class Replay(_Msg, tag="replay"):
    """To an edge's producer, from a replacement that starts from a replica's snapshot:
    send again from ``start`` (the snapshot's position, still retained) as if acknowledged
    only so far, with ``positions`` (the snapshot's output positions) as that ack's."""

    app: str
    edge: int
    start: int
    positions: dict[int, int] = msgspec.field(default_factory=dict)


class ReplicaSet(_Msg, tag="replica_set"):
    """Broadcast by a replicated vertex's host: the nodes that hold its replicas."""

    app: str
    vertex: str
    nodes: list[str]
    # from the vertex's host: its placement version there (its moves counted, as ``Moved``'s);
    # -1 from a node that runs no instance of it and answers for itself
    version: int = -1


class FetchReplica(_Msg, tag="fetch_replica"):
    """From a restore's replacement to a replica: send the newest snapshot you hold (a
    ``Replicate`` with ``rid``; ``k`` -1 and no state if none)."""

    app: str
    vertex: str
    rid: int
