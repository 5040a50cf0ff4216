"""Task coordinator: generates the pick-and-place workload and records every request's latency and outcome.

For each robot it serves, tasks arrive at `tasks_per_minute` (a fixed interval; a task waits while the robot
is busy with the previous one). A task is one pick cycle: take a target from the robot's planning scene (as
perception sees it), then, step by step (kuberos_pnp.tasks): solve the step's goal pose to a joint goal,
send a planning request (`plan/request`) and wait for the path (`plan/result`), have the onboard controller
execute it (`execute`, `execute/result`), open or close the gripper. After the release it waits for a camera
frame taken after the release and checks that the object lies on the platform.

A robot's workload starts once it is ready: its planner and controller matched, its scene and joint states
arrived (`ready` record with the seconds each took; `waiting` every 30 s before; `idle` with `startup` if not
within `startup_timeout` from the coordinator's start). Each robot has its own IK solver (collision model and
random restarts, `ik_solvers`): the robots' task threads run at once.

Every planning request and every cycle is logged as a result record (kuberos_pnp.common.log_result):
`plan` (robot, latency_ms seen here, planner, planning_ms and node reported by the planner, ok) and `cycle`
(robot, queue_s, duration_s, plans, outcome, reason).

Parameters: `tasks_per_minute`, `max_cycles` (per robot; 0 = until no target is left), `plan_timeout`,
`execute_timeout`, `scene_timeout`, `startup_timeout` (s from the coordinator's start for a robot to become
ready: 8 planners starting on one 2-core host take more than a minute), `seed` (the IK restarts).
"""

from __future__ import annotations

import itertools
import threading
import time
import zlib

import numpy as np

from kuberos_pnp import common, planning, tasks, world
from kuberos_pnp.offline import choose_yaw
from kuberos_pnp.perception import boxes_from_markers


class Waiter:
    """Results by request id: the subscriber callback sets them, the robot's task thread waits for them."""

    def __init__(self):
        self.lock = threading.Lock()
        self.events: dict[str, threading.Event] = {}
        self.values: dict[str, object] = {}

    def expect(self, request_id: str) -> threading.Event:
        with self.lock:
            event = self.events[request_id] = threading.Event()
        return event

    def deliver(self, request_id: str, value) -> None:
        with self.lock:
            event = self.events.pop(request_id, None)
            if event is not None:
                self.values[request_id] = value
                event.set()

    def take(self, request_id: str, event: threading.Event, timeout: float):
        if not event.wait(timeout):
            with self.lock:
                self.events.pop(request_id, None)
            return None
        with self.lock:
            return self.values.pop(request_id)


def ik_solvers(robots: list[str], seed: int = 0) -> dict[str, planning.IkSolver]:
    """One IK solver per robot: each robot's task thread solves in its own scene with its own collision model and
    its own random restarts (seeded by the seed and the robot's name, so a robot's goals do not depend on which
    other robots share the coordinator or how their threads interleave)."""
    return {r: planning.IkSolver(seed=(seed * 1_000_003 + zlib.crc32(r.encode())) % 2**32) for r in robots}


class CycleFailed(Exception):
    pass


class SceneUnknown(CycleFailed):
    """The planner has not received the scene the cycle plans in (yet): the cycle starts again on a newer one."""


def main(argv: list[str] | None = None) -> None:
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    from visualization_msgs.msg import MarkerArray

    robots = common.robots_from_env()
    rclpy.init(args=common.init_args(argv))

    class RobotView:
        def __init__(self):
            # The latest planning scene as one tuple, replaced whole by the subscriber callback, so that a task thread
            # never reads the boxes of one scene with the key of another: (boxes, key, camera time of the scene).
            self.latest: tuple[list, str, float] = ([], "", 0.0)
            self.q: np.ndarray | None = None
            self.names: list[str] = []

        @property
        def scene_stamp(self) -> float:
            return self.latest[2]

    class CoordinatorNode(Node):
        def __init__(self):
            super().__init__("task_coordinator")
            self.rate = float(common.declare(self, "tasks_per_minute", 6.0))
            self.max_cycles = int(common.declare(self, "max_cycles", 0))
            self.plan_timeout = float(common.declare(self, "plan_timeout", 30.0))
            self.execute_timeout = float(common.declare(self, "execute_timeout", 30.0))
            self.scene_timeout = float(common.declare(self, "scene_timeout", 20.0))
            self.startup_timeout = float(common.declare(self, "startup_timeout", 600.0))
            self.started = time.monotonic()
            self.ik = ik_solvers(robots, int(common.declare(self, "seed", 0)))
            self.joint_names, _limits = world.arm_model()
            self.views = {r: RobotView() for r in robots}
            self.waiter = Waiter()
            self.ids = itertools.count(1)
            self.stop = threading.Event()
            self.pub_plan = {
                r: self.create_publisher(JointTrajectory, common.topic(r, common.PLAN_REQUEST), common.reliable_qos())
                for r in robots
            }
            self.pub_exec = {
                r: self.create_publisher(JointTrajectory, common.topic(r, common.EXECUTE), common.reliable_qos()) for r in robots
            }
            for r in robots:
                self.create_subscription(
                    MarkerArray, common.topic(r, common.SCENE_OBJECTS), lambda m, r=r: self.on_scene(r, m), common.latched_qos()
                )
                self.create_subscription(
                    JointState, common.topic(r, common.JOINT_STATES), lambda m, r=r: self.on_joints(r, m), common.sensor_qos()
                )
                self.create_subscription(
                    JointTrajectory, common.topic(r, common.PLAN_RESULT), self.on_plan_result, common.reliable_qos(50)
                )
                self.create_subscription(
                    Header, common.topic(r, common.EXECUTE_RESULT), self.on_execute_result, common.reliable_qos()
                )
            self.threads = [threading.Thread(target=self.run_robot, args=(r,), name=f"tasks-{r}", daemon=True) for r in robots]
            for t in self.threads:
                t.start()
            self.get_logger().info(f"coordinator for {', '.join(robots)} on {common.node_name()}: {self.rate} tasks/min each")

        # --- inputs
        def on_scene(self, robot, msg) -> None:
            if not msg.markers:
                return
            stamp = msg.markers[0].header.stamp
            self.views[robot].latest = (boxes_from_markers(msg), common.scene_key(stamp), common.stamp_seconds(stamp))

        def on_joints(self, robot, msg) -> None:
            view = self.views[robot]
            view.names, view.q = list(msg.name), np.asarray(msg.position, float)

        def on_plan_result(self, msg) -> None:
            request_id, _ = common.decode_tag(msg.header.frame_id)
            self.waiter.deliver(request_id, msg)

        def on_execute_result(self, msg) -> None:
            request_id, _ = common.decode_tag(msg.frame_id)
            self.waiter.deliver(request_id, msg)

        # --- helpers for one robot's thread
        def arm_q(self, robot) -> np.ndarray:
            view = self.views[robot]
            return np.asarray([view.q[view.names.index(n)] for n in self.joint_names], float)

        def wait_for(self, what, condition, timeout) -> None:
            deadline = time.monotonic() + timeout
            while not condition():
                if self.stop.is_set() or time.monotonic() > deadline:
                    raise CycleFailed(f"no {what} within {timeout:.0f} s")
                time.sleep(0.05)

        def request_id(self, robot) -> str:
            return f"{robot}/{next(self.ids)}"

        def plan(self, robot, goal_q, step, scene_key, cycle) -> list:
            request_id = self.request_id(robot)
            msg = JointTrajectory()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.header.frame_id = common.encode_tag(
                request_id, scene=scene_key, ignore=common.encode_names(step.ignore), carry=common.encode_carry(step.carry)
            )
            msg.joint_names = list(self.joint_names)
            msg.points = [
                JointTrajectoryPoint(positions=[float(x) for x in self.arm_q(robot)]),
                JointTrajectoryPoint(positions=[float(x) for x in goal_q]),
            ]
            if not common.wait_for_subscriber(self.pub_plan[robot], self.plan_timeout):
                raise CycleFailed(f"planning {step.name}: no motion planner subscribed to {self.pub_plan[robot].topic_name}")
            event = self.waiter.expect(request_id)
            sent = time.monotonic()
            self.pub_plan[robot].publish(msg)
            reply = self.waiter.take(request_id, event, self.plan_timeout)
            latency = (time.monotonic() - sent) * 1000
            values = common.decode_tag(reply.header.frame_id)[1] if reply is not None else {}
            ok = reply is not None and values.get("status") == "ok" and len(reply.points) > 0
            common.log_result(
                "plan",
                robot=robot,
                request=request_id,
                cycle=cycle,
                step=step.name,
                ok=ok,
                latency_ms=round(latency, 1),
                planner=values.get("planner"),
                planning_ms=float(values["planning_ms"]) if "planning_ms" in values else None,
                queue_ms=float(values["queue_ms"]) if "queue_ms" in values else None,
                planner_node=values.get("node"),
                node=common.node_name(),
                reason=values.get("reason") or (None if reply is not None else "timeout"),
            )
            if not ok and (values.get("reason") or "").startswith("unknown scene"):
                raise SceneUnknown(f"planning {step.name}: {values['reason']}")
            if not ok:
                raise CycleFailed(f"planning {step.name}: {values.get('reason') or 'no answer within the timeout'}")
            return reply

        def execute(self, robot, msg, step) -> None:
            request_id = self.request_id(robot)
            msg.header.frame_id = common.encode_tag(request_id)
            if not common.wait_for_subscriber(self.pub_exec[robot], self.execute_timeout):
                raise CycleFailed(f"executing {step}: no controller subscribed to {self.pub_exec[robot].topic_name}")
            event = self.waiter.expect(request_id)
            self.pub_exec[robot].publish(msg)
            reply = self.waiter.take(request_id, event, self.execute_timeout)
            if reply is None:
                raise CycleFailed(f"executing {step}: no answer from the controller")
            values = common.decode_tag(reply.frame_id)[1]
            if values.get("status") != "ok":
                raise CycleFailed(f"executing {step}: {values.get('reason')}")

        def grip(self, robot, close: bool, step) -> None:
            msg = JointTrajectory()
            msg.joint_names = [common.GRIPPER_JOINT]
            msg.points = [JointTrajectoryPoint(positions=[1.0 if close else 0.0])]
            self.execute(robot, msg, step)

        def fresh_scene(self, robot, after: float, timeout: float | None = None) -> tuple[list, str]:
            """The first planning scene from a camera frame taken after `after` (wall clock), and its key."""
            view = self.views[robot]
            self.wait_for(
                "camera frame after the last motion",
                lambda: view.scene_stamp > after and view.q is not None,
                timeout or self.scene_timeout,
            )
            boxes, key, _stamp = view.latest
            return list(boxes), key

        def wait_until_ready(self, robot) -> bool:
            """Until the robot's motion planner and controller are matched (their subscriptions exist once they are
            ready: a planner subscribes after its worker processes started) and its scene and joint states arrive,
            at most `startup_timeout` seconds from the coordinator's start. Logs `ready` with the seconds each took,
            or `idle` with what was missing; while waiting, a `waiting` record every 30 s with what is missing and
            whether discovery has at least announced the missing subscription (matched or only discovered)."""
            view = self.views[robot]
            checks = {
                "planner": lambda: self.pub_plan[robot].get_subscription_count() > 0,
                "controller": lambda: self.pub_exec[robot].get_subscription_count() > 0,
                "scene": lambda: view.scene_stamp > 0,
                "joint_states": lambda: view.q is not None,
            }
            since: dict[str, float] = {}
            next_report = self.started + 30.0
            while True:
                now = time.monotonic()
                for name, ok in checks.items():
                    if name not in since and ok():
                        since[name] = round(now - self.started, 1)
                missing = [name for name in checks if name not in since]
                if not missing:
                    common.log_result("ready", robot=robot, node=common.node_name(), **{f"{k}_s": v for k, v in since.items()})
                    return True
                if self.stop.is_set() or now - self.started > self.startup_timeout:
                    common.log_result(
                        "idle",
                        robot=robot,
                        cycle=0,
                        startup=True,
                        reason=f"not ready within {self.startup_timeout:.0f} s: no {', no '.join(missing)}",
                        **{f"{k}_s": v for k, v in since.items()},
                    )
                    return False
                if now >= next_report:
                    next_report += 30.0
                    common.log_result(
                        "waiting",
                        robot=robot,
                        node=common.node_name(),
                        after_s=round(now - self.started, 1),
                        missing=missing,
                        discovered_planners=self.count_subscribers(self.pub_plan[robot].topic_name),
                        discovered_controllers=self.count_subscribers(self.pub_exec[robot].topic_name),
                    )
                time.sleep(0.1)

        # --- the workload
        def run_robot(self, robot) -> None:
            interval = 60.0 / self.rate if self.rate > 0 else 0.0
            # The workload starts once the robot's planner and controller are ready; the first scene is one the
            # planner had a chance to receive too (it plans in the scene a request names).
            if not self.wait_until_ready(robot):
                return
            settled_after = time.time() + 1.0
            next_arrival = time.monotonic()
            key = ""  # the scene the latest cycle planned in; a failed cycle goes home in it
            for cycle in itertools.count(1):
                if self.stop.is_set() or (self.max_cycles and cycle > self.max_cycles):
                    break
                while time.monotonic() < next_arrival and not self.stop.is_set():
                    time.sleep(0.05)
                arrival, next_arrival = next_arrival, next_arrival + interval
                started = time.monotonic()
                record = {"robot": robot, "cycle": cycle, "node": common.node_name(), "queue_s": round(started - arrival, 3)}
                try:
                    scene, key = self.fresh_scene(robot, settled_after, self.startup_timeout if cycle == 1 else None)
                    targets = tasks.remaining_targets(scene)
                    if not targets:
                        common.log_result("idle", robot=robot, cycle=cycle, reason="no target left on the table")
                        break
                    before = tasks.count_on_platform(scene)
                    record["object"] = targets[0].name
                    for attempt in range(3):
                        try:
                            record["plans"] = self.pick(robot, targets[0], scene, key, before, cycle)
                            break
                        except SceneUnknown as unknown:
                            # Nothing has moved yet (it is the cycle's first request): start over on a newer scene.
                            common.log_result("scene_retry", robot=robot, cycle=cycle, attempt=attempt + 1, reason=str(unknown))
                            if attempt == 2:
                                raise
                            scene, key = self.fresh_scene(robot, time.time())
                    settled_after = time.time()
                    after = tasks.count_on_platform(self.fresh_scene(robot, settled_after)[0])
                    record["outcome"] = "success" if after > before else "failed"
                    if after <= before:
                        record["reason"] = "perception sees no new object on the platform after the release"
                except Exception as failure:
                    reason = str(failure) if isinstance(failure, CycleFailed) else f"{type(failure).__name__}: {failure}"
                    record.update(outcome="failed", reason=reason)
                    self.recover(robot, key, cycle)
                    settled_after = time.time()
                record["duration_s"] = round(time.monotonic() - started, 3)
                common.log_result("cycle", **record)

        def pick(self, robot, target, scene, key, slot, cycle) -> int:
            """One pick cycle in the scene `key` (taken with the arm home): the steps of kuberos_pnp.tasks."""
            platform = tasks.platform_of(scene)
            if platform is None:
                raise CycleFailed("perception sees no platform")
            yaw, pregrasp_q = choose_yaw(self.ik[robot], target, self.arm_q(robot), scene)
            if pregrasp_q is None:
                raise CycleFailed(f"no grasp of {target.name} reachable from above")
            goals: dict[str, np.ndarray] = {"pregrasp": np.asarray(pregrasp_q)}
            plans = 0
            for step in tasks.pick_cycle_steps(target, platform, slot, yaw):
                if step.kind == "gripper":
                    self.grip(robot, bool(step.close_gripper), step.name)
                    continue
                goal = goals.get(step.name) if step.name == "pregrasp" else step.joint_goal
                if goal is None:
                    seed = goals.get(step.ik_seed_from, self.arm_q(robot))
                    goal = self.ik[robot].ik(step.pose[0], step.pose[1], seed, scene, step.ignore, step.carry)
                    if goal is None:
                        raise CycleFailed(f"no collision-free inverse kinematics for {step.name}")
                try:
                    reply = self.plan(robot, goal, step, key, cycle)
                except SceneUnknown as unknown:
                    if plans:  # the arm has moved: not a cycle to start over
                        raise CycleFailed(str(unknown)) from None
                    raise
                plans += 1
                self.execute(robot, reply, step.name)
                goals[step.name] = np.asarray(reply.points[-1].positions)
            return plans

        def recover(self, robot, key, cycle) -> None:
            """After a failed cycle: open the gripper and go home, best effort."""
            try:
                self.grip(robot, False, "recover")
                if key:
                    home = tasks.Step("recover-home", "move", joint_goal=tuple(tasks.home_q))
                    self.execute(robot, self.plan(robot, home.joint_goal, home, key, cycle), home.name)
            except CycleFailed:
                pass

        def on_shutdown(self) -> None:
            self.stop.set()
            for t in self.threads:
                t.join(timeout=2)

    common.spin(CoordinatorNode())


if __name__ == "__main__":
    main()
