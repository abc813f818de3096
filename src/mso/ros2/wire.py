"""rmw_zenoh's wire contract, as pure functions: what a ROS 2 node on Zenoh expects to see.

rmw_zenoh documents it (``docs/design.md`` of its repository) so that others can speak it:

- data key ``<domain>/<fully_qualified_name>/<type_name>/<type_hash>``, the name without its
  leading ``/``, the type in its DDS spelling (``std_msgs::msg::dds_::String_``) and the hash
  the REP-2016 ``RIHS01_…`` one (Humble, which has none, puts ``TypeHashNotSupported``);
- liveliness tokens under ``@ros2_lv/`` for the node (``NN``) and each publisher (``MP``) or
  subscription (``MS``): ``ros2 topic list`` and matching are built from them;
- an attachment on every sample: sequence number (int64), source timestamp in ns since the
  epoch (int64), the GID's length (one byte, 16) and the 16-byte GID, little-endian. rmw_zenoh
  drops a sample that has none.

Nothing here touches the network, so the tests check it against the design document's own
examples (golden vectors).
"""

from __future__ import annotations

import hashlib
import struct

import msgspec

HUMBLE_HASH = "TypeHashNotSupported"
ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
_ATTACHMENT = struct.Struct("<qqB16s")
ATTACHMENT_SIZE = _ATTACHMENT.size  # 33
DISTROS = ("humble", "iron", "jazzy", "kilted", "rolling")

# rmw_zenoh leaves out of the QoS key whatever equals its own defaults (qos.cpp): reliable,
# volatile, keep_last with depth 42; deadline, lifespan and liveliness are never set here.
RMW_DEFAULT_DEPTH = 42
_RELIABILITY = {"reliable": 1, "best_effort": 2}
_DURABILITY = {"transient_local": 1, "volatile": 2}
_HISTORY = {"keep_last": 1, "keep_all": 2}


class QoS(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A topic's QoS as ROS 2 names it; the defaults are rclcpp's (``QoS(10)``)."""

    reliability: str = "reliable"
    durability: str = "volatile"
    history: str = "keep_last"
    depth: int = 10

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("reliability", self.reliability, _RELIABILITY),
            ("durability", self.durability, _DURABILITY),
            ("history", self.history, _HISTORY),
        ):
            if value not in allowed:
                raise ValueError(f"qos {name}: expected one of {', '.join(allowed)}, got {value!r}")
        if not isinstance(self.depth, int) or self.depth < 0:
            raise ValueError(f"qos depth: expected a non-negative integer, got {self.depth!r}")

    def keyexpr(self) -> str:
        """rmw_zenoh's compact form (``qos_to_keyexpr``): ``::,10:,:,:,,`` for QoS(10)."""
        rel = "" if self.reliability == "reliable" else str(_RELIABILITY[self.reliability])
        dur = "" if self.durability == "volatile" else str(_DURABILITY[self.durability])
        hist = "" if self.history == "keep_last" else str(_HISTORY[self.history])
        depth = "" if self.depth == RMW_DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:{hist},{depth}:,:,:,,"


def qos_from(value: object) -> QoS:
    """A QoS from an app's ``qos`` param: a mapping, or None for the defaults."""
    if value is None:
        return QoS()
    if isinstance(value, QoS):
        return value
    try:
        return msgspec.convert(value, QoS)
    except msgspec.ValidationError as exc:
        raise ValueError(f"qos: {exc}") from None


def fully_qualified(topic: str) -> str:
    """``chatter`` and ``/chatter`` are the same ROS topic: ``/chatter``."""
    if not isinstance(topic, str) or not topic.strip("/"):
        raise ValueError(f"expected a ROS topic name like '/chatter', got {topic!r}")
    return "/" + topic.strip("/")


def dds_type_name(ros_type: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs::msg::dds_::String_`` (the name DDS and
    rmw_zenoh put on the wire)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"expected a ROS type like 'std_msgs/msg/String', got {ros_type!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression a topic's samples are put on."""
    return f"{domain}/{fully_qualified(topic)[1:]}/{dds_type_name(ros_type)}/{type_hash}"


def mangle(name: str) -> str:
    """A name inside a liveliness token: every ``/`` becomes ``%``; empty is ``%``."""
    return name.replace("/", "%") if name else "%"


def node_token(
    domain: int, session: str, node_id: int, node: str, namespace: str = "", enclave: str = ""
) -> str:
    """The ``NN`` token that makes a node visible to ``ros2 node list``."""
    return (
        f"{ADMIN_SPACE}/{domain}/{session}/{node_id}/{node_id}/NN/"
        f"{mangle(enclave)}/{mangle(namespace)}/{node}"
    )


def entity_token(
    kind: str,
    domain: int,
    session: str,
    node_id: int,
    entity_id: int,
    node: str,
    topic: str,
    ros_type: str,
    type_hash: str,
    qos: QoS,
    namespace: str = "",
    enclave: str = "",
) -> str:
    """The ``MP`` (publisher) or ``MS`` (subscription) token that ``ros2 topic list`` and
    rmw_zenoh's matching read."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"expected MP or MS, got {kind!r}")
    return (
        f"{ADMIN_SPACE}/{domain}/{session}/{node_id}/{entity_id}/{kind}/"
        f"{mangle(enclave)}/{mangle(namespace)}/{node}/{mangle(fully_qualified(topic))}/"
        f"{dds_type_name(ros_type)}/{type_hash}/{qos.keyexpr()}"
    )


def gid_of(token: str) -> bytes:
    """A 16-byte GID for the entity with this token. rmw_zenoh takes XXH3-128 of the token;
    any stable 16 bytes unique to the entity serve (it only tells publishers apart), and
    BLAKE2b needs no dependency."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


class Attachment(msgspec.Struct, frozen=True):
    """What rmw_zenoh attaches to every sample (and requires: it drops one without)."""

    seq: int
    stamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(self.gid)}")
        return _ATTACHMENT.pack(self.seq, self.stamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """Parse the 33 bytes; anything else raises ValueError (counted, never fatal)."""
        if len(data) != ATTACHMENT_SIZE:
            raise ValueError(f"an attachment has {ATTACHMENT_SIZE} bytes, got {len(data)}")
        seq, stamp, size, gid = _ATTACHMENT.unpack(data)
        if size != GID_SIZE:
            raise ValueError(f"a GID length of {size}, expected {GID_SIZE}")
        return cls(seq, stamp, gid)


def type_hash_for(distro: str, rihs01: str) -> str:
    """What goes in the keys: Humble's literal, or the RIHS01 hash for Iron and later."""
    if distro not in DISTROS:
        raise ValueError(f"distro: expected one of {', '.join(DISTROS)}, got {distro!r}")
    return HUMBLE_HASH if distro == "humble" else rihs01
