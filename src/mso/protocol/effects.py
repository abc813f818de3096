"""What the node core asks its driver to do, and what the executor reports back. Sans-IO.

The core never touches a socket, a clock or user code. It returns effects: messages to send,
replies to clients, timers, and *vertex effects* that start, feed, snapshot and stop vertex
instances. A driver carries the vertex effects out off the control plane (the asyncio driver in
worker threads, the simulator in virtual time) and feeds each :data:`VertexResult` back to the
core with ``NodeCore.on_vertex(result, now)``. Per instance, effects are carried out in the
order they were emitted, so a feed queued behind a start or a restore sees the started or
restored instance.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from mso.model.app import Vertex
from mso.protocol import messages as m


# The effects a core returns on every beat (a Send per neighbour, the next tick's SetTimer) are
# msgspec structs: immutable, compared and hashed by their fields as frozen dataclasses are, but
# made in a fifth of the time (a frozen dataclass sets each field through object.__setattr__),
# and not tracked by the cycle collector (they hold messages and timer keys, never each other).
class Send(msgspec.Struct, frozen=True, gc=False):
    """Send ``msg`` to node ``dst`` (routed hop by hop by the network layer)."""

    dst: str
    msg: m.Message

    @property
    def said(self) -> m.Message:
        """The message, as a control stream's frame carries it (``msg`` is the frame)."""
        return m.carried(self.msg)


class Reply(msgspec.Struct, frozen=True, gc=False):
    """Answer the client connection ``client``."""

    client: int
    msg: m.Message


class SetTimer(msgspec.Struct, frozen=True, gc=False):
    """Fire ``on_timer(key)`` at ``at``; setting a key again moves its timer."""

    key: Hashable  # a tuple, or a procedure's typed key (Deadline, Retry)
    at: float


class CancelTimer(msgspec.Struct, frozen=True, gc=False):
    key: Hashable


# -- vertex effects: carried out by the executor, in order per instance ----------------------
@dataclass(frozen=True)
class StartVertex:
    """Create an instance of ``vertex`` (user code: constructor, then its ``open()`` hook).
    ``inputs`` maps each input edge to the format its events decode into (None: any)."""

    instance: int
    app: str
    vertex: Vertex
    kind: str
    inputs: dict[int, Any] = field(default_factory=dict)
    # restored instances get their state before they open
    state: bytes | None = None
    # each output edge's format (None: any): what it emits is checked here, at the producer,
    # so a wrong output is blamed on the vertex that made it, not on its consumer
    outputs: dict[int, Any] = field(default_factory=dict)
    # each input and output edge as errors name it: "producer -> consumer"
    edge_names: dict[int, str] = field(default_factory=dict)
    # say which input event each output was made from (a merge's or forwarder's provenance)
    owners: bool = False


@dataclass(frozen=True)
class FeedVertex:
    """Decode and process ``events`` (encoded) that arrived on ``edge``, in order."""

    instance: int
    edge: int
    events: list[bytes]
    ts: float


@dataclass(frozen=True)
class RunSource:
    """Call a rated source ``count`` times for sequence numbers ``first``..."""

    instance: int
    first: int
    count: int
    now: float


@dataclass(frozen=True)
class Credit:
    """A free-running source (a read loop or a generator) may emit ``count`` more events."""

    instance: int
    count: int


@dataclass(frozen=True)
class RestoreVertex:
    """Give a relocated instance the state its old instance handed over (before any feed)."""

    instance: int
    state: bytes


@dataclass(frozen=True)
class SnapshotVertex:
    """Once everything queued before it is processed, encode the instance's state."""

    instance: int
    token: int


@dataclass(frozen=True)
class StopVertex:
    """Call the instance's ``close()`` hook and drop it. ``reason``: undeploy, moved, reset."""

    instance: int
    reason: str


VertexEffect = (
    StartVertex | FeedVertex | RunSource | Credit | RestoreVertex | SnapshotVertex | StopVertex
)
Effect = Send | Reply | SetTimer | CancelTimer | VertexEffect


# -- what the executor reports back ----------------------------------------------------------
@dataclass(frozen=True)
class Outcome:
    """Common to every result: CPU time spent in user code, errors raised (counted, never
    fatal), the vertex's own ``stats()`` and the size of its encoded state when they were last
    sampled (``state_size`` -1: its state cannot be taken, so it cannot move)."""

    instance: int
    cpu_s: float = 0.0
    errors: int = 0
    last_error: str = ""
    stats: Any = None
    state_size: int = 0


@dataclass(frozen=True)
class VertexStarted(Outcome):
    """The instance exists (``error`` empty) or could not be created. ``mode`` says how a
    source runs: ``timer`` (rated), ``loop`` (called in its worker, paced by credit)."""

    error: str = ""
    mode: str = ""


# End of stream: an empty payload, the last event an edge ever carries. It takes a sequence
# number like any event, so it is acknowledged, retransmitted and handed over with its channel.
END_OF_STREAM = b""


def events_in(payloads: list[bytes]) -> int:
    """Events among encoded payloads, not counting a closing end-of-stream marker."""
    return len(payloads) - (1 if payloads and payloads[-1] == END_OF_STREAM else 0)


@dataclass(frozen=True)
class VertexProcessed(Outcome):
    """``count`` events of ``edge`` were processed; ``outputs`` are the encoded results.
    ``ends`` of the events were end-of-stream markers; ``ended``: every input has ended (the
    instance's ``end()`` ran and ``outputs`` closes with a marker of its own)."""

    edge: int = 0
    count: int = 0
    outputs: list[bytes] = field(default_factory=list)
    # ``owners[j]``: the index in the batch of the event ``outputs[j]`` was made from
    owners: list[int] = field(default_factory=list)
    ts: float = 0.0
    ends: int = 0
    ended: bool = False


@dataclass(frozen=True)
class VertexEmitted(Outcome):
    """A source was called ``calls`` times and produced ``outputs`` (encoded). ``ended``: the
    source is exhausted (a generator returned, or a call raised StopIteration)."""

    calls: int = 0
    outputs: list[bytes] = field(default_factory=list)
    ended: bool = False


@dataclass(frozen=True)
class VertexSnapshot(Outcome):
    token: int = 0
    state: bytes = b""


@dataclass(frozen=True)
class VertexCrashed(Outcome):
    """The child process running an ``isolation: process`` instance died without being told
    to stop (a segfault in a C extension, an OOM kill, ``os._exit``): its state and the effects
    it had not answered are gone. ``reason`` says how it ended ("killed by SIGKILL", "exit code
    3"); ``exit_code`` is the child's (negative: the signal's number)."""

    reason: str = ""
    exit_code: int | None = None


VertexResult = VertexStarted | VertexProcessed | VertexEmitted | VertexSnapshot | VertexCrashed
