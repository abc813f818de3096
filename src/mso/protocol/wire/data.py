"""The data plane's messages: events on an edge instance, their acks, a chain's measured delay.
Part of the wire's message union (:data:`mso.protocol.messages.Message`, which re-exports every
name: import them from there); each message tagged and laid out as every other."""

from __future__ import annotations

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class Data(_Msg, tag="data"):
    """Events ``seq, seq+1, ...`` on one edge instance, encoded with the edge's format.

    ``also`` folds in other edges that carry the very same events at the same time to the
    same node — a vertex whose output feeds several vertices on one robot — as
    ``(edge, seq, floor)``: one frame on the radio, not one per edge (an empty ``also`` costs
    one byte). Retransmissions go edge by edge."""

    app: str
    edge: int
    epoch: int
    seq: int
    events: list[bytes]
    # when the oldest of these events entered its chain (the nodes' shared clock): the chain's
    # tail measures end-to-end delay from it
    ts: float = 0.0
    # the producer will never send anything below this again (its acked position): a consumer
    # that still waits for an event below it skips to it (events a parked chain dropped)
    floor: int = 0
    also: list[tuple[int, int, int]] = msgspec.field(default_factory=list)
    # of a stamped producer (mso.protocol.provenance): the generations of the numberings its
    # events' headers name (mso.protocol.channel; omitted for 0): what the consumer's marks
    # are of, so that a restore tells marks of one numbering from a producer's of another
    gens: dict[int, int] = msgspec.field(default_factory=dict)


class Ack(_Msg, tag="ack"):
    """Cumulative: every event of the edge instance below ``upto`` has been processed, and so
    has everything derived from them downstream (acks are chained, so a producer keeps each
    event until no single node failure can lose it). ``positions`` are the consumer's output
    sequence numbers at that point: a replacement instance numbers its output from them, so
    what it regenerates by replay is recognised downstream as duplicates. ``gens``: the
    generation of each of those edges' numberings (``mso.protocol.channel``: omitted for 0,
    the deployment's), so that positions of a numbering made anew are told from the first's."""

    app: str
    edge: int
    epoch: int
    upto: int
    positions: dict[int, int] = msgspec.field(default_factory=dict)
    gens: dict[int, int] = msgspec.field(default_factory=dict)


class ChainDelay(_Msg, tag="chain_delay"):
    """From a chain's tail node to its head node: the measured end-to-end delay."""

    app: str
    chain: int
    delay_ms: float
