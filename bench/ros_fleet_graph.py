"""A fleet's declared graph in one process, for bench_graph_check.py: for each robot, a perception node publishing
``detections`` (best effort, at ``--hz``) and a planner node subscribing it and publishing ``plan`` (reliable), which
a coordinator node subscribes. Usage: ros_fleet_graph.py ROBOTS HZ. Prints "up" once every endpoint exists."""

from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String


def main() -> None:
    robots, hz = sys.argv[1].split(","), float(sys.argv[2])
    rclpy.init()
    executor = SingleThreadedExecutor()
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    for robot in robots:
        namespace = "/" + robot.replace("-", "_")
        perception = rclpy.create_node("perception", namespace=namespace)
        publisher = perception.create_publisher(String, "detections", best_effort)
        perception.create_timer(1.0 / hz, lambda p=publisher: p.publish(String(data="box")))
        planner = rclpy.create_node("planner", namespace=namespace)
        planner.create_subscription(String, "detections", lambda _m: None, best_effort)
        planner.create_publisher(String, "plan", reliable)
        coordinator = rclpy.create_node("coordinator", namespace=namespace)
        coordinator.create_subscription(String, "plan", lambda _m: None, reliable)
        for node in (perception, planner, coordinator):
            executor.add_node(node)
    print("up", flush=True)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
