"""mso with ROS 2 (the optional ``mso[ros2]`` extra; docs/ros2.md).

``mso.ros2:Subscriber`` and ``mso.ros2:Publisher`` bridge ROS 2 topics over rmw_zenoh's wire
protocol; ``mso.ros2:BagSource`` and ``mso.ros2:BagSink`` replay and record rosbag2 bags.
Messages travel mso's edges as Structs generated per ROS type (:mod:`mso.ros2.types`). The
core never imports this package.
"""

from mso.ros2.bags import BagSink, BagSource
from mso.ros2.bridge import Publisher, Subscriber

__all__ = ["BagSink", "BagSource", "Publisher", "Subscriber"]
