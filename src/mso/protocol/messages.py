"""Every message nodes exchange: one tagged msgspec union, validated on decode.

A frame's payload is an :class:`Envelope` (source node, destination node, hop limit) around a
body that stays raw msgpack while it is relayed, so a node forwarding multi-hop traffic never
decodes it. The destination decodes the body as :data:`Message`; anything that does not decode
into one of these types is dropped and counted. Nothing received is ever unpickled, and vertex
code is only ever named here by the import paths in an app document, never shipped.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from mso.protocol.tapwire import Tap as Tap
from mso.protocol.tapwire import TapEvents as TapEvents

CONTROL, DATA, MARKER, HEARTBEAT = 0, 1, 2, 3  # Envelope.kind
KINDS = frozenset({CONTROL, DATA, MARKER, HEARTBEAT})


class Envelope(msgspec.Struct, array_like=True):
    """Routing header. ``kind``: CONTROL overtakes queued data; DATA (events, acks) is what an
    emulated lossy link may drop, recovered by retransmission; MARKER travels in order with the
    data it follows and is never dropped by emulated loss; HEARTBEAT overtakes everything, so
    bulk control never delays liveness (and is refused beyond a small size). ``origin``: with
    node identities, the originator's signature (:mod:`mso.protocol.origin`); empty (and not
    on the wire) without them."""

    src: str
    dst: str
    ttl: int
    kind: int
    body: msgspec.Raw
    origin: bytes = b""


class _Bare(msgspec.Struct, array_like=True):
    """An envelope without an origin, as it goes on the wire: the five fields alone (msgspec
    writes a trailing default of an array-like struct too)."""

    src: str
    dst: str
    ttl: int
    kind: int
    body: msgspec.Raw


def kind_of(msg: Message) -> int:
    if isinstance(msg, Data | Ack | TapEvents):  # a tap's copies never overtake control
        return DATA
    if isinstance(msg, Heartbeat):
        return HEARTBEAT
    return MARKER if isinstance(msg, Marker) else CONTROL


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


# -- link level (neighbour to neighbour) -----------------------------------------------------
class PeerHello(_Msg, tag="hello"):
    """First message on a node-to-node connection: who is speaking; with node identities,
    its certificate and its signature over both hellos (:mod:`mso.protocol.identity`)."""

    node: str
    cert: bytes = b""
    sig: bytes = b""


class ClientHello(_Msg, tag="client"):
    """First message from a CLI or API client connection; with a client identity, its
    certificate and its signature over both hellos (:mod:`mso.protocol.clients`)."""

    name: str
    cert: bytes = b""
    sig: bytes = b""


# -- data plane ------------------------------------------------------------------------------
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


# -- deployment (Algorithm 1) ----------------------------------------------------------------
class AppAnnounce(_Msg, tag="announce"):
    """The app document and the deploying node, sent to every node before placement."""

    app: str
    origin: str
    document: str
    epoch: int = 0  # this deployment's incarnation: data of an earlier one is not accepted
    # each vertex placed by capability: the node chosen, and the nodes that qualify, best first
    # (after a failure the next live one takes it)
    resolved: dict[str, str] = msgspec.field(default_factory=dict)
    capable: dict[str, list[str]] = msgspec.field(default_factory=dict)


class CapabilityQuery(_Msg, tag="capability_query"):
    """From the deploying node to every node (§3.3): which of you offers what these vertices
    require? ``needs``: vertex -> what it requires; ``anchors``: the nodes an answer reports its
    hops to (those a ``near`` constraint may name). Nodes that offer some of what a vertex
    requires answer with their offers (so a refusal can say what no node has), the others
    decline, so the deploying node chooses as soon as every node has spoken."""

    app: str
    qid: int
    needs: dict[str, dict[str, float]]
    anchors: list[str] = msgspec.field(default_factory=list)


class CapabilityReply(_Msg, tag="capability_reply"):
    """A node with some of what a :class:`CapabilityQuery` asks for: what it offers
    (its ``cpu`` included), its remaining energy (None: wall power), its hops to the anchors.
    ``declined``: it has none of it (no offers; not a candidate, but no need to wait for it)."""

    app: str
    qid: int
    node: str
    offers: dict[str, float]
    energy_j: float | None = None
    hops: dict[str, int] = msgspec.field(default_factory=dict)
    declined: bool = False


class Probe(_Msg, tag="probe"):
    """Travels hop by hop toward ``target``; each hop appends its capacity and its power
    figures ``[cpu_w, tx_uj_per_byte, rx_uj_per_byte]`` (for the bytes planner; a peer that
    predates them sends none, and the planner takes the defaults for every hop), and each hop
    that forwards it the rate of the link it forwards over (``rates``, Mb/s, 0: not known)."""

    app: str
    chain: int
    segment: int
    requester: str
    target: str
    nodes: list[str]
    capacities: list[float]
    power: list[list[float]] = []
    rates: list[float] = []


class ProbeReply(_Msg, tag="probe_reply"):
    app: str
    chain: int
    segment: int
    nodes: list[str]
    capacities: list[float]
    power: list[list[float]] = []
    rates: list[float] = []


class ChainPlaced(_Msg, tag="placed"):
    """A chain's placement, broadcast so every node knows the whole mapping."""

    app: str
    chain: int
    assignments: dict[str, str]


class BuildChain(_Msg, tag="build"):
    """From a chain head's node to each node hosting part of the chain: create its vertices."""

    app: str
    chain: int
    vertices: list[str]


class ChainPartReady(_Msg, tag="part_ready"):
    """A builder's part of a chain is up, in the builder's ``incarnation`` (-1: not said)."""

    app: str
    chain: int
    node: str
    incarnation: int = -1


class ChainBuilt(_Msg, tag="built"):
    """From a chain head's node to the origin: the chain's overlay exists, on nodes in these
    ``incarnations`` (as their builders said)."""

    app: str
    chain: int
    incarnations: dict[str, int] = {}


class StartApp(_Msg, tag="start"):
    """The overlay is complete: sources may emit. ``incarnations``: of each node it runs on,
    as its builders said, so that every node that holds the app knows a restart of one of
    them as a restart, though that node never sent it a beat (nobody says hello to every
    node at a first start: :meth:`~.membership.peers.Membership.on_routes_changed`)."""

    app: str
    incarnations: dict[str, int] = {}


class StopApp(_Msg, tag="stop"):
    """Undeploy ``app`` everywhere. On nodes with operator keys it carries the operator's
    signature of ``app`` and ``at`` (its clock, ms) by key ``key``: every node verifies it, and
    it revokes the app's grants made before ``at`` (:mod:`mso.protocol.authority`)."""

    app: str
    at: int = 0
    key: str = ""
    sig: bytes = b""


class DeployFailed(_Msg, tag="deploy_failed"):
    app: str
    reason: str


# -- reconfiguration (§3.4): relocation with a marker and state handover -----------------------
class Marker(_Msg, tag="marker"):
    """Sent down the old path after the producer switched an edge: every event before ``seq``
    went the old way. Travels as data so it never overtakes them."""

    app: str
    edge: int
    seq: int
    rid: int
    to: str  # where the vertex is going: its old instance hands over there


Hops = Annotated[int, msgspec.Meta(ge=1, le=64)]
"""A route's length: no route between the robots of one overlay is longer."""


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


class Rewire(_Msg, tag="rewire"):
    """After a failure: the edge's other end now runs on ``to``. The receiver is the edge's
    producer (it replays its unacknowledged events there) or its consumer."""

    app: str
    edge: int
    to: str
    rid: int
    producer: bool
    order: bytes = b""  # the operator's order the move carries out (mso.protocol.warrant)


class Resume(_Msg, tag="resume"):
    """To a replacement instance: where the edge stands. From the producer: the first event it
    will replay (``start``) and the output positions of the last ack it got; from the consumer:
    the next sequence number it expects."""

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


# -- chain replication (mso.protocol.procedures.replication) ----------------------------------
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


class FetchReplica(_Msg, tag="fetch_replica"):
    """From a restore's replacement to a replica: send the newest snapshot you hold (a
    ``Replicate`` with ``rid``; ``k`` -1 and no state if none)."""

    app: str
    vertex: str
    rid: int


class ChainDelay(_Msg, tag="chain_delay"):
    """From a chain's tail node to its head node: the measured end-to-end delay."""

    app: str
    chain: int
    delay_ms: float


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
    # edge -> [next expected seq, acknowledged up to, superseded, expired, deadline missed]
    inputs: dict[int, list[int]]
    outputs: dict[int, list[Any]]  # edge -> [next_seq, acked, [unacked events...], positions]
    processed: int
    emitted: int
    gate: list[Any] = msgspec.field(default_factory=list)  # pending chained-ack checkpoints
    parts: int = 0  # HandoverEvents sent ahead of it (the outputs' events past one frame)
    version: int = 0  # the move's version (the old host counted it)
    # input edge -> the provenance marks its consumer has of a merge's output (absent: unknown)
    marks: dict[int, dict[int, list[int]]] = msgspec.field(default_factory=dict)


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
    app it hosts no part of (its view is not kept up to date: it asks first)."""

    app: str
    qid: int


class PlacementReply(_Msg, tag="where_reply"):
    """The answer to :class:`PlacementQuery`: the sender's placement of ``app`` with each
    vertex's version (the asker keeps, per vertex, the highest)."""

    app: str
    qid: int
    placed: dict[str, str]
    versions: dict[str, int] = msgspec.field(default_factory=dict)
    vanished: list[str] = msgspec.field(default_factory=list)  # its instance went (a restart)


# -- requests from clients -------------------------------------------------------------------
class RelocateRequest(_Msg, tag="relocate"):
    """Move ``vertex`` upstream (onto its predecessor's node), downstream (onto its successor's
    next node) or to ``target``."""

    app: str
    vertex: str
    direction: str = ""
    target: str = ""
    # an operator's order, verified by every node a step of the move reaches (with operator
    # keys: mso.protocol.warrant): the signer's clock (ms), key id, signature, and a command
    # client's certificate
    at: int = 0
    key: str = ""
    sig: bytes = b""
    cert: bytes = b""


class RemapRequest(_Msg, tag="remap"):
    """Re-place chains along freshly probed routes (§3.4.2; several: §3.4.3, in dependency
    order). ``chains`` are chain indices; empty with ``everything`` remaps them all."""

    app: str
    chains: list[int]
    everything: bool = False
    # an operator's order, verified by every node a step of the move reaches (with operator
    # keys: mso.protocol.warrant): the signer's clock (ms), key id, signature, and a command
    # client's certificate
    at: int = 0
    key: str = ""
    sig: bytes = b""
    cert: bytes = b""


class RemapReply(_Msg, tag="remap_reply"):
    app: str
    ok: bool
    moved: dict[str, str]
    elapsed_ms: float = 0.0
    error: str = ""


class RelocateReply(_Msg, tag="relocate_reply"):
    app: str
    vertex: str
    ok: bool
    node: str = ""
    elapsed_ms: float = 0.0
    error: str = ""


class DeployRequest(_Msg, tag="deploy"):
    document: str
    file: str = "<app>"


class DeployReply(_Msg, tag="deploy_reply"):
    app: str
    ok: bool
    placement: dict[str, str]
    elapsed_ms: float
    error: str = ""


class StatusRequest(_Msg, tag="status"):
    """``everywhere``: the receiving node gathers every node's status before replying."""

    req: int = 0
    everywhere: bool = False


class StatusReply(_Msg, tag="status_reply"):
    req: int
    nodes: dict[str, Any]


# -- emulator control ------------------------------------------------------------------------
class LinkState(_Msg, tag="links"):
    """From the emulator controller: current neighbours (address, link shape) and routes."""

    version: int
    neighbours: dict[str, list[Any]]  # node -> [host, port, bandwidth_mbps|None, delay_ms, loss]
    routes: dict[str, list[Any]]  # destination -> [next hop, hops]
    # the links the routes were computed on ([a, b] pairs), so that the node can route around
    # a relay whose daemon it holds failed: in user space the daemon is the relay
    links: list[list[str]] = msgspec.field(default_factory=list)


class Shutdown(_Msg, tag="shutdown"):
    pass


# -- authority (mso.protocol.authority) -------------------------------------------------------
class RevokeNode(_Msg, tag="revoke_node"):
    """An operator withdraws a node key (its id: :mod:`mso.protocol.identity`): every node that
    hears it refuses that key on links and in origins from then on. The operator's signature
    covers the key id and its time (``at``/``key``/``sig``) and nothing of a connection, so
    every node it is passed on to verifies it itself (:mod:`mso.protocol.revocation`). Its
    echo, unsigned, answers the client."""

    node_key: str
    at: int = 0
    key: str = ""
    sig: bytes = b""


class Authorized(_Msg, tag="auth"):
    """A client command (``body``, an encoded message) signed with the Ed25519 key ``key``
    (its id) over the node's hello nonce of this connection and ``body``."""

    body: bytes
    key: str
    sig: bytes


class Refused(_Msg, tag="refused"):
    """The reply to a client command refused for want of authority, and why."""

    reason: str


Message = (
    PeerHello
    | ClientHello
    | Data
    | Ack
    | AppAnnounce
    | CapabilityQuery
    | CapabilityReply
    | Probe
    | ProbeReply
    | ChainPlaced
    | BuildChain
    | ChainPartReady
    | ChainBuilt
    | StartApp
    | StopApp
    | DeployFailed
    | DeployRequest
    | DeployReply
    | StatusRequest
    | StatusReply
    | PlacementQuery
    | PlacementReply
    | LinkState
    | Shutdown
    | RevokeNode
    | Authorized
    | Refused
    | Marker
    | Prepare
    | Unprepare
    | Moving
    | Prepared
    | Switch
    | Handover
    | HandoverEvents
    | Moved
    | HandoverDone
    | RelocateRequest
    | RelocateReply
    | RemapRequest
    | RemapReply
    | Heartbeat
    | NodeDown
    | Rewire
    | Resume
    | Replicate
    | ReplicaAck
    | Release
    | Replay
    | ReplicaSet
    | FetchReplica
    | ChainDelay
    | NodeUp
    | AppSync
    | Suspect
    | Hears
    | Tap
    | TapEvents
)

_ENVELOPE_DECODER = msgspec.msgpack.Decoder(Envelope)
_MESSAGE_DECODER: msgspec.msgpack.Decoder[Message] = msgspec.msgpack.Decoder(Message)
_ENCODER = msgspec.msgpack.Encoder()


def encode(msg: Message) -> bytes:
    return _ENCODER.encode(msg)


def _too_deep() -> msgspec.DecodeError:
    # msgspec raises RecursionError on a body nested ~1,000 deep: as a DecodeError it is
    # dropped and counted like any malformed frame, where it used to escape the connection's
    # data_received and drop the connection uncounted
    return msgspec.DecodeError("nested too deeply")


def decode(data: bytes | msgspec.Raw) -> Message:
    """Decode and validate a message body; raises msgspec.DecodeError/ValidationError."""
    try:
        return _MESSAGE_DECODER.decode(data)
    except UnicodeDecodeError as exc:  # msgspec lets an invalid UTF-8 tag through as this
        raise msgspec.DecodeError(f"invalid UTF-8: {exc.reason}") from None
    except RecursionError:
        raise _too_deep() from None


def wrap(src: str, dst: str, msg: Message, ttl: int = 32) -> bytes:
    body = msgspec.Raw(_ENCODER.encode(msg))
    return _ENCODER.encode(_Bare(src, dst, ttl, kind_of(msg), body))


def unwrap(data: bytes) -> Envelope:
    try:
        return _ENVELOPE_DECODER.decode(data)
    except UnicodeDecodeError as exc:
        raise msgspec.DecodeError(f"invalid UTF-8: {exc.reason}") from None
    except RecursionError:  # skipping a deeply nested body
        raise _too_deep() from None


def rewrap(env: Envelope) -> bytes:
    """Re-encode an envelope for the next hop (ttl already decremented); the body stays raw."""
    if env.origin:
        return _ENCODER.encode(env)
    return _ENCODER.encode(_Bare(env.src, env.dst, env.ttl, env.kind, env.body))
