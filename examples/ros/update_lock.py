"""Hold the robot's update lock while a task must not be disturbed (docs/software.md, "The robot's update lock").

A rollout run with ``rosdeployment_rollout_update_lock`` waits, before each wave, until no robot of the wave holds
its lock (up to ``rosdeployment_rollout_update_lock_wait`` seconds), then leaves the robots that still hold it pending:
none of their modules is touched, and the next rollout run finishes them.

The lock is a ROS 2 node named ``kuberos_update_lock`` in the robot's namespace (``/fetch_1`` for robot ``fetch-1``),
in a participant of its own: it exists exactly while the lock is held. A process that dies holding it releases it
once Fast DDS's participant lease runs out. In a module of a RosDeployment (whose pods have ``KUBEROS_ROBOTS``)::

    from update_lock import UpdateLock

    with UpdateLock():  # the robot this module runs for
        drive_to_the_shelf()

From a shell, for a try: ``python3 update_lock.py fetch-1`` holds the lock of robot fetch-1 until its standard input
closes (or Ctrl-D).
"""

from __future__ import annotations

import os
import sys

import rclpy
from rclpy.context import Context

LOCK_NODE = "kuberos_update_lock"


def robot_namespace(robot: str | None = None) -> str:
    """The robot's ROS namespace: its name with every character but letters and digits as ``_`` (``fetch-1`` ->
    ``/fetch_1``; a name starting with a digit gets ``r_``), as KubeROS names a robot's topics."""
    robot = robot or os.environ["KUBEROS_ROBOTS"].split(",")[0]
    name = "".join(c if c.isascii() and c.isalnum() else "_" for c in robot)
    return "/" + (name if name and not name[0].isdigit() else f"r_{name}")


class UpdateLock:
    """The robot's update lock: held from ``acquire`` (or entering ``with``) to ``release``."""

    def __init__(self, robot: str | None = None):
        self.namespace = robot_namespace(robot)
        self.context: Context | None = None
        self.node = None

    def acquire(self) -> UpdateLock:
        if self.node is None:
            self.context = Context()
            rclpy.init(context=self.context)
            self.node = rclpy.create_node(LOCK_NODE, namespace=self.namespace, context=self.context)
        return self

    def release(self) -> None:
        if self.node is not None:
            self.node.destroy_node()
            rclpy.shutdown(context=self.context)
            self.node = self.context = None

    def __enter__(self) -> UpdateLock:
        return self.acquire()

    def __exit__(self, *_exc) -> None:
        self.release()


if __name__ == "__main__":
    with UpdateLock(sys.argv[1] if len(sys.argv) > 1 else None) as lock:
        print(f"held {lock.namespace}/{LOCK_NODE}", flush=True)
        sys.stdin.read()
    print("released", flush=True)
