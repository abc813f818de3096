"""The two messages of a tap (:mod:`mso.protocol.taps`), part of the wire's message union.

Kept apart from :mod:`mso.protocol.messages` (which lists them in its union) so that module
stays one screenful per family; tagged and laid out as every other message.
"""

from __future__ import annotations

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class Tap(_Msg, tag="tap"):
    """Copies of edge ``edge`` of ``app`` (``src->dst``, ``src:dst``, or a vertex with one
    output edge) as they reach the edge's consumer, at most ``rate`` a second (0: counts and
    delays only), for ``lease_s``: asked again before then to keep the tap, so a client that
    goes away ends it. From a client to any node (``tap`` 0); that node asks the consumer's
    host with its own ``tap`` id and relays what comes back. A consumer's old host hands the
    tap to its new one with ``to``: the relay to send the copies to."""

    app: str
    edge: str
    rate: float
    lease_s: float
    tap: int = 0
    to: str = ""


class TapEvents(_Msg, tag="tap_events"):
    """What a tap saw since its last message: copies of events (``seqs``, ``events``, encoded
    as on the edge, ``stamps`` when each arrived), how long each batch had been in its chain
    when it arrived (``delays_ms``), and since the tap opened how many events reached the
    consumer (``seen``) and how many copies the tap gave up (``dropped``: its rate limit and
    its bounded queue; the edge's own events are never held for it). ``format`` and
    ``fields`` say how to read the events (a positional format's field names). ``ended`` says
    why there is no more: unknown app or edge, the app stopped, too many taps; ``host`` where
    the consumer runs."""

    tap: int
    app: str
    edge: str
    node: str
    at: float  # the serving node's clock
    seen: int
    dropped: int
    seqs: list[int] = msgspec.field(default_factory=list)
    events: list[bytes] = msgspec.field(default_factory=list)
    stamps: list[float] = msgspec.field(default_factory=list)  # arrivals, on ``at``'s clock
    delays_ms: list[float] = msgspec.field(default_factory=list)
    format: str = ""
    fields: list[str] = msgspec.field(default_factory=list)
    ended: str = ""
    host: str = ""
