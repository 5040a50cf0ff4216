"""Perception: a robot's head camera (RGB-D) to a sparse point cloud and the collision objects of its planning
scene.

For every robot it serves (one when dedicated, several when shared) it subscribes to the robot's sensor
interface, and for each depth frame with its RGB frame: back-projects the depth into a sparse point cloud in
the robot frame (`perception/points`, sensor_msgs/PointCloud2, xyz float32), segments it into boxes and
publishes them as the planning scene's collision objects (`planning_scene/objects`,
visualization_msgs/MarkerArray of CUBE markers: `ns` = target/obstacle/table/platform, `text` = object name,
pose = box centre, scale = box size, header.stamp = the camera frame's stamp).

Parameters (the module's rosParameters): `voxel_size` (m), `stride` (pixels), `max_rate_hz` (frames per
second processed per robot; extra frames are dropped).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from kuberos_pnp import common, perception_core

KINDS = ("target", "obstacle", "table", "platform")


def scene_markers(boxes, stamp, frame_id: str = "base_link"):
    from visualization_msgs.msg import Marker, MarkerArray

    array = MarkerArray()
    for i, box in enumerate(boxes):
        m = Marker()
        m.header.stamp, m.header.frame_id = stamp, frame_id
        m.ns, m.id, m.type, m.action = box.kind, i, Marker.CUBE, Marker.ADD
        m.text = box.name
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in box.center)
        m.pose.orientation.w = 1.0
        m.scale.x, m.scale.y, m.scale.z = (float(v) for v in box.size)
        m.color.a = 1.0
        array.markers.append(m)
    return array


def boxes_from_markers(msg) -> list:
    """The collision objects of a scene message, as perception_core.Box."""
    return [
        perception_core.Box(
            name=m.text,
            kind=m.ns,
            center=(m.pose.position.x, m.pose.position.y, m.pose.position.z),
            size=(m.scale.x, m.scale.y, m.scale.z),
        )
        for m in msg.markers
        if m.ns in KINDS
    ]


def cloud_msg(points: np.ndarray, stamp, frame_id: str = "base_link"):
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    data = np.ascontiguousarray(points, dtype=np.float32)
    msg.height, msg.width = 1, int(data.shape[0])
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * int(data.shape[0]), True
    msg.data = data.tobytes()
    return msg


def main(argv: list[str] | None = None) -> None:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2
    from visualization_msgs.msg import MarkerArray

    robots = common.robots_from_env()
    rclpy.init(args=common.init_args(argv))

    class RobotInput:
        def __init__(self):
            self.rgb = None
            self.depth = None
            self.info = None
            self.pose = None
            self.last_processed = 0.0

    class PerceptionNode(Node):
        def __init__(self):
            super().__init__("perception")
            self.voxel = float(common.declare(self, "voxel_size", 0.01))
            self.stride = int(common.declare(self, "stride", 2))
            self.max_rate = float(common.declare(self, "max_rate_hz", 2.0))
            self.inputs = {r: RobotInput() for r in robots}
            self.pub_scene = {
                r: self.create_publisher(
                    MarkerArray, common.topic(r, common.SCENE_OBJECTS), common.latched_qos(common.SCENE_HISTORY)
                )
                for r in robots
            }
            self.pub_points = {
                r: self.create_publisher(PointCloud2, common.topic(r, common.SCENE_POINTS), common.sensor_qos()) for r in robots
            }
            self.lock = threading.Lock()
            for r in robots:
                self.create_subscription(
                    Image, common.topic(r, common.CAMERA_RGB), lambda m, r=r: self.on_rgb(r, m), common.sensor_qos()
                )
                self.create_subscription(
                    Image, common.topic(r, common.CAMERA_DEPTH), lambda m, r=r: self.on_depth(r, m), common.sensor_qos()
                )
                self.create_subscription(
                    CameraInfo,
                    common.topic(r, common.CAMERA_INFO),
                    lambda m, r=r: setattr(self.inputs[r], "info", m),
                    common.sensor_qos(),
                )
                self.create_subscription(
                    PoseStamped,
                    common.topic(r, common.CAMERA_POSE),
                    lambda m, r=r: setattr(self.inputs[r], "pose", m),
                    common.latched_qos(),
                )
            self.get_logger().info(f"perception for {', '.join(robots)} on {common.node_name()}")

        def on_rgb(self, robot: str, msg) -> None:
            self.inputs[robot].rgb = msg
            self.process(robot)

        def on_depth(self, robot: str, msg) -> None:
            self.inputs[robot].depth = msg
            self.process(robot)

        def process(self, robot: str) -> None:
            """Once the depth and the RGB image of one camera frame (the same stamp) are both here, whichever came
            second: both are needed (colour tells targets from obstacles), and they travel separately."""
            state = self.inputs[robot]
            depth_msg, rgb_msg = state.depth, state.rgb
            if depth_msg is None or rgb_msg is None or depth_msg.header.stamp != rgb_msg.header.stamp:
                return
            now = time.monotonic()
            if state.info is None or state.pose is None or now - state.last_processed < 1.0 / self.max_rate:
                return
            state.last_processed = now
            state.depth = None
            try:
                self.perceive(robot, state, depth_msg, rgb_msg)
            except Exception as error:  # a bad frame is skipped; perception keeps running
                common.log_result(
                    "perception_error", robot=robot, node=common.node_name(), error=f"{type(error).__name__}: {error}"
                )

        def perceive(self, robot: str, state, depth_msg, rgb_msg) -> None:
            started = time.perf_counter()
            k = np.asarray(state.info.k, float).reshape(3, 3)
            p, o = state.pose.pose.position, state.pose.pose.orientation
            points, colors = perception_core.depth_to_points(
                common.image_array(depth_msg),
                k,
                np.array([p.x, p.y, p.z]),
                np.array([o.x, o.y, o.z, o.w]),
                stride=self.stride,
                rgb=common.image_array(rgb_msg),
                voxel_size=self.voxel,
            )
            boxes = perception_core.segment(points, colors)
            self.pub_points[robot].publish(cloud_msg(points, depth_msg.header.stamp))
            self.pub_scene[robot].publish(scene_markers(boxes, depth_msg.header.stamp))
            common.log_result(
                "perception",
                robot=robot,
                node=common.node_name(),
                ms=round((time.perf_counter() - started) * 1000, 2),
                points=int(points.shape[0]),
                targets=sum(1 for b in boxes if b.kind == "target"),
            )

    common.spin(PerceptionNode())


if __name__ == "__main__":
    main()
