"""Publish a counter on a std_msgs/String topic until killed (the ROS 2 side of test_discovery_netns).

Usage: talker.py TOPIC [PERIOD_SECONDS]. Prints one line per message published, flushed, so the
test can tell the talker is up. Discovery comes from the environment only (ROS_DISCOVERY_SERVER,
RMW_IMPLEMENTATION, ROS_DOMAIN_ID), exactly as a rendered module container gets it.
"""

from __future__ import annotations

import sys

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs
from std_msgs.msg import String


def main() -> None:
    topic = sys.argv[1]
    period = float(sys.argv[2]) if len(sys.argv) > 2 else 0.2
    rclpy.init()
    node = rclpy.create_node("kuberos_talker")
    publisher = node.create_publisher(String, topic, 10)
    count = 0

    def publish() -> None:
        nonlocal count
        count += 1
        publisher.publish(String(data=f"kuberos {count}"))
        print(f"published kuberos {count} subscribers={publisher.get_subscription_count()}", flush=True)

    node.create_timer(period, publish)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
