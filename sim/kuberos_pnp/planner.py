"""Motion planner: collision-free arm paths with OMPL against the perceived collision objects.

For every robot it serves it keeps the latest planning scene (`planning_scene/objects`) and answers requests
on `plan/request` with a path on `plan/result`, both trajectory_msgs/JointTrajectory:

- request: `joint_names` = the arm joints, `points[0]` = start configuration, `points[1]` = goal configuration;
  `header.frame_id` = `<request id>[;attached=<object>]` (the object in the hand, planned with the arm).
- result: the same `joint_names`, the path's waypoints (positions only: the controller times them);
  `header.frame_id` = `<request id>;status=ok|failed;planner=<winner>;planning_ms=<ms>;node=<this node>;reason=...`.

Requests from all robots go through one queue, in arrival order: a shared planner serves its robots one at a
time, each request with `parallel_plans` planners racing in worker processes within `planning_time` seconds.

Parameters: `planner` (first planner; the others race beside it), `planners` (comma separated, optional),
`planning_time` (s), `parallel_plans`.
"""

from __future__ import annotations

import queue
import threading
import time

import numpy as np

from kuberos_pnp import common, planning
from kuberos_pnp.perception import boxes_from_markers

DEFAULT_RACE = ("RRTConnect", "KPIECE1", "BiTRRT", "RRT")


def planner_list(first: str, listed: str, parallel: int) -> tuple[str, ...]:
    """`parallel` planners: the configured first, then the listed ones or the default race, cycled if short."""
    names = [n.strip() for n in listed.split(",") if n.strip()] or list(DEFAULT_RACE)
    ordered = [first] + [n for n in names if n != first] if first else names
    return tuple(ordered[i % len(ordered)] for i in range(max(1, parallel)))


def main(argv: list[str] | None = None) -> None:
    import rclpy
    from rclpy.node import Node
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    from visualization_msgs.msg import MarkerArray

    robots = common.robots_from_env()
    rclpy.init(args=common.init_args(argv))

    class PlannerNode(Node):
        def __init__(self):
            super().__init__("motion_planner")
            first = str(self.declare_parameter("planner", "RRTConnect").value)
            listed = str(self.declare_parameter("planners", "").value)
            self.budget = float(self.declare_parameter("planning_time", 1.0).value)
            parallel = int(self.declare_parameter("parallel_plans", 2).value)
            self.race = planner_list(first, listed, parallel)
            self.planner = planning.Planner(parallel=len(self.race))
            self.scenes: dict[str, list] = {r: [] for r in robots}
            self.requests: queue.Queue = queue.Queue(maxsize=256)
            self.results = {r: self.create_publisher(JointTrajectory, common.topic(r, common.PLAN_RESULT), common.reliable_qos()) for r in robots}
            for r in robots:
                self.create_subscription(MarkerArray, common.topic(r, common.SCENE_OBJECTS), lambda m, r=r: self.on_scene(r, m), common.latched_qos())
                self.create_subscription(JointTrajectory, common.topic(r, common.PLAN_REQUEST), lambda m, r=r: self.on_request(r, m), common.reliable_qos(50))
            self.stop = threading.Event()
            self.worker = threading.Thread(target=self.work, name="planning", daemon=True)
            self.worker.start()
            self.get_logger().info(f"planner for {', '.join(robots)} on {common.node_name()}: race {', '.join(self.race)}, {self.budget} s")

        def on_scene(self, robot: str, msg) -> None:
            self.scenes[robot] = boxes_from_markers(msg)

        def on_request(self, robot: str, msg) -> None:
            try:
                self.requests.put_nowait((robot, msg, time.monotonic()))
            except queue.Full:
                self.reply(robot, msg, None, "failed", reason="queue full")

        def work(self) -> None:
            while not self.stop.is_set():
                try:
                    robot, msg, arrived = self.requests.get(timeout=0.2)
                except queue.Empty:
                    continue
                self.answer(robot, msg, arrived)

        def answer(self, robot: str, msg, arrived: float) -> None:
            request_id, values = common.decode_tag(msg.header.frame_id)
            if len(msg.points) < 2:
                self.reply(robot, msg, None, "failed", reason="request needs a start and a goal point")
                return
            start, goal = np.asarray(msg.points[0].positions, float), np.asarray(msg.points[1].positions, float)
            attached = values.get("attached") or None
            scene = [b for b in self.scenes[robot] if b.name != attached]
            held = next((b for b in self.scenes[robot] if b.name == attached), None)
            waited = time.monotonic() - arrived
            result = self.planner.plan(start, goal, scene, attached=held, planners=self.race, time_budget_s=self.budget)
            status = "ok" if result.solved else "failed"
            self.reply(robot, msg, result.path if result.solved else None, status, planner=result.planner,
                       planning_ms=round(result.planning_time_s * 1000, 1), queue_ms=round(waited * 1000, 1),
                       reason=(result.reason or "").replace(";", ",").replace("=", ":") if not result.solved else None)
            common.log_result("planning", robot=robot, request=request_id, node=common.node_name(), solved=result.solved,
                              planner=result.planner, planning_ms=round(result.planning_time_s * 1000, 1),
                              queue_ms=round(waited * 1000, 1), objects=len(scene), waypoints=len(result.path or []))

        def reply(self, robot: str, request, path, status: str, **values) -> None:
            request_id, _ = common.decode_tag(request.header.frame_id)
            out = JointTrajectory()
            out.header.stamp = request.header.stamp
            out.header.frame_id = common.encode_tag(request_id, status=status, node=common.node_name(), **values)
            out.joint_names = list(request.joint_names)
            for q in path or []:
                out.points.append(JointTrajectoryPoint(positions=[float(x) for x in q]))
            self.results[robot].publish(out)

        def on_shutdown(self) -> None:
            self.stop.set()
            self.worker.join(timeout=5)
            self.planner.close()

    common.spin(PlannerNode())


if __name__ == "__main__":
    main()
