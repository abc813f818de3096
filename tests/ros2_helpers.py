"""An in-process Zenoh router on 127.0.0.1 and an independent ROS 2 talker and listener
written from rmw_zenoh's design document (literal keys, rosbags' CDR, the attachment packed
by hand): what a ROS 2 node on rmw_zenoh would put on the wire and expect from it. Nothing of
mso.ros2 is used here, so the round trips test mso against the document, not against itself.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from rosbags.typesys import Stores, get_typestore

from mso.benchmarks import rmwpeers
from mso.benchmarks.rmwpeers import free_port as free_port
from mso.benchmarks.rmwpeers import tokens as tokens
from waits import patience

STORE = get_typestore(Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def router(port: int) -> Any:
    """A Zenoh router listening on 127.0.0.1:port only (rmw_zenohd's role)."""
    return rmwpeers.router(port)[0]


def ros_peer(port: int) -> Any:
    """A session as rmw_zenoh opens one: a peer connected to the router, no multicast."""
    return rmwpeers.ros_peer(f"tcp/127.0.0.1:{port}")


def chatter_key(domain: int = 0, hash_: str = STRING_HASH, topic: str = "chatter") -> str:
    return f"{domain}/{topic}/std_msgs::msg::dds_::String_/{hash_}"


def cdr_string(text: str) -> bytes:
    msg = STORE.types["std_msgs/msg/String"](data=text)
    return bytes(STORE.serialize_cdr(msg, "std_msgs/msg/String"))


def decode_string(sample: Any) -> str:
    """A ``std_msgs/String`` sample's text."""
    msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String")
    return str(msg.data)


def attachment(seq: int, gid: bytes) -> bytes:
    return rmwpeers.attachment(seq, time.time_ns(), gid)


def wait_for(check: Callable[[], bool], timeout: float = 10.0) -> bool:
    return rmwpeers.wait_until(check, patience(timeout))


def routed(session: Any, key: str, timeout: float = 10.0) -> bool:
    """True once ``session`` knows a subscription on ``key`` in another session (Zenoh's
    matching status, read from a probe publisher: every publisher of the session routes by the
    same tables), so what its publishers put from then on reaches it; False at the deadline."""
    probe = session.declare_publisher(key)
    try:
        return wait_for(lambda: bool(probe.matching_status.matching), timeout)
    finally:
        probe.undeclare()


class Listener:
    """A ROS 2 listener as rmw_zenoh would be one: subscribes on the literal key, requires
    the 33-byte attachment, decodes CDR with rosbags."""

    def __init__(self, session: Any, key: str) -> None:
        self.got: list[tuple[str, int, int, bytes]] = []  # text, seq, stamp, gid
        self.bad = 0
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else b""
        if len(att) != 33 or att[16] != 16:
            with self.lock:
                self.bad += 1
            return
        seq, stamp = struct.unpack_from("<qq", att)
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String")
        with self.lock:
            self.got.append((msg.data, seq, stamp, att[17:]))

    def texts(self) -> list[str]:
        with self.lock:
            return [g[0] for g in self.got]
