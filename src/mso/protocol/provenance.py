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

A merge lost *with* its consumer (one node hosting both) takes the interleaving along: the
consumer's replacement, from its replica's snapshot, gets the merge's replay in a new order, and
numbered by its own positions its output would not match what its own consumer has (seed 8029:
one event twice, one lost, and a count that went back). So the merge's direct consumer (a
*forwarder*, ``Layout.forwarders``) passes on each event's provenance, in the merge's inputs'
terms: its outputs carry the header of the event they were made from, ``k`` combining the
merge's ``k`` and the forwarder's own (:func:`forward`). Its consumer keeps the marks; on a
restore it tells the replacement (``Resume.marks``), which numbers its output from where that
consumer stands, sends only what was made past the marks, and takes its input up to the marks
first (:class:`CatchUp`): its state then counts what its consumer saw before anything newer.
The merge's order downstream of the forwarder is not logged: a merge lost with two vertices
after it is not exact (docs/architecture.md).

A *fork* (``Layout.forks``: two consumers or more) stamps its outputs too, with its input's
provenance: after two partitions in quick succession each side may have re-placed it, and its
consumers then hold outputs of different lost instances numbered alike (seed 5040: one had the
source's events 0-9 as 12-21, the other 24 events of the other side's instance). Numbered by
one consumer's position, the next replacement's output is wrong for the other; with each
consumer's marks in the input's terms it sends each only what that one lacks. A consumer
started fresh from a stamped producer's ``Resume`` keeps marks from then on (empty: what its
lost instance had went on and was acknowledged).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping

HEADER = struct.Struct("<HqI")  # input edge, input sequence number, k

Mark = tuple[int, int]  # (input sequence number, k): the last event made from one input
Marks = dict[int, Mark]  # input edge -> mark
Head = tuple[int, int, int]  # one event's header: (input edge, input sequence number, k)
NO_HEAD: Head = (0xFFFF, -1, 0)  # an event too short for a header (no genuine node sends one)
CATCH_UP_S = 2.0  # a forwarder's replacement holds newer input this long at most


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


def split(events: Iterable[bytes]) -> tuple[list[bytes], list[Head]]:
    """The payloads and their headers (a forwarder's input, stripped as it is fed)."""
    payloads, heads = [], []
    size = HEADER.size
    for ev in events:
        if len(ev) < size:
            payloads.append(ev)
            heads.append(NO_HEAD)
        else:
            heads.append(HEADER.unpack_from(ev))
            payloads.append(ev[size:])
    return payloads, heads


def note(events: Iterable[bytes], marks: Marks | None) -> None:
    """Learn the marks of stamped events kept whole (a forwarder strips them when fed)."""
    if marks is None:
        return
    size = HEADER.size
    for ev in events:
        if len(ev) >= size:
            edge, seq, k = HEADER.unpack_from(ev)
            marks[edge] = (seq, k)


def forward(payloads: list[bytes], heads: list[Head], owners: list[int]) -> list[bytes]:
    """A forwarder's ``payloads``, each stamped with the header of the event it was made
    from (``owners[j]``: its index in the batch), ``k`` combining that event's and the
    forwarder's own count (16 bits each: past 65,535 outputs of one event they tie)."""
    out = []
    j, last = 0, -1
    pack = HEADER.pack
    for payload, owner in zip(payloads, owners, strict=True):
        j = j + 1 if owner == last else 0
        last = owner
        # (a batch's headers are kept as it is fed; never trust they are there: no crash)
        edge, seq, k = heads[owner] if 0 <= owner < len(heads) else NO_HEAD
        out.append(pack(edge, seq, (min(k, 0xFFFF) << 16) | min(j, 0xFFFF)) + payload)
    return out


def processed(marks: Marks | None, later: Iterable[bytes]) -> Marks | None:
    """A forwarder's marks as of what it processed: ``marks`` (learnt on delivery) taken
    back to just before the first of each input's ``later`` events (delivered, whole, not
    processed yet)."""
    if marks is None:
        return None
    out = dict(marks)
    seen: set[int] = set()
    size = HEADER.size
    for ev in later:
        if len(ev) < size:
            continue
        edge, seq, k = HEADER.unpack_from(ev)
        if edge not in seen:
            seen.add(edge)
            out[edge] = (seq, k - 1) if k > 0 else (seq - 1, 0xFFFFFFFF)
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


def outlived(payloads: list[bytes], marks: Marks) -> None:
    """Drop from ``marks`` each input an event of ``payloads`` (sent on) went past: each input
    comes in order, so what follows is past it too, unless that input is numbered anew later —
    and then a mark kept would drop its new events as had (fault seed 84293: a forwarder's
    replacement, fed a restored merge's input anew from 0, dropped its first 14 events)."""
    for ev in payloads:
        edge, seq, k = HEADER.unpack_from(ev)
        mark = marks.get(edge)
        if mark is not None and (seq, k) > mark:
            del marks[edge]


Held = dict[int, tuple[Mark, int]]  # input edge -> (a consumer's mark, the generation it names)


def held(marks: Marks, gens: Mapping[int, int]) -> Held:
    """``marks`` with the generations of the numberings they name (``gens``; 0 left out)."""
    return {i: (mark, gens.get(i, 0)) for i, mark in marks.items()}


def past_held(payloads: list[bytes], marks: Held, gens: Mapping[int, int]) -> list[bytes]:
    """The stamped payloads a consumer with ``marks`` lacks, by generation: an event of an
    input numbered in the generation its mark names (``gens``: the producer's frames' word,
    0 left out) and not past that mark is had; one of another numbering is not. Each mark an
    event of its own numbering went past is dropped (what follows is past it too)."""
    if not marks:
        return payloads
    keep = []
    for ev in payloads:
        edge, seq, k = HEADER.unpack_from(ev)
        mk = marks.get(edge)
        if mk is None or mk[1] != gens.get(edge, 0):
            keep.append(ev)
        elif (seq, k) > mk[0]:
            keep.append(ev)
            del marks[edge]
    return keep


def renamed(marks: Marks, held: Held, gens: Mapping[int, int]) -> None:
    """Drop from ``marks`` each input whose events come in another numbering than the one
    its mark held by generation names (``gens``: the producer's frames' word, 0 left out):
    that input was numbered anew after the marks were taken, with no word that said so (a
    merge restored after its forwarder, a producer of that input lost too: fault seed
    277659, the forwarder dropped a restarted source's first 12 events as had by the sink's
    marks of the first numbering). Held, the mark still drops what its own numbering makes
    again, should the input come back to it (seed 150917)."""
    for i, (_, gen) in held.items():
        if i in marks and gens.get(i, 0) != gen:
            del marks[i]


def without(marks: Marks, inputs: Iterable[int]) -> Marks:
    """``marks`` but those of ``inputs`` (numbered anew: their marks name a numbering gone)."""
    gone = set(inputs)
    return {i: mk for i, mk in marks.items() if i not in gone}


def highest(a: Marks, b: Marks) -> Marks:
    """The higher mark of each input over two views of what one consumer has."""
    out = dict(a)
    for i, mark in b.items():
        out[i] = max(out.get(i, mark), mark)
    return out


def to_wire(marks: Marks | None) -> dict[int, list[int]] | None:
    return None if marks is None else {e: [s, k] for e, (s, k) in marks.items()}


def from_wire(data: Mapping[int, list[int]] | None) -> Marks | None:
    """Marks from a message (a peer's: malformed ones are dropped, never trusted as a mark)."""
    if data is None:
        return None
    return {int(e): (int(v[0]), int(v[1])) for e, v in data.items() if len(v) == 2}


class CatchUp:
    """A forwarder's replacement takes first, in any order, the input its consumer already
    saw the effects of (everything up to ``marks``), then the rest: input past the marks on
    one edge waits until every marked edge has reached its mark (or :data:`CATCH_UP_S`).
    Each edge's events come in order, so an event past an edge's mark says that edge has
    caught up."""

    def __init__(self, marks: Marks, now: float, edge: int) -> None:
        self.marks = dict(marks)
        self.waiting = set(marks)  # marked edges not reached yet
        self.held: list[bytes] = []
        self.since = now
        self.edge = edge  # the forwarder's input edge (what is held goes back on it)
        self.ts = 0.0  # when the newest held events entered their chain

    def due(self, now: float) -> bool:
        return now - self.since > CATCH_UP_S

    def release(self) -> list[bytes]:
        """Everything held, to process now (the deadline, or the vertex is moving)."""
        self.waiting.clear()
        held, self.held = self.held, []
        return held

    def take(self, events: list[bytes], now: float) -> list[bytes]:
        """Of stamped ``events`` in arrival order, those to process now (the rest held)."""
        if not self.waiting:
            return events
        go = []
        size = HEADER.size
        for ev in events:
            if len(ev) < size:
                go.append(ev)
                continue
            edge, seq, k = HEADER.unpack_from(ev)
            mark = self.marks.get(edge)
            if mark is not None and (seq, k) <= mark:
                go.append(ev)
                if (seq, k) == mark:
                    self.waiting.discard(edge)
                continue
            self.waiting.discard(edge)  # (everything of it up to its mark came before)
            self.held.append(ev)
        if not self.waiting or self.due(now):
            go.extend(self.release())
        return go

    @property
    def done(self) -> bool:
        return not self.waiting
