"""One robot's simulated world in PyBullet (``p.DIRECT``), deterministic for a given seed.

The robot is a Clearpath Husky base (fixed: it stays still during manipulation) carrying a Franka Panda
arm loaded with a fixed base on the top plate, both from ``pybullet_data``. In front stands a table (a box)
with ``n_objects`` red 5 cm target cubes at seeded random positions, one tall blue obstacle between the
cubes and a green drop-off platform (a flat box) on the table.

Frames and units: everything is in the robot base frame, which is the world frame of this simulation
(x forward, y left, z up, metres, radians, quaternions xyzw). Simulated time is ``time_step`` per
``step()``; nothing here depends on wall time.

Grasping: closing the gripper attaches the target cube lying between the fingers (within
``GRASP_CAPTURE_RADIUS`` of the grasp point) to the hand with a fixed constraint, and opening releases
it. Friction grasps in PyBullet are too flaky for a >=95% success target, so this is deliberate.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import pybullet as p
import pybullet_data
from pybullet_utils import bullet_client

# --- fixed scene geometry (robot frame, metres) -------------------------------------------------------
CHASSIS_CENTER = (0.0, 0.0, 0.27)
CHASSIS_SIZE = (1.01, 0.58, 0.27)
ARM_BASE_POSITION = (0.25, 0.0, 0.405)
ARM_BASE_QUAT = (0.0, 0.0, 0.0, 1.0)
TABLE_CENTER = (0.85, 0.0, 0.20)
TABLE_SIZE = (0.60, 1.10, 0.40)
TABLE_TOP = TABLE_CENTER[2] + TABLE_SIZE[2] / 2
CUBE_SIZE = 0.05
CUBE_MASS = 0.05
CUBE_REGION = ((0.58, 0.80), (-0.32, 0.04))  # (x range, y range) of target cube centres
OBSTACLE_SIZE = (0.06, 0.06, 0.25)
OBSTACLE_REGION = ((0.62, 0.76), (0.12, 0.16))
PLATFORM_CENTER = (0.66, 0.37, TABLE_TOP + 0.01)
PLATFORM_SIZE = (0.20, 0.20, 0.02)
PLATFORM_TOP = PLATFORM_CENTER[2] + PLATFORM_SIZE[2] / 2
MIN_CUBE_SPACING = 0.12  # centre to centre, so open fingers never touch a neighbour
MIN_OBSTACLE_CLEARANCE = 0.13

RED = (0.85, 0.1, 0.1, 1.0)
BLUE = (0.15, 0.25, 0.8, 1.0)
GREEN = (0.2, 0.7, 0.25, 1.0)
TABLE_COLOR = (0.72, 0.62, 0.48, 1.0)

# --- arm -----------------------------------------------------------------------------------------------
PANDA_URDF = "franka_panda/panda.urdf"
ARM_JOINTS = (0, 1, 2, 3, 4, 5, 6)
FINGER_JOINTS = (9, 10)
HAND_LINK = 8
EE_LINK = 11  # panda_grasptarget: between the finger pads, 11.5 mm above the fingertips
FINGERTIP_BELOW_EE = 0.0115
ARM_FORCES = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
ARM_ACCEL_LIMIT = 4.0  # rad/s^2, chosen (the real Panda allows 7.5-20); used by trajectory generation
HOME_Q = (0.0, -1.7, 0.0, -3.0, 0.0, 1.5, 0.785)  # folded back: the hand stays off the table in the camera view
FINGER_OPEN = 0.04
GRASP_CAPTURE_RADIUS = 0.035

# --- head camera ---------------------------------------------------------------------------------------
CAMERA_EYE = (0.30, 0.0, 1.45)  # on a (virtual, collision-free) mast above the base
CAMERA_TARGET = (0.78, 0.0, 0.40)
CAMERA_UP = (0.0, 0.0, 1.0)
CAMERA_FOV_DEG = 60.0  # vertical
CAMERA_NEAR = 0.1
CAMERA_FAR = 3.0
CAMERA_WIDTH = 160
CAMERA_HEIGHT = 120


@dataclass(frozen=True)
class JointLimits:
    """Arm joint limits: positions (rad), max velocity (rad/s) and the acceleration limit (rad/s^2)."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


@dataclass(frozen=True)
class ObjectState:
    """Ground truth of one scene object in the robot frame."""

    name: str
    kind: str  # 'target' | 'obstacle' | 'platform' | 'table'
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    size: tuple[float, float, float]


@dataclass
class CameraFrame:
    """One RGB-D image.

    ``depth`` is the metric z-distance along the optical axis (float32, metres; ``far`` where nothing
    was hit). ``K`` uses pixel-index coordinates: the centre of pixel (u=col, v=row) is (u, v), so a
    point (x, y, z) in the optical frame projects to u = fx*x/z + cx, v = fy*y/z + cy.
    ``position``/``quat_xyzw`` give the optical frame in the robot frame; optical frame convention:
    x right, y down, z forward (REP 103 ``_optical_frame``).
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    width: int
    height: int
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    near: float
    far: float
    sim_time: float
    segmentation: np.ndarray | None = field(default=None, repr=False)


def camera_intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole K matching PyBullet's projection matrix (vertical fov, square pixels).

    The principal point is in pixel-index coordinates. ER_TINY_RENDERER samples pixels at integer
    viewport coordinates with rows flipped, so pixel (u, v) sees continuous image point (u, v + 1):
    hence cx = W/2 and cy = H/2 - 1 (measured against the table plane: residual bias < 1 mm).
    """
    fy = (height / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[fy, 0.0, width / 2.0], [0.0, fy, height / 2.0 - 1.0], [0.0, 0.0, 1.0]])


def optical_frame(eye, target, up) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (columns x right, y down, z forward) and position of a look-at camera."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z]), np.asarray(eye, float)


def rotation_to_quat(rot: np.ndarray) -> tuple[float, float, float, float]:
    """3x3 rotation matrix to a quaternion xyzw."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(rot).as_quat()
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def depth_from_zbuffer(zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
    """OpenGL z-buffer values in [0, 1] to metric depth along the optical axis."""
    zbuf = np.asarray(zbuf, dtype=np.float64)
    return (far * near / (far - (far - near) * zbuf)).astype(np.float32)


def sample_layout(seed: int, n_objects: int) -> tuple[list[tuple[float, float]], tuple[float, float]]:
    """Seeded cube xy positions (non-overlapping, clear of the obstacle) and the obstacle xy."""
    rng = np.random.default_rng(seed)
    obstacle = (float(rng.uniform(*OBSTACLE_REGION[0])), float(rng.uniform(*OBSTACLE_REGION[1])))
    cubes: list[tuple[float, float]] = []
    for _ in range(10000):
        if len(cubes) == n_objects:
            break
        xy = (float(rng.uniform(*CUBE_REGION[0])), float(rng.uniform(*CUBE_REGION[1])))
        if math.dist(xy, obstacle) < MIN_OBSTACLE_CLEARANCE:
            continue
        if all(math.dist(xy, c) >= MIN_CUBE_SPACING for c in cubes):
            cubes.append(xy)
    if len(cubes) != n_objects:
        raise ValueError(f"cannot place {n_objects} cubes without overlap")
    return cubes, obstacle


class RobotWorld:
    """The simulated world of one robot. Not thread-safe; one PyBullet client per instance."""

    def __init__(self, seed: int, n_objects: int = 3, time_step: float = 1.0 / 240.0) -> None:
        if not 1 <= n_objects <= 4:
            raise ValueError("n_objects must be 1..4")
        self.seed = seed
        self.time_step = time_step
        self.sim_time = 0.0
        self._p = bullet_client.BulletClient(connection_mode=p.DIRECT)
        self._p.setAdditionalSearchPath(pybullet_data.getDataPath())
        self._p.setPhysicsEngineParameter(fixedTimeStep=time_step, numSolverIterations=100, deterministicOverlappingPairs=1)
        self._p.setGravity(0, 0, -9.81)
        self._attachment: tuple[int, str] | None = None  # (constraint id, object name)
        self._gripper_closed = False
        self._objects: dict[str, tuple[int, str, tuple[float, float, float]]] = {}  # name -> (body, kind, size)
        self._build_robot()
        self._build_scene(seed, n_objects)
        self.step(60)  # let the cubes settle
        self.sim_time = 0.0
        self._camera_rot, self._camera_pos = optical_frame(CAMERA_EYE, CAMERA_TARGET, CAMERA_UP)
        self.K = camera_intrinsics(CAMERA_WIDTH, CAMERA_HEIGHT, CAMERA_FOV_DEG)

    # --- construction ----------------------------------------------------------------------------------
    def _build_robot(self) -> None:
        pb = self._p
        pb.loadURDF("plane.urdf")
        self.base_id = pb.loadURDF("husky/husky.urdf", useFixedBase=True)
        self.arm_id = pb.loadURDF(
            PANDA_URDF, ARM_BASE_POSITION, ARM_BASE_QUAT, useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE
        )
        for link in range(-1, pb.getNumJoints(self.base_id)):
            pb.setCollisionFilterPair(self.base_id, self.arm_id, link, -1, 0)
        info = [pb.getJointInfo(self.arm_id, j) for j in ARM_JOINTS]
        self.joint_names = [i[1].decode() for i in info]
        self.joint_limits = JointLimits(
            lower=np.array([i[8] for i in info]),
            upper=np.array([i[9] for i in info]),
            velocity=np.array([i[11] for i in info]),
            acceleration=np.full(len(ARM_JOINTS), ARM_ACCEL_LIMIT),
        )
        self.home_q = np.array(HOME_Q)
        for j, q in zip(ARM_JOINTS, HOME_Q, strict=True):
            pb.resetJointState(self.arm_id, j, q)
        for j in FINGER_JOINTS:
            pb.resetJointState(self.arm_id, j, FINGER_OPEN)
            pb.changeDynamics(self.arm_id, j, lateralFriction=1.0)
        self.set_joint_targets(self.home_q)
        self._drive_fingers(FINGER_OPEN)

    def _box(self, name: str, kind: str, center, size, color, mass: float = 0.0) -> int:
        pb = self._p
        half = [s / 2 for s in size]
        col = pb.createCollisionShape(p.GEOM_BOX, halfExtents=half)
        vis = pb.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=color)
        body = pb.createMultiBody(mass, col, vis, center)
        if mass > 0:
            pb.changeDynamics(body, -1, lateralFriction=0.8, spinningFriction=0.001, rollingFriction=0.0001)
        self._objects[name] = (body, kind, tuple(float(s) for s in size))
        return body

    def _build_scene(self, seed: int, n_objects: int) -> None:
        cubes, obstacle = sample_layout(seed, n_objects)
        self._box("table", "table", TABLE_CENTER, TABLE_SIZE, TABLE_COLOR)
        self._box("platform", "platform", PLATFORM_CENTER, PLATFORM_SIZE, GREEN)
        ob_center = (obstacle[0], obstacle[1], TABLE_TOP + OBSTACLE_SIZE[2] / 2)
        self._box("obstacle_0", "obstacle", ob_center, OBSTACLE_SIZE, BLUE)
        for i, (x, y) in enumerate(cubes):
            center = (x, y, TABLE_TOP + CUBE_SIZE / 2 + 0.001)
            self._box(f"cube_{i}", "target", center, (CUBE_SIZE,) * 3, RED, mass=CUBE_MASS)

    # --- time ------------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance the physics by ``n`` fixed steps of ``time_step`` simulated seconds."""
        for _ in range(n):
            self._p.stepSimulation()
        self.sim_time += n * self.time_step

    # --- arm -------------------------------------------------------------------------------------------
    def joint_positions(self) -> np.ndarray:
        return np.array([s[0] for s in self._p.getJointStates(self.arm_id, ARM_JOINTS)])

    def joint_velocities(self) -> np.ndarray:
        return np.array([s[1] for s in self._p.getJointStates(self.arm_id, ARM_JOINTS)])

    def set_joint_targets(self, q, qd=None) -> None:
        """Position control towards ``q`` (rad) with velocity feed-forward ``qd`` (rad/s)."""
        q = [float(v) for v in q]
        qd = [0.0] * len(q) if qd is None else [float(v) for v in qd]
        self._p.setJointMotorControlArray(
            self.arm_id,
            ARM_JOINTS,
            p.POSITION_CONTROL,
            targetPositions=q,
            targetVelocities=qd,
            forces=ARM_FORCES,
            positionGains=[0.3] * len(q),
            velocityGains=[1.0] * len(q),
        )

    def reset_joints(self, q) -> None:
        """Teleport the arm (tests, not for execution)."""
        for j, v in zip(ARM_JOINTS, q, strict=True):
            self._p.resetJointState(self.arm_id, j, float(v))
        self.set_joint_targets(q)

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Grasp point (between the finger pads) position and quaternion xyzw."""
        s = self._p.getLinkState(self.arm_id, EE_LINK, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    # --- gripper ---------------------------------------------------------------------------------------
    def _drive_fingers(self, opening: float) -> None:
        self._p.setJointMotorControlArray(
            self.arm_id, FINGER_JOINTS, p.POSITION_CONTROL, targetPositions=[opening] * 2, forces=[20.0, 20.0]
        )

    def set_gripper(self, closed: bool) -> bool:
        """Close (attach the target between the fingers; True if one was caught) or open (release)."""
        if not closed:
            if self._attachment is not None:
                self._p.removeConstraint(self._attachment[0])
                self._attachment = None
            self._gripper_closed = False
            self._drive_fingers(FINGER_OPEN)
            return True
        self._gripper_closed = True
        if self._attachment is not None:
            return True
        name = self._object_at_grasp_point()
        if name is None:
            self._drive_fingers(0.0)
            return False
        self._attach(name)
        self._drive_fingers(max(0.0, CUBE_SIZE / 2 - 0.003))
        return True

    def _object_at_grasp_point(self) -> str | None:
        ee, _ = self.ee_pose()
        best, best_d = None, GRASP_CAPTURE_RADIUS
        for name, (body, kind, _size) in self._objects.items():
            if kind != "target":
                continue
            pos, _ = self._p.getBasePositionAndOrientation(body)
            d = float(np.linalg.norm(np.asarray(pos) - ee))
            if d < best_d:
                best, best_d = name, d
        return best

    def _attach(self, name: str) -> None:
        pb = self._p
        body = self._objects[name][0]
        s = pb.getLinkState(self.arm_id, EE_LINK, computeForwardKinematics=True)
        obj_pos, obj_orn = pb.getBasePositionAndOrientation(body)
        inv_pos, inv_orn = pb.invertTransform(s[4], s[5])
        rel_pos, rel_orn = pb.multiplyTransforms(inv_pos, inv_orn, obj_pos, obj_orn)
        cid = pb.createConstraint(
            self.arm_id, EE_LINK, body, -1, p.JOINT_FIXED, (0, 0, 0), rel_pos, (0, 0, 0), parentFrameOrientation=rel_orn
        )
        pb.changeConstraint(cid, maxForce=200.0)
        self._attachment = (cid, name)

    def grasped(self) -> str | None:
        """Name of the attached object, if any."""
        return None if self._attachment is None else self._attachment[1]

    @property
    def gripper_closed(self) -> bool:
        return self._gripper_closed

    # --- ground truth ----------------------------------------------------------------------------------
    def object_states(self) -> list[ObjectState]:
        """Ground-truth pose of every scene object (targets, obstacle, platform, table)."""
        out = []
        for name, (body, kind, size) in self._objects.items():
            pos, orn = self._p.getBasePositionAndOrientation(body)
            out.append(ObjectState(name, kind, tuple(pos), tuple(orn), size))
        return out

    def platform_region(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (min, max) corners of the volume counted as "on the platform"."""
        c, s = np.array(PLATFORM_CENTER), np.array(PLATFORM_SIZE)
        lo = np.array([c[0] - s[0] / 2, c[1] - s[1] / 2, PLATFORM_TOP])
        hi = np.array([c[0] + s[0] / 2, c[1] + s[1] / 2, PLATFORM_TOP + 1.5 * CUBE_SIZE])
        return lo, hi

    def objects_on_platform(self) -> int:
        """Targets at rest inside the platform region and not held: the success criterion."""
        lo, hi = self.platform_region()
        held = self.grasped()
        count = 0
        for name, (body, kind, _size) in self._objects.items():
            if kind != "target" or name == held:
                continue
            pos, _ = self._p.getBasePositionAndOrientation(body)
            lin, _ = self._p.getBaseVelocity(body)
            if np.all(np.asarray(pos) >= lo) and np.all(np.asarray(pos) <= hi) and np.linalg.norm(lin) < 0.05:
                count += 1
        return count

    def n_targets(self) -> int:
        return sum(1 for _b, kind, _s in self._objects.values() if kind == "target")

    # --- camera ----------------------------------------------------------------------------------------
    def camera(self, with_segmentation: bool = False) -> CameraFrame:
        """Render the head RGB-D camera (ER_TINY_RENDERER, CAMERA_WIDTH x CAMERA_HEIGHT)."""
        pb = self._p
        view = pb.computeViewMatrix(CAMERA_EYE, CAMERA_TARGET, CAMERA_UP)
        proj = pb.computeProjectionMatrixFOV(CAMERA_FOV_DEG, CAMERA_WIDTH / CAMERA_HEIGHT, CAMERA_NEAR, CAMERA_FAR)
        flags = 0 if with_segmentation else p.ER_NO_SEGMENTATION_MASK
        _w, _h, rgba, zbuf, seg = pb.getCameraImage(
            CAMERA_WIDTH, CAMERA_HEIGHT, view, proj, renderer=p.ER_TINY_RENDERER, flags=flags, shadow=0
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(CAMERA_HEIGHT, CAMERA_WIDTH, 4)[:, :, :3].copy()
        depth = depth_from_zbuffer(np.asarray(zbuf).reshape(CAMERA_HEIGHT, CAMERA_WIDTH), CAMERA_NEAR, CAMERA_FAR)
        segm = np.asarray(seg).reshape(CAMERA_HEIGHT, CAMERA_WIDTH) if with_segmentation else None
        return CameraFrame(
            rgb=rgb,
            depth=depth,
            K=self.K.copy(),
            width=CAMERA_WIDTH,
            height=CAMERA_HEIGHT,
            position=tuple(float(v) for v in self._camera_pos),
            quat_xyzw=rotation_to_quat(self._camera_rot),
            near=CAMERA_NEAR,
            far=CAMERA_FAR,
            sim_time=self.sim_time,
            segmentation=segm,
        )

    def object_body(self, name: str) -> int:
        return self._objects[name][0]

    def close(self) -> None:
        try:
            self._p.disconnect()
        except p.error:
            pass


def measure_camera_ms(seed: int = 0, repeats: int = 20) -> float:
    """Mean wall time of one ``RobotWorld.camera()`` call in milliseconds."""
    w = RobotWorld(seed)
    try:
        w.camera()
        t0 = time.perf_counter()
        for _ in range(repeats):
            w.camera()
        return (time.perf_counter() - t0) / repeats * 1000.0
    finally:
        w.close()


def arm_model() -> tuple[list[str], JointLimits]:
    """The arm's joint names and limits, read from its URDF without building a world (for the modules that time
    and plan motions but have no physics: the controller, the coordinator)."""
    client = bullet_client.BulletClient(connection_mode=p.DIRECT)
    try:
        client.setAdditionalSearchPath(pybullet_data.getDataPath())
        arm = client.loadURDF(PANDA_URDF, ARM_BASE_POSITION, ARM_BASE_QUAT, useFixedBase=True)
        info = [client.getJointInfo(arm, j) for j in ARM_JOINTS]
    finally:
        client.disconnect()
    limits = JointLimits(
        lower=np.array([i[8] for i in info]),
        upper=np.array([i[9] for i in info]),
        velocity=np.array([i[11] for i in info]),
        acceleration=np.full(len(ARM_JOINTS), ARM_ACCEL_LIMIT),
    )
    return [i[1].decode() for i in info], limits
