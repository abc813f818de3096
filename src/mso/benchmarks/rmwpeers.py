"""ROS 2 on Zenoh without ROS 2, for the tests and bench/ros2.py (the ``mso[ros2]`` extra).

An in-process Zenoh router on 127.0.0.1 (``rmw_zenohd``'s role) and sessions opened the way
rmw_zenoh opens them, with what its design document (``docs/design.md`` of ros2/rmw_zenoh) says
a talker puts on the wire: the literal key, CDR from rosbags, the 33-byte attachment packed by
hand. Nothing of :mod:`mso.ros2` is used here, so a round trip through these checks mso against
the document, not against itself.
"""

from __future__ import annotations

import json
import socket
import struct
import time
from collections.abc import Callable
from typing import Any

import zenoh

GID_SIZE = 16


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def config(mode: str, listen: str | None = None, connect: str | None = None) -> zenoh.Config:
    """A Zenoh config: ``mode`` (router, peer, client), multicast scouting off, timestamps on
    (as rmw_zenoh's: its transient_local publishers need them)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps([listen]))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps([connect]))
    return conf


def router(port: int | None = None) -> tuple[Any, str]:
    """A Zenoh router listening on 127.0.0.1 only (a free port by default), and its endpoint."""
    endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    return zenoh.open(config("router", listen=endpoint)), endpoint


def ros_peer(endpoint: str) -> Any:
    """A session as rmw_zenoh opens one: a peer connected to the router, no multicast."""
    return zenoh.open(config("peer", connect=endpoint))


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment: seq (int64), source timestamp ns (int64), GID length (one
    byte, 16), the GID; little-endian."""
    return struct.pack("<qq", seq, stamp_ns) + bytes([GID_SIZE]) + gid


def stamp_of(cdr: bytes) -> int:
    """``header.stamp`` in ns from a stamped message's CDR bytes (its first field, after the
    4-byte encapsulation header): no decoding of the rest."""
    sec, nsec = struct.unpack_from("<iI", cdr, 4)
    return int(sec) * 10**9 + int(nsec)


def tokens(session: Any, prefix: str = "@ros2_lv/0/**") -> list[str]:
    """The liveliness tokens the router knows under ``prefix`` (what ``ros2 topic list``
    reads)."""
    return [str(r.ok.key_expr) for r in session.liveliness().get(prefix, timeout=2.0) if r.ok]


def wait_until(check: Callable[[], bool], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(0.02)
    return check()
