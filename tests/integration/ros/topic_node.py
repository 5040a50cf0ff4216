"""One ROS 2 node that publishes and subscribes std_msgs/msg/String topics with given QoS and rate (the module side
of test_topic_check).

Usage: topic_node.py NAME NAMESPACE [--pub TOPIC:RELIABILITY:HZ[:DEADLINE_MS]]... [--sub TOPIC:RELIABILITY[:DEADLINE_MS]]...
Relative topics are in NAMESPACE; a deadline is offered (--pub) or requested (--sub).
Prints "up" once every endpoint exists; each message published is "tick N".
"""

from __future__ import annotations

import argparse

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

_RELIABILITY = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}


def _qos(reliability: str, deadline_ms: str = "") -> QoSProfile:
    qos = QoSProfile(depth=10, reliability=_RELIABILITY[reliability])
    if deadline_ms:
        qos.deadline = Duration(nanoseconds=int(float(deadline_ms) * 1e6))
    return qos


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("name")
    parser.add_argument("namespace")
    parser.add_argument("--pub", action="append", default=[])
    parser.add_argument("--sub", action="append", default=[])
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node(args.name, namespace=args.namespace)
    for spec in args.pub:
        topic, reliability, hz, *deadline = spec.split(":")
        publisher = node.create_publisher(String, topic, _qos(reliability, *deadline))
        count = [0]

        def tick(publisher=publisher, count=count):
            count[0] += 1
            publisher.publish(String(data=f"tick {count[0]}"))

        node.create_timer(1.0 / float(hz), tick)
    for spec in args.sub:
        topic, reliability, *deadline = spec.split(":")
        node.create_subscription(String, topic, lambda _m: None, _qos(reliability, *deadline))
    print("up", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
