"""Motion planner: collision-free arm paths with OMPL against the perceived collision objects.

For every robot it serves it keeps the recent planning scenes (`planning_scene/objects`, by camera stamp) and
answers requests on `plan/request` with a path on `plan/result`, both trajectory_msgs/JointTrajectory:

- request: `joint_names` = the arm joints, `points[0]` = start configuration, `points[1]` = goal configuration;
  `header.frame_id` = `<request id>;scene=<stamp>[;ignore=<a+b>][;carry=<box>|<xyz>|<quat xyzw>|<a+b>]`:
  which scene to plan in (the coordinator picks one taken while the arm was out of the camera's view: this
  perception has no self-filter), the boxes the arm may touch (the object between the fingers), and the
  object carried in the hand with its pose in the grasp frame and the boxes it may touch.
- result: the same `joint_names`, the path's waypoints (positions only: the controller times them);
  `header.frame_id` = `<request id>;status=ok|failed;planner=<winner>;planning_ms=..;queue_ms=..;node=..;reason=..`.

Requests from all robots go through one queue, in arrival order: a shared planner serves its robots one at a
time. Each request races `parallel_plans` OMPL planners in worker processes (kuberos_pnp.planning.Planner)
for `planning_time` seconds, and once more with twice the time if none found a path.

Parameters: `planner` (first in the race), `planners` (comma separated, the rest of the race),
`planning_time` (s), `parallel_plans`, `scene_history` (scenes kept per robot), `scene_wait` (s), `seed` (the
worker processes' OMPL seeds).

Once its worker processes run and its subscriptions exist it logs a `planner_ready` record (seconds since start):
a coordinator matched with its subscription can send.
"""

from __future__ import annotations

import queue
import threading
import time

import numpy as np

from kuberos_pnp import common, planning
from kuberos_pnp.perception import boxes_from_markers

DEFAULT_RACE = planning.DEFAULT_PLANNERS
STARTED = time.monotonic()  # about when the process started (this module is its main)


def planner_list(first: str, listed: str, parallel: int) -> tuple[str, ...]:
    """`parallel` planners: the configured first, then the listed ones or the default race, cycled if short."""
    names = [n.strip() for n in listed.split(",") if n.strip()] or list(dict.fromkeys(DEFAULT_RACE))
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
            first = str(common.declare(self, "planner", "RRTConnect"))
            listed = str(common.declare(self, "planners", ""))
            self.budget = float(common.declare(self, "planning_time", 1.0))
            parallel = int(common.declare(self, "parallel_plans", 2))
            self.history = int(common.declare(self, "scene_history", 600))
            self.scene_wait = float(common.declare(self, "scene_wait", 3.0))
            seed = int(common.declare(self, "seed", 0))
            self.race = planner_list(first, listed, parallel)
            pool_started = time.monotonic()
            self.planner = planning.Planner(parallel=len(self.race), planners=self.race, seed=seed)
            pool_s = time.monotonic() - pool_started
            self.scenes: dict[str, dict[str, list]] = {r: {} for r in robots}
            self.requests: queue.Queue = queue.Queue(maxsize=256)
            self.results = {
                r: self.create_publisher(JointTrajectory, common.topic(r, common.PLAN_RESULT), common.reliable_qos())
                for r in robots
            }
            for r in robots:
                self.create_subscription(
                    MarkerArray, common.topic(r, common.SCENE_OBJECTS), lambda m, r=r: self.on_scene(r, m), common.latched_qos()
                )
                self.create_subscription(
                    JointTrajectory,
                    common.topic(r, common.PLAN_REQUEST),
                    lambda m, r=r: self.on_request(r, m),
                    common.reliable_qos(50),
                )
            self.stop = threading.Event()
            self.worker = threading.Thread(target=self.work, name="planning", daemon=True)
            self.worker.start()
            self.get_logger().info(
                f"planner for {', '.join(robots)} on {common.node_name()}: race {', '.join(self.race)}, {self.budget} s"
            )
            # Ready: the worker processes run and the subscriptions exist (a coordinator matching them may send).
            common.log_result(
                "planner_ready",
                robots=robots,
                node=common.node_name(),
                startup_s=round(time.monotonic() - STARTED, 2),
                pool_s=round(pool_s, 2),
            )

        def on_scene(self, robot: str, msg) -> None:
            if not msg.markers:
                return
            scenes = self.scenes[robot]
            scenes[common.scene_key(msg.markers[0].header.stamp)] = boxes_from_markers(msg)
            while len(scenes) > self.history:
                scenes.pop(next(iter(scenes)))

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
            waited = time.monotonic() - arrived
            if len(msg.points) < 2:
                self.reply(robot, msg, None, "failed", reason="request needs a start and a goal point")
                return
            scene = self.wait_for_scene(robot, values.get("scene", ""))
            if scene is None:
                self.reply(robot, msg, None, "failed", reason=f"unknown scene {values.get('scene')}")
                return
            try:
                carry = self.carried(scene, values.get("carry"))
            except (KeyError, ValueError) as error:
                self.reply(robot, msg, None, "failed", reason=f"bad carry: {error}")
                return
            start, goal = np.asarray(msg.points[0].positions, float), np.asarray(msg.points[1].positions, float)
            ignore = common.decode_names(values.get("ignore"))
            result = self.planner.plan(start, goal, scene, carry, self.budget, ignore)
            if not result.solved:  # once more, with twice the time
                result = self.planner.plan(start, goal, scene, carry, 2 * self.budget, ignore)
            self.reply(
                robot,
                msg,
                result.path if result.solved else None,
                "ok" if result.solved else "failed",
                planner=result.planner,
                planning_ms=round(result.planning_time_s * 1000, 1),
                queue_ms=round(waited * 1000, 1),
                reason=None if result.solved else (result.reason or "").replace(";", ",").replace("=", ":"),
            )
            common.log_result(
                "planning",
                robot=robot,
                request=request_id,
                node=common.node_name(),
                solved=result.solved,
                planner=result.planner,
                planning_ms=round(result.planning_time_s * 1000, 1),
                queue_ms=round(waited * 1000, 1),
                objects=len(scene),
                waypoints=len(result.path or []),
            )

        def wait_for_scene(self, robot: str, key: str):
            """The scene the request names; it may still be on its way here (perception publishes it to the
            coordinator and to this planner over different links), so wait up to `scene_wait` seconds."""
            deadline = time.monotonic() + self.scene_wait
            while (scene := self.scenes[robot].get(key)) is None and time.monotonic() < deadline:
                time.sleep(0.02)
            return scene

        @staticmethod
        def carried(scene, text):
            decoded = common.decode_carry(text)
            if decoded is None:
                return None
            name, position, quat, ignore = decoded
            box = next((b for b in scene if b.name == name), None)
            if box is None:
                raise KeyError(f"no box {name} in the scene")
            return planning.Attached(box, position, quat, ignore)

        def reply(self, robot: str, request, path, status: str, **values) -> None:
            request_id, _ = common.decode_tag(request.header.frame_id)
            out = JointTrajectory()
            out.header.stamp = request.header.stamp
            out.header.frame_id = common.encode_tag(request_id, status=status, node=common.node_name(), **values)
            out.joint_names = list(request.joint_names)
            for q in path or []:
                out.points.append(JointTrajectoryPoint(positions=[float(x) for x in q]))
            common.wait_for_subscriber(self.results[robot], 5.0)
            self.results[robot].publish(out)

        def on_shutdown(self) -> None:
            self.stop.set()
            self.worker.join(timeout=5)
            self.planner.close()

    common.spin(PlannerNode())


if __name__ == "__main__":
    main()
