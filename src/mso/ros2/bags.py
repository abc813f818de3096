"""rosbag2 bags as mso vertices: :class:`BagSource` replays one, :class:`BagSink` records one.

So ROS data drives an mso app without ROS (a bag recorded on the robot, replayed on a laptop),
and what mso makes opens in ROS tools (``ros2 bag play``, Foxglove). A bag is rosbag2's
directory (``metadata.yaml`` beside its ``.db3`` or ``.mcap`` file); rosbags reads and writes
it, and messages travel as the Structs of :mod:`mso.ros2.types`. An mso edge carries one
format, so a BagSource replays topics of one message type (name them in ``topics``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from mso.ros2.types import TypeMap, register, type_map

POLL_S = 0.05  # the longest one next() sleeps towards a message's time before it yields None
_STORAGE = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def _bag_dir(path: str | Path) -> Path:
    """The bag's directory: the one named, or the one holding the named .db3/.mcap file."""
    p = Path(path)
    if p.is_file() and (p.parent / "metadata.yaml").is_file():
        return p.parent
    return p


class BagSource:
    """A source: the messages of a bag, in order, as Structs.

    Params: ``path`` (the bag directory or its .db3/.mcap file), ``topics`` (a list; default
    every topic, which must then share one type), ``rate`` (1.0 replays at the recorded
    timing, 10 ten times as fast, 0 as fast as the edge takes them), ``distro`` (the type store
    to decode with), ``msgdef`` and ``type`` (a custom type's ``.msg`` text and name).
    A relocated BagSource carries how far it got and goes on from there.
    """

    def __init__(
        self,
        path: str,
        topics: list[str] | None = None,
        rate: float = 1.0,
        distro: str = "jazzy",
        type: str | None = None,
        msgdef: str | None = None,
    ) -> None:
        if not isinstance(rate, int | float) or rate < 0:
            raise ValueError(f"rate: expected a factor >= 0 (0: as fast as possible), got {rate}")
        if msgdef is not None:
            if type is None:
                raise ValueError("msgdef needs the type it defines (type: my_pkg/msg/Name)")
            register(type, msgdef)
        self.path = _bag_dir(path)
        self.topics = None if topics is None else [("/" + t.strip("/")) for t in topics]
        self.rate = float(rate)
        self.types: TypeMap = type_map(distro)
        self.ros_type = type
        self.reader: Reader | None = None
        self.messages: Any = None
        self.pending: tuple[int, Any] | None = None
        self.first_stamp: int | None = None
        self.t0 = 0.0
        self.emitted = 0
        self.skip = 0  # messages already replayed before a move

    def open(self) -> None:
        reader = Reader(self.path)
        reader.open()
        conns = [c for c in reader.connections if self.topics is None or c.topic in self.topics]
        kinds = {c.msgtype for c in conns}
        if len(kinds) != 1:
            reader.close()
            found = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections))
            raise ValueError(
                f"a BagSource replays topics of one type; {self.path} has {found}: name them "
                "in topics"
            )
        msgtype = kinds.pop()
        if self.ros_type is not None and self.ros_type != msgtype:
            reader.close()
            raise ValueError(f"the bag's topics carry {msgtype}, not {self.ros_type}")
        self.types.check(msgtype)
        self.ros_type = msgtype
        self.reader = reader
        self.messages = reader.messages(connections=conns)

    def __iter__(self) -> BagSource:
        return self

    def __next__(self) -> Any:
        if self.messages is None:
            raise StopIteration
        while self.skip > 0:
            self.skip -= 1
            next(self.messages)
        if self.pending is None:
            try:
                _conn, stamp, raw = next(self.messages)
            except StopIteration:
                self._close_reader()
                raise
            self.pending = (stamp, raw)
        stamp, raw = self.pending
        if self.rate > 0:
            if self.first_stamp is None:
                self.first_stamp, self.t0 = stamp, time.monotonic()
            wait = self.t0 + (stamp - self.first_stamp) / 1e9 / self.rate - time.monotonic()
            if wait > 0:  # not due yet: sleep a little, and let the worker take a stop
                time.sleep(min(wait, POLL_S))
                if wait > POLL_S:
                    return None
        self.pending = None
        assert self.ros_type is not None
        msg = self.types.store.deserialize_cdr(raw, self.ros_type)
        self.emitted += 1
        return self.types.to_struct(self.ros_type, msg)

    def get_state(self) -> int:
        return self.emitted

    def set_state(self, state: int) -> None:
        self.emitted = self.skip = int(state)

    def stats(self) -> dict[str, Any]:
        return {"replayed": self.emitted, "type": self.ros_type}

    def _close_reader(self) -> None:
        reader, self.reader, self.messages = self.reader, None, None
        if reader is not None:
            reader.close()

    def close(self) -> None:
        self._close_reader()


class BagSink:
    """A sink: records every event it consumes to a new bag, stamped with the time it arrived.

    Params: ``path`` (the bag directory to create; it must not exist), ``topic``, ``type``,
    ``storage`` (``mcap``, or ``sqlite3`` for a .db3), ``distro``, ``msgdef``. The bag is
    complete once the stream ends or the vertex stops here.
    """

    def __init__(
        self,
        path: str,
        topic: str,
        type: str,
        storage: str = "mcap",
        distro: str = "jazzy",
        msgdef: str | None = None,
    ) -> None:
        if storage not in _STORAGE:
            raise ValueError(f"storage: expected mcap or sqlite3, got {storage!r}")
        if msgdef is not None:
            register(type, msgdef)
        self.types: TypeMap = type_map(distro)
        self.types.check(type)
        self.path = Path(path)
        self.topic = "/" + topic.strip("/")
        self.ros_type = type
        self.storage = _STORAGE[storage]
        self.writer: Writer | None = None
        self.connection: Any = None
        self.written = 0

    def open(self) -> None:
        writer = Writer(self.path, version=9, storage_plugin=self.storage)
        writer.open()
        self.connection = writer.add_connection(
            self.topic, self.ros_type, typestore=self.types.store
        )
        self.writer = writer

    def __call__(self, event: Any) -> None:
        if self.writer is None:
            raise RuntimeError(f"the bag {self.path} is closed")
        msg = self.types.to_ros(self.ros_type, event)
        data = self.types.store.serialize_cdr(msg, self.ros_type)
        self.writer.write(self.connection, time.time_ns(), data)
        self.written += 1

    def stats(self) -> dict[str, Any]:
        return {"recorded": self.written, "path": str(self.path)}

    def end(self) -> None:
        self.close()

    def close(self) -> None:
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.close()
