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


class Ack(_Msg, tag="ack"):
    """Cumulative: every event of the edge instance below ``upto`` has been processed, and so
    has everything derived from them downstream (acks are chained, so a producer keeps each
    event until no single node failure can lose it). ``positions`` are the consumer's output
    sequence numbers at that point: a replacement instance numbers its output from them, so
    what it regenerates by replay is recognised downstream as duplicates."""

    app: str
    edge: int
    epoch: int
    upto: int
    positions: dict[int, int] = msgspec.field(default_factory=dict)


class ChainDelay(_Msg, tag="chain_delay"):
    """From a chain's tail node to its head node: the measured end-to-end delay."""

    app: str
    chain: int
    delay_ms: float
