"""An operator for the ROS 2 app tests: what a robotics engineer's own vertex would be."""

from __future__ import annotations

from mso.ros2.types import std_msgs__msg__String


def shout(event: std_msgs__msg__String) -> std_msgs__msg__String:
    """Upper-case a chatter line: proof that the event arrived typed and went on typed."""
    return std_msgs__msg__String(data=event.data.upper())
