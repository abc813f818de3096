"""Make the small bag the ROS 2 tests and docs replay: ``tests/data/ros2_chatter``.

20 ``std_msgs/msg/String`` messages on ``/chatter`` ("hello world 0" … 19), 100 ms apart (a
10 Hz talker), written with rosbags as a rosbag2 MCAP bag. Run it again to remake the bag:
``.venv/bin/python tests/make_ros2_bag.py``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

BAG = Path(__file__).resolve().parent / "data" / "ros2_chatter"
COUNT = 20
PERIOD_NS = 100_000_000
START_NS = 1_700_000_000_000_000_000  # a fixed start, so the bag is the same every time


def texts() -> list[str]:
    return [f"hello world {i}" for i in range(COUNT)]


def main() -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types["std_msgs/msg/String"]
    shutil.rmtree(BAG, ignore_errors=True)
    with Writer(BAG, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for i, text in enumerate(texts()):
            data = store.serialize_cdr(String(data=text), "std_msgs/msg/String")
            writer.write(conn, START_NS + i * PERIOD_NS, data)
    print(f"wrote {BAG}")


if __name__ == "__main__":
    main()
