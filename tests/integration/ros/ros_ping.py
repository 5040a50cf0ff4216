"""Round trips of ROS 2 messages between two nodes (the real-node tests' delay check).

Usage: ros_ping.py ping|echo. `echo` republishes every std_msgs/String of /kuberos_ping on /kuberos_pong;
`ping` publishes its clock on /kuberos_ping five times a second and prints `rtt_ms <value>` per answer, flushed.
Discovery comes from the environment only, exactly as a rendered module container gets it.
"""

from __future__ import annotations

import sys
import time

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs
from std_msgs.msg import String


def main() -> None:
    mode = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node(f"kuberos_{mode}")
    if mode == "echo":
        pong = node.create_publisher(String, "/kuberos_pong", 10)
        node.create_subscription(String, "/kuberos_ping", pong.publish, 10)
    else:
        ping = node.create_publisher(String, "/kuberos_ping", 10)

        def answered(msg: String) -> None:
            print(f"rtt_ms {(time.monotonic_ns() - int(msg.data)) / 1e6:.2f}", flush=True)

        node.create_subscription(String, "/kuberos_pong", answered, 10)
        node.create_timer(0.2, lambda: ping.publish(String(data=str(time.monotonic_ns()))))
    print("ready", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
