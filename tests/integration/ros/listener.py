"""Print every std_msgs/String received on a topic until killed (the ROS 2 side of test_discovery_netns).

Usage: listener.py TOPIC. Prints "ready" once subscribed, then "received <data>" per message,
flushed. Discovery comes from the environment only, exactly as a rendered module container gets it.
"""

from __future__ import annotations

import sys

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs
from std_msgs.msg import String


def main() -> None:
    topic = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node("kuberos_listener")
    node.create_subscription(String, topic, lambda msg: print(f"received {msg.data}", flush=True), 10)
    print("ready", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
