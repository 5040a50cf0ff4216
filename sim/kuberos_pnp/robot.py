"""A simulated mobile manipulator: the PyBullet world of one robot behind its two ROS 2 interfaces.

- Sensor interface: the head camera's RGB (`head_camera/rgb`, rgb8), depth (`head_camera/depth`, 32FC1 metres),
  `head_camera/camera_info` and the camera's pose in the robot frame (`head_camera/pose`, latched).
- Control interface: `joint_states` out (the 7 arm joints and the gripper); a timed
  `arm_controller/joint_trajectory` and `gripper/command` (std_msgs/Bool, true = close) in.

Physics runs in real time: a timer steps the world until its simulated time has caught up with the wall clock
since start (at most `max_catch_up_steps` per tick). When the machine cannot keep up the simulation falls
behind, and the real-time factor it logs every `report_period_s` drops below 1. The physics is the robot's
hardware, not a module: the simulation runtime starts it on the robot's host outside the robot computer's CPU
limit. Ground truth (how many objects lie on the platform) is logged as a result record for the evaluation.

Run: `python -m kuberos_pnp.robot` with KUBEROS_ROBOT_NAME set; parameters `seed`, `objects`, `camera_rate_hz`,
`joint_state_rate_hz`, `physics_rate_hz`, `max_catch_up_steps`, `report_period_s`.
"""

from __future__ import annotations

import time
import zlib

import numpy as np

from kuberos_pnp import common
from kuberos_pnp.world import RobotWorld


class TrajectoryFollower:
    """Linear interpolation of a timed joint trajectory, in simulated time."""

    def __init__(self):
        self.times: np.ndarray | None = None
        self.positions: np.ndarray | None = None
        self.start = 0.0

    def load(self, times: list[float], positions: list[list[float]], now: float) -> None:
        if len(times) != len(positions) or not times:
            return
        self.times, self.positions, self.start = np.asarray(times, float), np.asarray(positions, float), now

    def target(self, now: float) -> np.ndarray | None:
        if self.times is None:
            return None
        t = now - self.start
        if t >= self.times[-1]:
            return self.positions[-1]
        i = int(np.searchsorted(self.times, t, side="right"))
        if i == 0:
            return self.positions[0]
        t0, t1 = self.times[i - 1], self.times[i]
        w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        return (1 - w) * self.positions[i - 1] + w * self.positions[i]


def robot_seed(robot: str, seed: int) -> int:
    """Each robot of a fleet gets its own scene; the same robot name and seed always give the same one."""
    return (seed * 1_000_003 + zlib.crc32(robot.encode())) % (2**31)


def main(argv: list[str] | None = None) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, JointState
    from std_msgs.msg import Bool
    from trajectory_msgs.msg import JointTrajectory

    (robot,) = common.robots_from_env()[:1]
    rclpy.init(args=common.init_args(argv))

    class RobotNode(Node):
        def __init__(self):
            super().__init__("robot_sim", namespace=common.robot_namespace(robot))
            p = {
                "seed": common.declare(self, "seed", 1),
                "objects": common.declare(self, "objects", 3),
                "camera_rate_hz": common.declare(self, "camera_rate_hz", 2.0),
                "joint_state_rate_hz": common.declare(self, "joint_state_rate_hz", 30.0),
                "physics_rate_hz": common.declare(self, "physics_rate_hz", 60.0),
                "max_catch_up_steps": common.declare(self, "max_catch_up_steps", 24),
                "report_period_s": common.declare(self, "report_period_s", 5.0),
            }
            self.params = p
            self.world = RobotWorld(seed=robot_seed(robot, int(p["seed"])), n_objects=int(p["objects"]))
            self.follower = TrajectoryFollower()
            self.wall_start = time.monotonic()
            self.sim_start = self.world.sim_time
            self.last_report = self.wall_start
            self.camera_ms: list[float] = []

            self.pub_rgb = self.create_publisher(Image, common.CAMERA_RGB, common.sensor_qos())
            self.pub_depth = self.create_publisher(Image, common.CAMERA_DEPTH, common.sensor_qos())
            self.pub_info = self.create_publisher(CameraInfo, common.CAMERA_INFO, common.sensor_qos())
            self.pub_pose = self.create_publisher(PoseStamped, common.CAMERA_POSE, common.latched_qos())
            self.pub_joints = self.create_publisher(JointState, common.JOINT_STATES, common.sensor_qos())
            self.create_subscription(JointTrajectory, common.ARM_TRAJECTORY, self.on_trajectory, common.reliable_qos())
            self.create_subscription(Bool, common.GRIPPER_COMMAND, self.on_gripper, common.reliable_qos())
            self.create_timer(1.0 / float(p["physics_rate_hz"]), self.on_physics)
            self.create_timer(1.0 / float(p["joint_state_rate_hz"]), self.on_joint_states)
            self.create_timer(1.0 / float(p["camera_rate_hz"]), self.on_camera)
            self.get_logger().info(
                f"robot {robot}: {len(self.world.joint_names)} arm joints, seed {p['seed']}, {p['objects']} objects"
            )

        # --- control interface
        def on_trajectory(self, msg: JointTrajectory) -> None:
            order = [msg.joint_names.index(n) for n in self.world.joint_names] if msg.joint_names else None
            if order is None or len(order) != len(self.world.joint_names):
                self.get_logger().warning("trajectory without the arm's joint names: ignored")
                return
            times = [pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9 for pt in msg.points]
            positions = [[pt.positions[i] for i in order] for pt in msg.points]
            self.follower.load(times, positions, self.world.sim_time)

        def on_gripper(self, msg: Bool) -> None:
            grasped = self.world.set_gripper(bool(msg.data))
            self.get_logger().info(f"gripper {'close' if msg.data else 'open'}: holding={grasped}")

        def on_physics(self) -> None:
            target = self.sim_start + (time.monotonic() - self.wall_start)
            steps = 0
            while self.world.sim_time < target and steps < int(self.params["max_catch_up_steps"]):
                q = self.follower.target(self.world.sim_time)
                if q is not None:
                    self.world.set_joint_targets(q)
                self.world.step()
                steps += 1
            now = time.monotonic()
            if now - self.last_report >= float(self.params["report_period_s"]):
                self.last_report = now
                self.report()

        def report(self) -> None:
            wall = time.monotonic() - self.wall_start
            sim = self.world.sim_time - self.sim_start
            common.log_result(
                "sim",
                robot=robot,
                node=common.node_name(),
                sim_time=round(sim, 3),
                wall_time=round(wall, 3),
                rtf=round(sim / wall, 4) if wall > 0 else None,
                on_platform=self.world.objects_on_platform(),
                objects=int(self.params["objects"]),
                camera_ms_p50=round(float(np.median(self.camera_ms)), 2) if self.camera_ms else None,
            )

        def on_joint_states(self) -> None:
            msg = JointState()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.name = [*self.world.joint_names, common.GRIPPER_JOINT]
            msg.position = [float(x) for x in self.world.joint_positions()] + [1.0 if self.world.grasped() else 0.0]
            msg.velocity = [float(x) for x in self.world.joint_velocities()] + [0.0]
            self.pub_joints.publish(msg)

        # --- sensor interface
        def on_camera(self) -> None:
            started = time.perf_counter()
            frame = self.world.camera()
            self.camera_ms.append((time.perf_counter() - started) * 1000)
            self.camera_ms = self.camera_ms[-200:]
            stamp = self.get_clock().now().to_msg()
            frame_id = "head_camera_optical"
            self.pub_rgb.publish(common.image_msg(frame.rgb, "rgb8", stamp, frame_id))
            self.pub_depth.publish(common.image_msg(frame.depth.astype(np.float32), "32FC1", stamp, frame_id))
            info = CameraInfo()
            info.header.stamp, info.header.frame_id = stamp, frame_id
            info.width, info.height = int(frame.width), int(frame.height)
            info.k = [float(x) for x in np.asarray(frame.K, float).reshape(9)]
            info.distortion_model = "plumb_bob"
            info.d = [0.0] * 5
            info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            k = np.asarray(frame.K, float)
            info.p = [k[0, 0], 0.0, k[0, 2], 0.0, 0.0, k[1, 1], k[1, 2], 0.0, 0.0, 0.0, 1.0, 0.0]
            self.pub_info.publish(info)
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = stamp, "base_link"
            (pose.pose.position.x, pose.pose.position.y, pose.pose.position.z) = [float(v) for v in frame.position]
            (
                pose.pose.orientation.x,
                pose.pose.orientation.y,
                pose.pose.orientation.z,
                pose.pose.orientation.w,
            ) = [float(v) for v in frame.quat_xyzw]
            self.pub_pose.publish(pose)

        def on_shutdown(self) -> None:
            self.report()
            self.world.close()

    common.spin(RobotNode())


if __name__ == "__main__":
    main()
