"""Every message nodes exchange: one tagged msgspec union, validated on decode.

A frame's payload is an :class:`Envelope` (source node, destination node, hop limit) around a
body that stays raw msgpack while it is relayed, so a node forwarding multi-hop traffic never
decodes it. The destination decodes the body as :data:`Message`; anything that does not decode
into one of these types is dropped and counted. Nothing received is ever unpickled, and vertex
code is only ever named here by the import paths in an app document, never shipped.
"""

from __future__ import annotations

import msgspec

from mso.protocol.tapwire import Tap as Tap
from mso.protocol.tapwire import TapEvents as TapEvents
from mso.protocol.wire.data import Ack as Ack
from mso.protocol.wire.data import ChainDelay as ChainDelay
from mso.protocol.wire.data import Data as Data
from mso.protocol.wire.deploy import AppAnnounce as AppAnnounce
from mso.protocol.wire.deploy import BuildChain as BuildChain
from mso.protocol.wire.deploy import CapabilityQuery as CapabilityQuery
from mso.protocol.wire.deploy import CapabilityReply as CapabilityReply
from mso.protocol.wire.deploy import ChainBuilt as ChainBuilt
from mso.protocol.wire.deploy import ChainPartReady as ChainPartReady
from mso.protocol.wire.deploy import ChainPlaced as ChainPlaced
from mso.protocol.wire.deploy import DeployFailed as DeployFailed
from mso.protocol.wire.deploy import Probe as Probe
from mso.protocol.wire.deploy import ProbeReply as ProbeReply
from mso.protocol.wire.deploy import StartApp as StartApp
from mso.protocol.wire.deploy import StopApp as StopApp
from mso.protocol.wire.link import ClientHello as ClientHello
from mso.protocol.wire.link import PeerHello as PeerHello
from mso.protocol.wire.membership import MAX_PROOF as MAX_PROOF
from mso.protocol.wire.membership import AppSync as AppSync
from mso.protocol.wire.membership import Figures as Figures
from mso.protocol.wire.membership import Hears as Hears
from mso.protocol.wire.membership import Heartbeat as Heartbeat
from mso.protocol.wire.membership import Hops as Hops
from mso.protocol.wire.membership import NodeDown as NodeDown
from mso.protocol.wire.membership import NodeUp as NodeUp
from mso.protocol.wire.membership import Suspect as Suspect
from mso.protocol.wire.recovery import FetchReplica as FetchReplica
from mso.protocol.wire.recovery import Release as Release
from mso.protocol.wire.recovery import Replay as Replay
from mso.protocol.wire.recovery import ReplicaAck as ReplicaAck
from mso.protocol.wire.recovery import ReplicaSet as ReplicaSet
from mso.protocol.wire.recovery import Replicate as Replicate
from mso.protocol.wire.recovery import Resume as Resume
from mso.protocol.wire.recovery import Rewire as Rewire
from mso.protocol.wire.relocation import Handover as Handover
from mso.protocol.wire.relocation import HandoverDone as HandoverDone
from mso.protocol.wire.relocation import HandoverEvents as HandoverEvents
from mso.protocol.wire.relocation import Marker as Marker
from mso.protocol.wire.relocation import Moved as Moved
from mso.protocol.wire.relocation import Moving as Moving
from mso.protocol.wire.relocation import PlacementQuery as PlacementQuery
from mso.protocol.wire.relocation import PlacementReply as PlacementReply
from mso.protocol.wire.relocation import Prepare as Prepare
from mso.protocol.wire.relocation import Prepared as Prepared
from mso.protocol.wire.relocation import Switch as Switch
from mso.protocol.wire.relocation import Unprepare as Unprepare
from mso.protocol.wire.requests import Authorized as Authorized
from mso.protocol.wire.requests import DeployReply as DeployReply
from mso.protocol.wire.requests import DeployRequest as DeployRequest
from mso.protocol.wire.requests import LinkState as LinkState
from mso.protocol.wire.requests import Refused as Refused
from mso.protocol.wire.requests import RelocateReply as RelocateReply
from mso.protocol.wire.requests import RelocateRequest as RelocateRequest
from mso.protocol.wire.requests import RemapReply as RemapReply
from mso.protocol.wire.requests import RemapRequest as RemapRequest
from mso.protocol.wire.requests import RevokeNode as RevokeNode
from mso.protocol.wire.requests import Shutdown as Shutdown
from mso.protocol.wire.requests import StatusReply as StatusReply
from mso.protocol.wire.requests import StatusRequest as StatusRequest


class Sequenced(msgspec.Struct, tag_field="t", tag="seq", array_like=True):
    """A control message on its sender's control stream to this node
    (:mod:`mso.protocol.control_stream`): numbered per (sender incarnation, receiver), held
    by the sender until acknowledged and sent again, delivered once and in order. ``low``:
    the lowest number the sender still holds for this receiver (nothing below it will come:
    given up or acknowledged). ``ack``/``ack_inc``: an acknowledgement of the receiver's own
    stream to the sender, piggybacked (-1: none). ``to``: the receiver's incarnation as the
    sender knows it (-1: unknown); a later process of the receiver drops the frame, which was
    for one that died or reset."""

    inc: int
    seq: int
    low: int
    body: Message
    ack_inc: int = -1
    ack: int = -1
    to: int = -1


class Got(msgspec.Struct, tag_field="t", tag="got", array_like=True):
    """Everything of the receiver's control stream of incarnation ``inc`` up to ``upto`` has
    arrived here (sent when no control message to it carried the acknowledgement)."""

    inc: int
    upto: int


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


# a tap's copies never overtake control; every other message is CONTROL (looked up by its
# exact type: a message type is never subclassed, and an ``isinstance`` on a union cost more
# than the rest of a beat's envelope)
_KINDS: dict[type, int] = {
    Data: DATA,
    Ack: DATA,
    TapEvents: DATA,
    Heartbeat: HEARTBEAT,
    Marker: MARKER,
}


def kind_of(msg: Message) -> int:
    return _KINDS.get(type(msg), CONTROL)


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
    | Sequenced
    | Got
)

_ENVELOPE_DECODER = msgspec.msgpack.Decoder(Envelope)
_MESSAGE_DECODER: msgspec.msgpack.Decoder[Message] = msgspec.msgpack.Decoder(Message)
_ENCODER = msgspec.msgpack.Encoder()


def carried(msg: Message) -> Message:
    """The message itself: what a control stream's frame carries, or ``msg``."""
    return msg.body if type(msg) is Sequenced else msg


def name_of(msg: Message) -> str:
    """A message's type name, a control stream's frame named by what it carries (logs, traces)."""
    return type(msg.body if type(msg) is Sequenced else msg).__name__


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
