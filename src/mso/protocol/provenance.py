"""Provenance: each output of a merge vertex says which input event it was made from.

A restored instance regenerates by replay what its lost instance had made and not got
acknowledged. With one input the replay comes in the order the events first came, so numbering
the output from the producers' acks (:class:`mso.protocol.messages.Ack` ``positions``) gives
every regenerated event the number it had and the consumer drops what it has. A merge's output
interleaves its inputs in the order their events happened to arrive, which a replay does not
repeat: numbered the same way, an event the consumer lacks could take the number of one it has
(dropped: lost) and one it has a number it lacks (delivered twice) — fault seeds 1964, 3859,
5490, 8029, 8895, 9916.

So a merge's (``Layout.merges``) output events carry their provenance, ``(input edge, input
sequence number, k)`` (``k``: the k-th output made from that event), in a header of
:data:`HEADER` bytes the consumer strips before decoding. The consumer keeps, per input of the
merge, the provenance of the last event it has; each input is processed in order, so it has
everything made from that input up to there. A replacement told these marks (``Resume.marks``)
sends on each edge only what was made past them, numbered from where the consumer stands: every
event once, whatever the interleaving.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping

HEADER = struct.Struct("<HqI")  # input edge, input sequence number, k

Mark = tuple[int, int]  # (input sequence number, k): the last event made from one input
Marks = dict[int, Mark]  # input edge -> mark


def stamp(payloads: list[bytes], edge: int, first: int, owners: list[int]) -> list[bytes]:
    """``payloads`` made from a batch of ``edge`` starting at sequence number ``first``;
    ``owners[j]``: the index in the batch of the event the j-th payload was made from."""
    out = []
    k, last = 0, -1
    pack = HEADER.pack
    for payload, owner in zip(payloads, owners, strict=True):
        k = k + 1 if owner == last else 0
        last = owner
        out.append(pack(edge, first + owner, k) + payload)
    return out


def strip(events: Iterable[bytes], marks: Marks | None) -> list[bytes]:
    """The payloads without their headers; ``marks`` (if kept) learn the last provenance seen
    per input. A frame too short for a header (no genuine node sends one) passes unchanged:
    its consumer fails to decode it and counts it."""
    out = []
    size = HEADER.size
    for ev in events:
        if len(ev) < size:
            out.append(ev)
            continue
        edge, seq, k = HEADER.unpack_from(ev)
        if marks is not None:
            marks[edge] = (seq, k)
        out.append(ev[size:])
    return out


def past(payloads: list[bytes], marks: Mapping[int, Mark]) -> list[bytes]:
    """The stamped payloads made after the marks: what a consumer with those marks lacks."""
    if not marks:
        return payloads
    keep = []
    for ev in payloads:
        edge, seq, k = HEADER.unpack_from(ev)
        mark = marks.get(edge)
        if mark is None or (seq, k) > mark:
            keep.append(ev)
    return keep


def to_wire(marks: Marks | None) -> dict[int, list[int]] | None:
    return None if marks is None else {e: [s, k] for e, (s, k) in marks.items()}


def from_wire(data: Mapping[int, list[int]] | None) -> Marks | None:
    """Marks from a message (a peer's: malformed ones are dropped, never trusted as a mark)."""
    if data is None:
        return None
    return {int(e): (int(v[0]), int(v[1])) for e, v in data.items() if len(v) == 2}
