"""Trajectory and control, onboard: times planned paths and drives the robot's control interface.

`execute` (trajectory_msgs/JointTrajectory, `header.frame_id` = `<id>`) is either an arm path (the arm's
joint names, waypoints without times) or a gripper goal (`joint_names` = [gripper], one point: 1 closes,
0 opens). An arm path is time-parameterised time-optimally within the joints' velocity and acceleration
limits (toppra, kuberos_pnp.trajectory) and sent to the robot as a timed `arm_controller/joint_trajectory`;
the controller then watches `joint_states` until the arm has settled at the last waypoint. A gripper goal
goes to `gripper/command`. Either way the outcome goes back on `execute/result` (std_msgs/Header,
`frame_id` = `<id>;status=ok|failed;duration_ms=...;reason=...`).

Parameters: `velocity_scale`, `acceleration_scale` (fractions of the limits), `goal_tolerance` (rad),
`settle_timeout` (s beyond the trajectory's duration), `gripper_settle` (s).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from kuberos_pnp import common, trajectory, world


def main(argv: list[str] | None = None) -> None:
    import rclpy
    from builtin_interfaces.msg import Duration
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool, Header
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    robots = common.robots_from_env()
    rclpy.init(args=common.init_args(argv))

    class RobotState:
        def __init__(self):
            self.names: list[str] = []
            self.q: np.ndarray | None = None
            self.qd: np.ndarray | None = None
            self.busy = threading.Lock()

    class ControlNode(Node):
        def __init__(self):
            super().__init__("controller")
            self.v_scale = float(common.declare(self, "velocity_scale", 1.0))
            self.a_scale = float(common.declare(self, "acceleration_scale", 1.0))
            self.tolerance = float(common.declare(self, "goal_tolerance", 0.02))
            self.settle_timeout = float(common.declare(self, "settle_timeout", 3.0))
            self.gripper_settle = float(common.declare(self, "gripper_settle", 0.3))
            _names, self.limits = world.arm_model()
            self.state = {r: RobotState() for r in robots}
            self.pub_traj = {
                r: self.create_publisher(JointTrajectory, common.topic(r, common.ARM_TRAJECTORY), common.reliable_qos())
                for r in robots
            }
            self.pub_grip = {
                r: self.create_publisher(Bool, common.topic(r, common.GRIPPER_COMMAND), common.reliable_qos()) for r in robots
            }
            self.pub_done = {
                r: self.create_publisher(Header, common.topic(r, common.EXECUTE_RESULT), common.reliable_qos()) for r in robots
            }
            for r in robots:
                self.create_subscription(
                    JointState, common.topic(r, common.JOINT_STATES), lambda m, r=r: self.on_joints(r, m), common.sensor_qos()
                )
                self.create_subscription(
                    JointTrajectory, common.topic(r, common.EXECUTE), lambda m, r=r: self.on_execute(r, m), common.reliable_qos()
                )
            self.get_logger().info(f"controller for {', '.join(robots)} on {common.node_name()}")

        def on_joints(self, robot: str, msg) -> None:
            s = self.state[robot]
            s.names, s.q, s.qd = list(msg.name), np.asarray(msg.position, float), np.asarray(msg.velocity, float)

        def on_execute(self, robot: str, msg) -> None:
            # Execution waits for the arm; a thread per goal keeps the executor free for joint states.
            threading.Thread(target=self.execute, args=(robot, msg), daemon=True).start()

        def execute(self, robot: str, msg) -> None:
            request_id, _ = common.decode_tag(msg.header.frame_id)
            started = time.monotonic()
            with self.state[robot].busy:
                try:
                    if list(msg.joint_names) == [common.GRIPPER_JOINT]:
                        status, reason = self.gripper(robot, msg)
                    else:
                        status, reason = self.arm(robot, msg)
                except Exception as error:  # a bad goal must not take the controller down
                    status, reason = "failed", f"{type(error).__name__}: {error}"
            done = Header()
            done.stamp = msg.header.stamp
            clean = (reason or "").replace(";", ",").replace("=", ":")
            done.frame_id = common.encode_tag(
                request_id, status=status, duration_ms=round((time.monotonic() - started) * 1000), reason=clean
            )
            common.wait_for_subscriber(self.pub_done[robot], self.settle_timeout)
            self.pub_done[robot].publish(done)

        def gripper(self, robot: str, msg):
            close = bool(msg.points and msg.points[0].positions and msg.points[0].positions[0] > 0.5)
            if not common.wait_for_subscriber(self.pub_grip[robot], self.settle_timeout):
                return "failed", "the robot does not subscribe to its gripper topic"
            self.pub_grip[robot].publish(Bool(data=close))
            time.sleep(self.gripper_settle)
            return "ok", None

        def arm(self, robot: str, msg):
            s = self.state[robot]
            if s.q is None:
                return "failed", "no joint states from the robot yet"
            index = [s.names.index(n) for n in msg.joint_names]
            path = np.asarray([p.positions for p in msg.points], float)
            if path.ndim != 2 or path.shape[0] < 1 or path.shape[1] != len(index):
                return "failed", "path does not match its joint names"
            path = np.vstack([s.q[index], path])  # from where the arm is now
            timed = trajectory.time_parameterize(
                path, self.limits.velocity * self.v_scale, self.limits.acceleration * self.a_scale
            )
            common.log_result(
                "trajectory",
                robot=robot,
                method=timed.method,
                compute_ms=round(timed.compute_ms, 2),
                duration_s=round(float(timed.times[-1]), 3),
            )
            out = JointTrajectory()
            out.joint_names = list(msg.joint_names)
            for t, q, qd in zip(timed.times, timed.positions, timed.velocities, strict=True):
                out.points.append(
                    JointTrajectoryPoint(
                        positions=[float(x) for x in q],
                        velocities=[float(x) for x in qd],
                        time_from_start=Duration(sec=int(t), nanosec=int((t - int(t)) * 1e9)),
                    )
                )
            if not common.wait_for_subscriber(self.pub_traj[robot], self.settle_timeout):
                return "failed", "the robot does not subscribe to its trajectory topic"
            self.pub_traj[robot].publish(out)
            # Trajectories run in simulated time; a simulation behind the wall clock needs longer (down to half speed).
            deadline = time.monotonic() + 2 * float(timed.times[-1]) + self.settle_timeout
            goal = path[-1]
            while time.monotonic() < deadline:
                time.sleep(0.02)
                if s.q is not None and np.max(np.abs(s.q[index] - goal)) < self.tolerance:
                    return "ok", None
            error = float(np.max(np.abs(s.q[index] - goal)))
            return "failed", f"arm did not reach the goal ({error:.3f} rad off)"

    common.spin(ControlNode())


if __name__ == "__main__":
    main()
