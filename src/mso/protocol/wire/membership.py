"""Membership (:mod:`mso.protocol.procedures.membership`): heartbeats and their figures, failure
claims and their questions, rejoins and app syncs. Part of the wire's message union
(:data:`mso.protocol.messages.Message`, which re-exports every name: import them from there);
each message tagged and laid out as every other."""

from __future__ import annotations

from typing import Annotated

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


Hops = Annotated[int, msgspec.Meta(ge=1, le=64)]
"""A route's length: no route between the robots of one overlay is longer."""
Nonce = Annotated[bytes, msgspec.Meta(max_length=16)]
"""An asker's challenge in a :class:`Suspect`, echoed by the suspect's own answer."""
MAX_PROOF = 4096
Proof = Annotated[bytes, msgspec.Meta(max_length=MAX_PROOF)]
"""A suspect's own answer as it came, with its origin signature (:class:`Hears`)."""


class Figures(msgspec.Struct, array_like=True, frozen=True):
    """A node's monitored figures, what the rules weigh a move toward it by."""

    cpu: float
    load: float
    drain_w: float
    remaining_j: float | None
    lifetime_s: float | None
    power: tuple[float, float, float, float]  # idle_w, cpu_w, tx_uj_per_byte, rx_uj_per_byte
    # the sender's routes: hops to each node it reaches. With them a node tells which nodes
    # in its view relay the traffic between two others (a move's radio cost at the relays)
    hops: dict[str, Hops] = msgspec.field(default_factory=dict)


class Heartbeat(_Msg, tag="heartbeat"):
    """Sent to every neighbour each heartbeat period: liveness and membership, and on some
    beats the sender's monitored figures.

    The figures change once a monitor period (1 s) and the power model never, so they ride
    on one beat in ten and on the first to a neighbour: in the energy study a beat with them
    cost 111 bytes, ten a second to every neighbour — over half an interior robot's radio."""

    node: str
    # membership: a restarted or reset node comes back with a higher incarnation; ``failed``
    # (node -> the incarnation declared failed) and ``leader`` (the lowest node the sender
    # counts alive) let two sides of a healed partition agree which one rejoins the other
    incarnation: int = 0
    failed: dict[str, int] = msgspec.field(default_factory=dict)
    leader: str = ""
    hosting: int = 0  # vertex instances the sender runs: a node with none yields first
    figures: Figures | None = None  # None: as on the last beat that carried them
    # failure claims the sender accepted lately, piggybacked (each on a few beats, then
    # dropped): dissemination without a message of its own (bounded: MAX_NEWS)
    news: list[NodeDown] = msgspec.field(default_factory=list)


class NodeDown(_Msg, tag="node_down"):
    """``node`` has failed (fail-stop): its neighbour ``detector`` stopped hearing it, and
    ``witness`` (asked by the detector, '' when there was nobody to ask) did not hear it either.
    A claim is acted on only when corroborated: a witness, a second detector, or the
    receiver's own probe (see :mod:`mso.protocol.procedures.membership.peers`)."""

    node: str
    detector: str
    incarnation: int = 0  # the incarnation that failed: news of an older one is stale
    witness: str = ""


class Suspect(_Msg, tag="suspect"):
    """From a node that lost every route to ``node``, to each node it still reaches: do you
    hear it? Answered with :class:`Hears`; ``rid`` is the asker's suspicion (a procedure)."""

    node: str
    rid: int
    # the asker's fresh challenge (with node identities): a member that hears ``node`` asks
    # it on, and ``node``'s own signed answer, which echoes it, is the member's proof
    nonce: Nonce = b""


class Hears(_Msg, tag="hears"):
    """The answer to :class:`Suspect`: ``yes`` if the sender heard ``node`` within its own
    liveness window (and does not hold it failed). A yes keeps ``node`` from being declared
    failed on the asker's missing route alone."""

    node: str
    rid: int
    yes: bool
    # how long ago the sender last heard ``node`` (ms; -1: never): a yes moves the asker's
    # silence clock to then, not to now (a dead node is not kept alive by a late answer)
    ago_ms: int = -1
    nonce: Nonce = b""  # the asker's challenge this answers
    # with node identities: ``node``'s own yes to ``nonce`` as it came, signed by ``node``
    # (the frame, with its origin): a member's "I hear it" backed by the suspect's own word,
    # which a member cannot write for a dead node. Set and checked by the receiving
    # transport (mso.net.trust), never taken as sent
    proof: Proof = b""


class NodeUp(_Msg, tag="node_up"):
    """``node``, declared failed, is back as a new ``incarnation`` that hosts nothing."""

    node: str
    incarnation: int


class AppSync(_Msg, tag="app_sync"):
    """To a node that rejoined: an app it must know again and where its vertices run now
    (``vanished``: vertices whose instances went with the node's old incarnation)."""

    app: str
    origin: str
    document: str
    epoch: int
    placed: dict[str, str]
    vanished: list[str] = msgspec.field(default_factory=list)
    # vertices the sender ran and handed over, and to whom: its first-hand word on where they
    # went (a node that missed the move's Moved, held failed then, learns it from this)
    handed: dict[str, str] = msgspec.field(default_factory=dict)
    # the nodes chosen for vertices placed by capability, and their ranked candidates (§3.3)
    resolved: dict[str, str] = msgspec.field(default_factory=dict)
    capable: dict[str, list[str]] = msgspec.field(default_factory=dict)
    # the incarnation the sender knows of each node it places a vertex on: a receiver that
    # never heard of one (it restarted since) learns which incarnation runs them, so a newer
    # one heard later is a restart whose instances went
    incarnations: dict[str, int] = msgspec.field(default_factory=dict)
    # how many moves of each vertex the sender knows of: its hearsay never replaces a later
    # placement the receiver knows (a node that missed a move syncs its older view)
    versions: dict[str, int] = msgspec.field(default_factory=dict)
    # where each replicated vertex's replicas are, as the sender knows (issue 24.1: a node
    # given the app learns them, so a host it becomes tells the old ones they are no more)
    replicas: dict[str, list[str]] = msgspec.field(default_factory=dict)
