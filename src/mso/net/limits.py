"""Bounds on what a connection may cost a node: counts, time to authenticate, idle time, bytes.

A MANET is open air: anyone in range can open connections. A connection that has not proved
the overlay key (hello + key confirmation, :mod:`mso.protocol.framing`) and said who it is
within ``handshake_s`` is closed; so is one silent for ``idle_s`` (peers send heartbeats every
0.1 s; a client such as the emulator controller may sit idle much longer). A node serves at most
``max_connections`` introduced clients at once and ``max_per_address`` from one address; a
connection still proving the key takes a slot of a pending pool (:mod:`mso.net.admission`).
Before authentication a connection can make the node buffer at most one 20-byte frame; after
it at most one frame of ``max_frame`` bytes, and all connections together at most
``max_buffered`` of partial frames; a client that does not read its replies is closed past
``max_client_backlog``, or past ``max_partial_share`` while all clients together hold more than
``max_clients_backlog``. Each link's queues are bounded per class (``queues``,
:mod:`mso.net.shaping`), and a heartbeat, which overtakes every other frame, may be at most
``max_beat_frame`` bytes, relayed or not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mso.net.shaping import QueueBounds
from mso.protocol.framing import MAX_FRAME


@dataclass(frozen=True)
class Limits:
    handshake_s: float = 5.0
    # the pool of connections still proving the key (:mod:`mso.net.admission`)
    max_pending: int = 64
    max_pending_per_address: int = 16
    handshake_min_s: float = 0.5  # a source's deadline after its strikes, at the least
    strike_half_life_s: float = 10.0
    known_for_s: float = 600.0  # a source a connection proved the key from, preferred as long
    peer_idle_s: float = 60.0
    client_idle_s: float = 3600.0  # the emulator controller may sit idle between link changes
    max_connections: int = 256
    max_per_address: int = 64
    max_frame: int = MAX_FRAME
    # partial frames held across every connection; past it, a connection holding more than
    # ``max_partial_share`` of a frame is closed (a member announcing big frames on many
    # connections cannot fill the node's memory)
    max_buffered: int = 64 * 1024 * 1024
    max_partial_share: int = 1024 * 1024
    # replies a client does not read: past this its connection is closed; and past
    # ``max_clients_backlog`` across every client, one holding over ``max_partial_share``
    # (20 clients each under the first bound once took a node to 1.18 GB)
    max_client_backlog: int = 16 * 1024 * 1024
    max_clients_backlog: int = 64 * 1024 * 1024
    sweep_s: float = 1.0  # how often idle and unfinished connections are looked for
    # bytes each class may queue on one link; a beat's largest frame (its failed map is
    # bounded by membership: about 20 bytes a node)
    queues: QueueBounds = field(default_factory=QueueBounds)
    max_beat_frame: int = 256 * 1024
    # frames a relay passes on for one neighbour per second, by class (:mod:`mso.net.relaying`)
    relay_control_per_s: float = 2000.0
    relay_beats_per_s: float = 100.0
    # frames held for a neighbour whose connection is being set up, per neighbour
    max_held_bytes: int = 64 * 1024 * 1024


DEFAULT_LIMITS = Limits()


class ConnectionCounters:
    """Connections refused or closed by the limits (reported in status with the traffic)."""

    def __init__(self) -> None:
        self.connections_refused = 0  # over the node's or one address's limit
        self.evicted = 0  # a pending connection closed to make room for a new one
        self.handshake_timeouts = 0  # no key confirmation and hello in time
        self.wrong_key = 0  # a key confirmation that failed: closed without a word
        self.identity_refused = 0  # a neighbour's proof of its name did not hold
        self.client_refused = 0  # a client without a certificate that holds (when required)
        self.idle_timeouts = 0
        self.over_buffer = 0  # closed for holding too much (partial frames, unread replies)

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))
