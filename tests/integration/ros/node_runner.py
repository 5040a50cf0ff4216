"""What the test's ROS 2 programs share: spin a node until killed, then shut down cleanly."""

from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException


def spin_until_killed(node) -> None:
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
