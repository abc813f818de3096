"""rmw_zenoh's wire contract against the golden vectors of its design document
(``docs/design.md`` of ros2/rmw_zenoh: "Topic and Service name mapping to Zenoh key
expressions", "Graph Cache", "Publishers"), and the ROS types as typed Structs."""

from __future__ import annotations

import struct
import subprocess
import sys

import msgspec
import pytest

from mso.ros2 import wire
from mso.ros2.bridge import CdrBuffer
from mso.ros2.types import struct_for, type_map

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"


def test_the_rihs01_hash_of_std_msgs_string_is_the_design_documents() -> None:
    assert type_map("jazzy").rihs01("std_msgs/msg/String") == STRING_HASH
    assert wire.type_hash_for("jazzy", STRING_HASH) == STRING_HASH
    assert wire.type_hash_for("humble", STRING_HASH) == "TypeHashNotSupported"


def test_topic_keys_are_the_design_documents() -> None:
    assert wire.dds_type_name("std_msgs/msg/String") == STRING_DDS
    assert (
        wire.topic_key(0, "chatter", "std_msgs/msg/String", STRING_HASH)
        == f"0/chatter/{STRING_DDS}/{STRING_HASH}"
    )
    assert (
        wire.topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH)
        == f"0/robot1/chatter/{STRING_DDS}/{STRING_HASH}"
    )
    humble = wire.topic_key(0, "/chatter", "std_msgs/msg/String", "TypeHashNotSupported")
    assert humble == f"0/chatter/{STRING_DDS}/TypeHashNotSupported"


def test_liveliness_tokens_are_the_design_documents() -> None:
    listener = "aac3178e146ba6f1fc6e6a4085e77f21"
    talker = "8b20917502ee955ac4476e0266340d5c"
    assert (
        wire.node_token(2, listener, 0, "listener") == f"@ros2_lv/2/{listener}/0/0/NN/%/%/listener"
    )
    ms = wire.entity_token(
        "MS", 2, listener, 0, 10, "listener", "chatter", "std_msgs/msg/String", STRING_HASH,
        wire.QoS(depth=10),
    )  # fmt: skip
    assert ms == (
        f"@ros2_lv/2/{listener}/0/10/MS/%/%/listener/%chatter/{STRING_DDS}/{STRING_HASH}"
        "/::,10:,:,:,,"
    )
    mp = wire.entity_token(
        "MP", 2, talker, 0, 10, "talker", "/chatter", "std_msgs/msg/String", STRING_HASH,
        wire.QoS(depth=7),
    )  # fmt: skip
    assert mp == (
        f"@ros2_lv/2/{talker}/0/10/MP/%/%/talker/%chatter/{STRING_DDS}/{STRING_HASH}/::,7:,:,:,,"
    )


def test_qos_keys_leave_out_rmw_zenohs_defaults() -> None:
    assert wire.QoS(depth=42).keyexpr() == "::,:,:,:,,"
    odd = wire.QoS("best_effort", "transient_local", "keep_all", 5)
    assert odd.keyexpr() == "2:1:2,5:,:,:,,"
    assert wire.qos_from({"history": "keep_last", "depth": 1}) == wire.QoS(depth=1)
    with pytest.raises(ValueError, match="reliability"):
        wire.qos_from({"reliability": "sometimes"})
    with pytest.raises(ValueError):
        wire.qos_from({"depht": 3})


def test_the_attachment_is_33_little_endian_bytes() -> None:
    gid = bytes(range(16))
    att = wire.Attachment(seq=1, stamp_ns=1_700_000_000_123_456_789, gid=gid)
    raw = att.encode()
    # the design document: 8 B sequence number, 8 B timestamp (ns), 1 B GID length, 16 B GID
    expected = (
        (1).to_bytes(8, "little")
        + (1_700_000_000_123_456_789).to_bytes(8, "little")
        + b"\x10"
        + gid
    )
    assert raw == expected and len(raw) == 33
    assert wire.Attachment.decode(raw) == att
    with pytest.raises(ValueError):
        wire.Attachment.decode(raw[:-1])
    with pytest.raises(ValueError):
        wire.Attachment.decode(raw[:16] + b"\x08" + gid)
    assert len(wire.gid_of("@ros2_lv/0/x")) == 16


def test_cdr_of_a_string_is_what_rmw_zenoh_puts_on_the_wire() -> None:
    tm = type_map()
    msg = tm.to_ros("std_msgs/msg/String", struct_for("std_msgs/msg/String")(data="hi"))
    # little-endian CDR header, uint32 length with the NUL, the bytes, the NUL
    assert bytes(tm.store.serialize_cdr(msg, "std_msgs/msg/String")) == (
        b"\x00\x01\x00\x00" + struct.pack("<I", 3) + b"hi\x00"
    )


def test_a_publishers_reused_buffer_gives_each_message_its_own_exact_cdr() -> None:
    """The Publisher serializes into one buffer kept between calls: a message of the same
    size with its padding and NULs elsewhere must not inherit the last one's bytes."""
    tm = type_map()
    kv = "diagnostic_msgs/msg/KeyValue"
    buffer = CdrBuffer(tm, kv)
    # 22 bytes each; the 2 bytes of padding after the first string fall elsewhere each time
    for key, value in [("xxxxx", "y"), ("x", "yyyyy"), ("ab", "cdef"), ("", "z" * 7)]:
        msg = tm.store.types[kv](key=key, value=value)
        assert bytes(buffer.encode(msg)) == bytes(tm.store.serialize_cdr(msg, kv)), (key, value)
    image = "sensor_msgs/msg/Image"
    buffer = CdrBuffer(tm, image)
    for fill in (255, 7):
        event = msgspec.convert({**_sample(image), "data": bytes([fill]) * 6}, struct_for(image))
        msg = tm.to_ros(image, event)
        assert bytes(buffer.encode(msg)) == bytes(tm.store.serialize_cdr(msg, image))


@pytest.mark.parametrize(
    "ros_type",
    [
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/LaserScan",
        "sensor_msgs/msg/CameraInfo",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "diagnostic_msgs/msg/DiagnosticArray",
    ],
)
def test_ros_messages_become_typed_structs_and_back(ros_type: str) -> None:
    tm = type_map()
    cls = struct_for(ros_type)
    assert issubclass(cls, msgspec.Struct) and cls.__name__ == ros_type.replace("/", "__")
    event = msgspec.convert(_sample(ros_type), cls)
    raw = tm.store.serialize_cdr(tm.to_ros(ros_type, event), ros_type)
    back = tm.to_struct(ros_type, tm.store.deserialize_cdr(raw, ros_type))
    assert back == event
    # and it crosses an mso edge as msgpack, typed at the other end
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(back), type=cls) == event


def _sample(ros_type: str) -> dict[str, object]:
    header = {"stamp": {"sec": 12, "nanosec": 34}, "frame_id": "base"}
    return {
        "sensor_msgs/msg/Image": {
            "header": header, "height": 2, "width": 3, "encoding": "mono8", "step": 3,
            "data": bytes(range(6)),
        },
        "sensor_msgs/msg/LaserScan": {
            "header": header, "angle_min": -1.5, "ranges": [1.0, 2.5, 4.0], "intensities": [],
        },
        "sensor_msgs/msg/CameraInfo": {"header": header, "k": [float(i) for i in range(9)]},
        "geometry_msgs/msg/PoseWithCovarianceStamped": {
            "header": header, "pose": {"pose": {"position": {"x": 1.0}}, "covariance": [0.5] * 36},
        },
        "diagnostic_msgs/msg/DiagnosticArray": {
            "header": header,
            "status": [{"level": 1, "name": "motor", "values": [{"key": "t", "value": "40"}]}],
        },
    }[ros_type]  # fmt: skip


def test_a_format_path_names_the_generated_struct_under_the_allowlist() -> None:
    from mso.model.imports import DEFAULT_ALLOWED, allow_code, allowed_code, resolve

    before = allowed_code()
    allow_code(DEFAULT_ALLOWED)
    try:
        cls = resolve("mso.ros2.types:sensor_msgs__msg__LaserScan")
        assert cls is struct_for("sensor_msgs/msg/LaserScan")
        assert resolve("mso.ros2:Subscriber").__name__ == "Subscriber"
        assert resolve("mso.ros2:BagSource").__name__ == "BagSource"
    finally:
        allow_code(before)


def test_the_core_imports_nothing_of_ros2() -> None:
    code = (
        "import sys, mso.cli, mso.node.core, mso.sim.runner, mso.daemon.assembly\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('zenoh', 'rosbags')"
        " or m.startswith('mso.ros2')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
