"""Round trips of ROS 2 messages between two nodes (the real-node tests' delay check).

Usage: ros_ping.py ping|echo [PING_TOPIC PONG_TOPIC]. `echo` republishes every std_msgs/String of the ping topic
(/kuberos_ping) on the pong topic (/kuberos_pong); `ping` publishes its clock on the ping topic five times a second
and prints `rtt_ms <value>` per answer, flushed.
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
    ping_topic, pong_topic = sys.argv[2:4] if len(sys.argv) >= 4 else ("/kuberos_ping", "/kuberos_pong")
    rclpy.init()
    node = rclpy.create_node(f"kuberos_{mode}")
    if mode == "echo":
        pong = node.create_publisher(String, pong_topic, 10)
        node.create_subscription(String, ping_topic, pong.publish, 10)
    else:
        ping = node.create_publisher(String, ping_topic, 10)

        def answered(msg: String) -> None:
            print(f"rtt_ms {(time.monotonic_ns() - int(msg.data)) / 1e6:.2f}", flush=True)

        node.create_subscription(String, pong_topic, answered, 10)
        node.create_timer(0.2, lambda: ping.publish(String(data=str(time.monotonic_ns()))))
    print("ready", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
