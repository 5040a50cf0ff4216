"""ROS 2 ends of the bridge tests: talk, listen, respond (request/reply). Discovery from the environment only.

    bridge_probe.py talk TOPIC string|image [--period S] [--size BYTES] [--best-effort] [--transient-local]
    bridge_probe.py listen TOPIC string|image [--best-effort] [--transient-local]
    bridge_probe.py respond REQUEST_TOPIC REPLY_TOPIC
    bridge_probe.py request REQUEST_TOPIC REPLY_TOPIC [--period S]

Lines, flushed: "ready"; "published <n> subscribers=<k>"; "received <n> bytes=<b>" (an image's n is its
header.frame_id, its bytes the length of its data); "replied <n>"; "reply <n> rtt_ms=<ms>".
"""

from __future__ import annotations

import argparse
import time

import rclpy
from node_runner import spin_until_killed  # beside this file, on sys.path when it runs
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String


def qos(args) -> QoSProfile:
    return QoSProfile(
        depth=10,
        reliability=ReliabilityPolicy.BEST_EFFORT if args.best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if args.transient_local else DurabilityPolicy.VOLATILE,
    )


def make(kind: str, count: int, size: int):
    if kind == "string":
        return String(data=f"kuberos {count}")
    image = Image(height=1, width=size, encoding="mono8", step=size, is_bigendian=0)
    image.header.frame_id = str(count)
    image.header.stamp.sec, image.header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
    image.data = bytes([count % 256]) * size
    return image


def describe(kind: str, msg) -> tuple[int, int]:
    if kind == "string":
        return int(msg.data.split()[-1]), len(msg.data)
    return int(msg.header.frame_id), len(msg.data)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=("talk", "listen", "respond", "request"))
    parser.add_argument("topic")
    parser.add_argument("second")  # the type (talk, listen) or the reply topic (respond, request)
    parser.add_argument("--period", type=float, default=0.2)
    parser.add_argument("--size", type=int, default=1 << 20)
    parser.add_argument("--best-effort", action="store_true")
    parser.add_argument("--transient-local", action="store_true")
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node(f"kuberos_probe_{args.mode}")
    count = 0
    if args.mode == "talk":
        kind = args.second
        publisher = node.create_publisher(String if kind == "string" else Image, args.topic, qos(args))

        def publish() -> None:
            nonlocal count
            count += 1
            publisher.publish(make(kind, count, args.size))
            print(f"published {count} subscribers={publisher.get_subscription_count()}", flush=True)

        node.create_timer(args.period, publish)
    elif args.mode == "listen":
        kind = args.second

        def received(msg) -> None:
            number, size = describe(kind, msg)
            print(f"received {number} bytes={size}", flush=True)

        node.create_subscription(String if kind == "string" else Image, args.topic, received, qos(args))
    elif args.mode == "respond":
        publisher = node.create_publisher(String, args.second, 10)

        def answer(msg) -> None:
            number = int(msg.data.split()[-1])
            publisher.publish(String(data=f"reply {number}"))
            print(f"replied {number}", flush=True)

        node.create_subscription(String, args.topic, answer, 10)
    else:
        publisher = node.create_publisher(String, args.topic, 10)
        sent: dict[int, float] = {}

        def request() -> None:
            nonlocal count
            count += 1
            sent[count] = time.monotonic()
            publisher.publish(String(data=f"request {count}"))
            print(f"published {count} subscribers={publisher.get_subscription_count()}", flush=True)

        def reply(msg) -> None:
            number = int(msg.data.split()[-1])
            rtt = (time.monotonic() - sent.pop(number, time.monotonic())) * 1000
            print(f"reply {number} rtt_ms={rtt:.2f}", flush=True)

        node.create_subscription(String, args.second, reply, 10)
        node.create_timer(args.period, request)
    print("ready", flush=True)
    spin_until_killed(node)


if __name__ == "__main__":
    main()
