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

Scaled (docs/scaling.md): with `KUBEROS_ROBOTS_FILE` the planner reads its robots from that file and follows its
changes (every 0.5 s): a robot added is subscribed to, and gets the robot's recent planning scenes at once (they
are published with a history of `SCENE_HISTORY`, so the scene a cycle in progress names is there); a robot removed
is still answered for `handover_s` seconds (until the new planner's subscription has surely matched; the
coordinator takes the first of two answers), then unsubscribed; requests already taken are answered (drained). A
robot added while running whose named scene has not arrived within 0.5 s is left to its previous planner (no
"unknown scene" answer during a handover). Its load gauge
`kuberos_planner_queue_depth` (requests waiting or being solved, averaged over the last 10 s) is written to
`KUBEROS_METRICS_FILE` (Prometheus text format) and, with `metrics_port` (not 0), served on that port at
`/metrics`.
"""

from __future__ import annotations

import http.server
import os
import queue
import threading
import time
from collections import deque

import numpy as np

from kuberos_pnp import common, planning
from kuberos_pnp.perception import boxes_from_markers

DEFAULT_RACE = planning.DEFAULT_PLANNERS
LOAD_WINDOW_S = 10.0  # the queue gauge's averaging window
GAUGE = "kuberos_planner_queue_depth"


class Load:
    """Requests waiting or being solved, sampled every 0.1 s and averaged over ``window`` seconds."""

    def __init__(self, window: float = LOAD_WINDOW_S):
        self.samples: deque = deque()
        self.window = window

    def sample(self, now: float, depth: int) -> None:
        self.samples.append((now, depth))
        while self.samples and self.samples[0][0] < now - self.window:
            self.samples.popleft()

    def mean(self) -> float:
        return sum(d for _, d in self.samples) / len(self.samples) if self.samples else 0.0

    def exposition(self, robots: int) -> str:
        return (
            f"# HELP {GAUGE} Planning requests waiting or being solved, mean of the last {self.window:g} s.\n"
            f"# TYPE {GAUGE} gauge\n{GAUGE} {self.mean():.4f}\n"
            "# HELP kuberos_planner_robots Robots this planner serves.\n"
            f"# TYPE kuberos_planner_robots gauge\nkuberos_planner_robots {robots}\n"
        )


def write_atomically(path: str, text: str) -> None:
    with open(path + ".new", "w", encoding="utf-8") as handle:
        handle.write(text)
    os.replace(path + ".new", path)


def serve_metrics(port: int, text_of) -> None:
    """/metrics on ``port`` (all addresses), from ``text_of()``, in a daemon thread."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = text_of().encode()
            self.send_response(200 if self.path.startswith("/metrics") else 404)
            self.send_header("Content-Type", "text/plain; version=0.0.4")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("", port), Handler)
    threading.Thread(target=server.serve_forever, name="metrics", daemon=True).start()


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
    robots_file = os.environ.get("KUBEROS_ROBOTS_FILE", "")
    metrics_file = os.environ.get("KUBEROS_METRICS_FILE", "")
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
            self.handover_s = float(common.declare(self, "handover_s", 5.0))
            metrics_port = int(common.declare(self, "metrics_port", 0))
            self.race = planner_list(first, listed, parallel)
            pool_started = time.monotonic()
            self.planner = planning.Planner(parallel=len(self.race), planners=self.race, seed=seed)
            pool_s = time.monotonic() - pool_started
            self.scenes: dict[str, dict[str, list]] = {}
            self.requests: queue.Queue = queue.Queue(maxsize=256)
            self.results = {}
            self.wiring: dict[str, list] = {}  # robot -> its subscriptions
            self.lost: dict[str, float] = {}  # robot -> when it was removed (answered for the cycle in progress)
            self.added: dict[str, float] = {}  # robot -> when it was added while running
            self.busy = 0
            self.load = Load()
            for r in robots:
                self.serve(r)
            self.stop = threading.Event()
            self.worker = threading.Thread(target=self.work, name="planning", daemon=True)
            self.worker.start()
            self.get_logger().info(
                f"planner for {', '.join(robots)} on {common.node_name()}: race {', '.join(self.race)}, {self.budget} s"
            )
            if robots_file:
                self.create_timer(0.5, lambda: self.follow(common.read_robots(robots_file)))
            if metrics_file or metrics_port:
                self.create_timer(0.1, self.measure)
            if metrics_port:
                serve_metrics(metrics_port, lambda: self.load.exposition(len(self.wiring) - len(self.lost)))
            # Ready: the worker processes run and the subscriptions exist (a coordinator matching them may send).
            common.log_result(
                "planner_ready",
                robots=robots,
                node=common.node_name(),
                startup_s=round(time.monotonic() - STARTED, 2),
                pool_s=round(pool_s, 2),
            )

        def serve(self, robot: str) -> None:
            """Subscribe to a robot's scenes and requests, and publish its results."""
            self.scenes.setdefault(robot, {})
            self.results[robot] = self.create_publisher(
                JointTrajectory, common.topic(robot, common.PLAN_RESULT), common.reliable_qos()
            )
            self.wiring[robot] = [
                self.create_subscription(
                    MarkerArray, common.topic(robot, common.SCENE_OBJECTS), lambda m, r=robot: self.on_scene(r, m),
                    common.latched_qos(common.SCENE_HISTORY),
                ),
                self.create_subscription(
                    JointTrajectory, common.topic(robot, common.PLAN_REQUEST), lambda m, r=robot: self.on_request(r, m),
                    common.reliable_qos(50),
                ),
            ]  # fmt: skip

        def follow(self, listed: list[str]) -> None:
            """The robots file changed (or not): serve robots added, keep removed ones for the handover, then drop them."""
            now = time.monotonic()
            for robot in listed:
                if robot in self.lost:
                    del self.lost[robot]  # given back before its handover ended
                elif robot not in self.wiring:
                    self.serve(robot)
                    self.added[robot] = now
                    common.log_result("robot_added", robot=robot, node=common.node_name())
            for robot in [r for r in self.wiring if r not in listed and r not in self.lost]:
                self.lost[robot] = now
                common.log_result("robot_removed", robot=robot, node=common.node_name())
            for robot, since in list(self.lost.items()):
                if now - since >= self.handover_s:
                    for subscription in self.wiring.pop(robot):
                        self.destroy_subscription(subscription)
                    self.destroy_publisher(self.results.pop(robot))
                    del self.lost[robot]
                    self.scenes.pop(robot, None)

        def measure(self) -> None:
            now = time.monotonic()
            self.load.sample(now, self.requests.qsize() + self.busy)
            if metrics_file and int(now * 10) % 5 == 0:  # the file every 0.5 s
                write_atomically(metrics_file, self.load.exposition(len(self.wiring) - len(self.lost)))

        def on_scene(self, robot: str, msg) -> None:
            if not msg.markers:
                return
            scenes = self.scenes.setdefault(robot, {})
            key = common.scene_key(msg.markers[0].header.stamp)
            scenes[key] = boxes_from_markers(msg)
            while len(scenes) > self.history:
                scenes.pop(next(iter(scenes)))

        def mine(self, robot: str, msg) -> bool:
            """Whether this planner takes a request: always for its robots; for a robot it lost, only during the
            handover (until the new planner's subscription surely matched; a request both answer is answered twice,
            and the coordinator takes the first). What it took before is answered either way (drained)."""
            return robot not in self.lost or time.monotonic() - self.lost[robot] < self.handover_s

        def taking_over(self, robot: str) -> bool:
            return robot in self.added and time.monotonic() - self.added[robot] < self.handover_s

        def on_request(self, robot: str, msg) -> None:
            if not self.mine(robot, msg):
                return  # the robot's other planner answers it
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
                self.busy = 1
                try:
                    self.answer(robot, msg, arrived)
                finally:
                    self.busy = 0

        def answer(self, robot: str, msg, arrived: float) -> None:
            request_id, values = common.decode_tag(msg.header.frame_id)
            waited = time.monotonic() - arrived
            if len(msg.points) < 2:
                self.reply(robot, msg, None, "failed", reason="request needs a start and a goal point")
                return
            taking_over = self.taking_over(robot)  # a scene in flight arrives within 0.5 s; an older one never
            scene = self.wait_for_scene(robot, values.get("scene", ""), min(0.5, self.scene_wait) if taking_over else None)
            if scene is None and taking_over:
                return  # a scene from before this planner took the robot over: its previous planner answers
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

        def wait_for_scene(self, robot: str, key: str, wait: float | None = None):
            """The scene the request names; it may still be on its way here (perception publishes it to the
            coordinator and to this planner over different links), so wait up to `scene_wait` seconds."""
            deadline = time.monotonic() + (self.scene_wait if wait is None else wait)
            while (scene := self.scenes.get(robot, {}).get(key)) is None and time.monotonic() < deadline:
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
            publisher = self.results.get(robot)
            if publisher is None:
                return  # handed over and dropped meanwhile
            common.wait_for_subscriber(publisher, 5.0)
            publisher.publish(out)

        def on_shutdown(self) -> None:
            self.stop.set()
            self.worker.join(timeout=5)
            self.planner.close()

    common.spin(PlannerNode())


if __name__ == "__main__":
    main()
