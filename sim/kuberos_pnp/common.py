"""What every pick-and-place module shares: which robots it serves, its parameters, topic names, the request
and result convention, image conversion and the result log lines the evaluation reads.

The modules talk in standard ROS 2 message types only. Requests and results carry their bookkeeping in
`header.frame_id` as `<id>;key=value;...` (see `encode_tag`/`decode_tag`): the request id, which object the hand
holds, which planner won. Nothing here imports the physics or the planner, so every module can import it.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

RESULT_PREFIX = "KUBEROS_RESULT "

# Topic names, relative to a robot's namespace (see robot_namespace).
CAMERA_RGB = "head_camera/rgb"
CAMERA_DEPTH = "head_camera/depth"
CAMERA_INFO = "head_camera/camera_info"
CAMERA_POSE = "head_camera/pose"
JOINT_STATES = "joint_states"
ARM_TRAJECTORY = "arm_controller/joint_trajectory"
GRIPPER_COMMAND = "gripper/command"
SCENE_OBJECTS = "planning_scene/objects"
SCENE_POINTS = "perception/points"
PLAN_REQUEST = "plan/request"
PLAN_RESULT = "plan/result"
EXECUTE = "execute"
EXECUTE_RESULT = "execute/result"
GRIPPER_JOINT = "gripper"


def robot_namespace(robot: str) -> str:
    """`/fetch_1` for robot fetch-1: ROS names allow letters, digits and underscores only."""
    cleaned = "".join(c if c.isalnum() else "_" for c in robot)
    if not cleaned or cleaned[0].isdigit():
        cleaned = f"r_{cleaned}"
    return f"/{cleaned}"


def topic(robot: str, name: str) -> str:
    return f"{robot_namespace(robot)}/{name}"


def read_robots(path: str) -> list[str]:
    """The robots listed in a scaled module's robots file (comma separated; the file may be empty)."""
    try:
        with open(path, encoding="utf-8") as handle:
            return [r.strip() for r in handle.read().split(",") if r.strip()]
    except OSError:
        return []


def robots_from_env(environ=os.environ) -> list[str]:
    """The robots this instance serves: KUBEROS_ROBOTS (comma separated, set for every module instance by the
    rendered manifests), the file KUBEROS_ROBOTS_FILE names (a scaled module's, as it is now; modules that follow
    its changes read it again, see planner.py), else KUBEROS_ROBOT_NAME (a robot's own simulator)."""
    if environ.get("KUBEROS_ROBOTS_FILE"):
        return read_robots(environ["KUBEROS_ROBOTS_FILE"])
    listed = [r.strip() for r in environ.get("KUBEROS_ROBOTS", "").split(",") if r.strip()]
    if listed:
        return listed
    robot = environ.get("KUBEROS_ROBOT_NAME", "").strip()
    if not robot:
        raise SystemExit("neither KUBEROS_ROBOTS nor KUBEROS_ROBOT_NAME is set: which robots does this module serve?")
    return [robot]


def init_args(argv: list[str] | None = None, environ=os.environ) -> list[str]:
    """Arguments for rclpy.init: the command line, plus the rendered parameters file (the module's rosParameters,
    a ConfigMap mounted at KUBEROS_PARAMS_FILE) as `--params-file`, the way `ros2 run` passes one."""
    args = list(sys.argv if argv is None else argv)
    params = environ.get("KUBEROS_PARAMS_FILE", "")
    if params and os.path.isfile(params):
        if "--ros-args" not in args:
            args.append("--ros-args")
        args += ["--params-file", params]
    return args


def declare(node, name: str, default):
    """A parameter's value; any type given on the command line or in the params file is accepted (`-p rate:=12`
    for a float parameter), and converted to the default's type."""
    from rcl_interfaces.msg import ParameterDescriptor

    value = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True)).value
    return type(default)(value) if value is not None else default


def node_name() -> str:
    return os.environ.get("KUBEROS_NODE_NAME", "") or os.uname().nodename


def encode_tag(request_id: str, **values) -> str:
    """`id;key=value;...` for header.frame_id; values must not contain ';' or '='."""
    parts = [request_id] + [f"{k}={v}" for k, v in values.items() if v is not None and v != ""]
    return ";".join(parts)


def decode_tag(tag: str) -> tuple[str, dict[str, str]]:
    request_id, *rest = tag.split(";")
    values = {}
    for part in rest:
        key, _, value = part.partition("=")
        values[key] = value
    return request_id, values


def wait_for_subscriber(publisher, timeout: float) -> bool:
    """Wait until the publisher has matched a subscriber (a reliable message sent before the match is lost:
    discovery through the discovery servers takes a moment after a module starts)."""
    deadline = time.monotonic() + timeout
    while publisher.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def scene_key(stamp) -> str:
    """A planning scene's key: its camera frame's stamp, `sec.nanosec`."""
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def encode_names(names) -> str:
    return "+".join(names)


def decode_names(text: str | None) -> tuple[str, ...]:
    return tuple(n for n in (text or "").split("+") if n)


def encode_carry(carry) -> str | None:
    """A carried object (kuberos_pnp.planning.Attached) as `<box>|x,y,z|qx,qy,qz,qw|<ignored+boxes>`; the box
    itself is the planning scene's box of that name. Numbers are written exactly (repr of the float): the planner
    checks the carried box where the coordinator's IK did, not a rounded micrometre away."""
    if carry is None:
        return None
    position = ",".join(repr(float(v)) for v in carry.ee_position)
    quat = ",".join(repr(float(v)) for v in carry.ee_quat_xyzw)
    return f"{carry.box.name}|{position}|{quat}|{encode_names(carry.ignore)}"


def decode_carry(text: str | None):
    """(box name, position, quaternion, ignored names) of `encode_carry`, or None."""
    if not text:
        return None
    name, position, quat, ignore = text.split("|")
    return name, tuple(float(v) for v in position.split(",")), tuple(float(v) for v in quat.split(",")), decode_names(ignore)


def log_result(kind: str, **fields) -> None:
    """One line for the evaluation: `KUBEROS_RESULT {"kind": ..., "t": <unix time>, ...}` on stdout (the
    module's log, as `kubectl logs` would show it)."""
    record = {"kind": kind, "t": round(time.time(), 4), **fields}
    sys.stdout.write(RESULT_PREFIX + json.dumps(record, sort_keys=True, default=_plain) + "\n")
    sys.stdout.flush()


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON: {type(value).__name__}")


def read_results(text: str) -> list[dict]:
    """Every result record in a module's log."""
    records = []
    for line in text.splitlines():
        if line.startswith(RESULT_PREFIX):
            try:
                records.append(json.loads(line[len(RESULT_PREFIX) :]))
            except json.JSONDecodeError:
                continue  # a line cut off by a killed process
    return records


# --- images -----------------------------------------------------------------------------------------------


def image_msg(array: np.ndarray, encoding: str, stamp, frame_id: str):
    from sensor_msgs.msg import Image

    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(array.shape[0]), int(array.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    data = np.ascontiguousarray(array)
    msg.step = int(data.strides[0])
    msg.data = data.tobytes()
    return msg


def image_array(msg) -> np.ndarray:
    """An Image as a numpy array: rgb8 -> (h, w, 3) uint8, 32FC1 -> (h, w) float32."""
    if msg.encoding == "rgb8":
        return (
            np.frombuffer(bytes(msg.data), dtype=np.uint8)
            .reshape(msg.height, msg.step)[:, : msg.width * 3]
            .reshape(msg.height, msg.width, 3)
        )
    if msg.encoding == "32FC1":
        row = msg.step // 4
        return np.frombuffer(bytes(msg.data), dtype=np.float32).reshape(msg.height, row)[:, : msg.width]
    raise ValueError(f"unsupported image encoding {msg.encoding!r}")


def stamp_seconds(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def reliable_qos(depth: int = 10):
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


SCENE_HISTORY = 120  # planning scenes a late subscriber gets: about a minute at perception's 2 Hz


def latched_qos(depth: int = 1):
    """Reliable and transient local: a subscriber that joins later gets the last ``depth`` messages. Planning scenes
    keep ``SCENE_HISTORY``: a planner that takes a robot over mid-cycle (scaling) has the scene the cycle names."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def sensor_qos():
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


def spin(node) -> None:
    """Spin until Ctrl-C or SIGTERM (the kubelet's stop), then shut down quietly."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        closing = getattr(node, "on_shutdown", None)
        if closing:
            closing()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
