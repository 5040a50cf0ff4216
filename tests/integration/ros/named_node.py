"""Spin one ROS 2 node of a given name and namespace until killed (the ROS 2 side of test_ros_probe).

Usage: named_node.py NAME NAMESPACE. Prints "up" once the node exists. Discovery comes from the environment.
"""

from __future__ import annotations

import sys

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs


def main() -> None:
    rclpy.init()
    node = rclpy.create_node(sys.argv[1], namespace=sys.argv[2])
    print("up", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
