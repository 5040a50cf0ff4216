"""Pick-and-place task geometry, shared by the offline loop and the ROS coordinator. Pure functions.

Grasps are top-down: the grasp link (``world.EE_LINK``, between the finger pads) points straight down
(roll = pi) with a yaw from ``GRASP_YAWS`` (cubes are symmetric, so the yaw is free up to 90 degrees and
the caller tries candidates until IK succeeds). All poses are (position xyz in metres, quaternion xyzw)
in the robot frame.

One pick cycle is ``pick_cycle_steps(target, platform, slot)``: pregrasp -> grasp (descend) -> close
gripper -> lift (carrying) -> above platform (carrying) -> place (carrying) -> open gripper -> retreat ->
home. Each ``Step`` with ``kind == 'move'`` is a planning request: a pose goal (or ``joint_goal``), the
carried object (``carry``) and the boxes to ignore (the target while the fingers surround it; the
support the carried object touches at lift-off / set-down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from . import world as W
from .perception_core import Box
from .planning import Attached

home_q: tuple[float, ...] = W.HOME_Q
PREGRASP_HEIGHT = 0.10  # above the grasp pose
LIFT_HEIGHT = 0.12
PREPLACE_HEIGHT = 0.10
PLACE_CLEARANCE = 0.01  # carried object's bottom above the platform surface when released
FINGERTIP_CLEARANCE = 0.012  # fingertips above the table at the grasp
SLOT_OFFSETS = ((-0.05, -0.05), (0.05, -0.05), (-0.05, 0.05), (0.05, 0.05))
GRASP_YAWS = (0.0, math.pi / 2, -math.pi / 2, math.pi)
PLATFORM_PADDING = 0.01  # perception pads the platform box; the real surface is this much lower

Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]


def down_quat(yaw: float = 0.0) -> tuple[float, float, float, float]:
    """Grasp link pointing down (z towards -z of the robot frame), rotated by ``yaw`` about vertical."""
    q = Rotation.from_euler("xyz", [math.pi, 0.0, 0.0]) * Rotation.from_euler("z", -yaw)
    x, y, z, w = q.as_quat()
    return (float(x), float(y), float(z), float(w))


def _bottom(box: Box) -> float:
    return box.center[2] - box.size[2] / 2


def grasp_pose(box: Box, yaw: float = 0.0) -> Pose:
    """Grasp point at the box centre, raised if needed so the fingertips clear the table."""
    z = _bottom(box) + max(box.size[2] / 2, FINGERTIP_CLEARANCE + W.FINGERTIP_BELOW_EE)
    return (box.center[0], box.center[1], z), down_quat(yaw)


def pregrasp_pose(box: Box, yaw: float = 0.0) -> Pose:
    (x, y, z), q = grasp_pose(box, yaw)
    return (x, y, z + PREGRASP_HEIGHT), q


def lift_pose(box: Box, yaw: float = 0.0) -> Pose:
    (x, y, z), q = grasp_pose(box, yaw)
    return (x, y, z + LIFT_HEIGHT), q


def slot_xy(platform: Box, index: int) -> tuple[float, float]:
    dx, dy = SLOT_OFFSETS[index % len(SLOT_OFFSETS)]
    return platform.center[0] + dx, platform.center[1] + dy


def place_pose(platform_box: Box, index: int, carried: Box | None = None, yaw: float = 0.0, ee_offset_z: float = 0.0) -> Pose:
    """Grasp-link pose releasing the carried cube ``PLACE_CLEARANCE`` above slot ``index`` of the platform.

    ``ee_offset_z`` is the carried box centre's height above the grasp point (0 for centre grasps).
    """
    size_z = carried.size[2] if carried is not None else W.CUBE_SIZE
    surface = platform_box.top - PLATFORM_PADDING
    x, y = slot_xy(platform_box, index)
    return (x, y, surface + PLACE_CLEARANCE + size_z / 2 - ee_offset_z), down_quat(yaw)


def preplace_pose(platform_box: Box, index: int, carried: Box | None = None, yaw: float = 0.0, ee_offset_z: float = 0.0) -> Pose:
    (x, y, z), q = place_pose(platform_box, index, carried, yaw, ee_offset_z)
    return (x, y, z + PREPLACE_HEIGHT), q


def attachment(box: Box, grasp: Pose, ignore: tuple[str, ...] = ()) -> Attached:
    """The grasped box expressed in the grasp-link frame at ``grasp``."""
    pos, quat = grasp
    rot = Rotation.from_quat(quat)
    rel = rot.inv().apply(np.asarray(box.center) - np.asarray(pos))
    rel_q = rot.inv().as_quat()
    return Attached(box, tuple(float(v) for v in rel), tuple(float(v) for v in rel_q), ignore)


@dataclass(frozen=True)
class Step:
    """One step of a pick cycle: a motion (planning request) or a gripper command."""

    name: str
    kind: str  # 'move' | 'gripper'
    pose: Pose | None = None
    joint_goal: tuple[float, ...] | None = None
    carry: Attached | None = None
    ignore: tuple[str, ...] = ()
    close_gripper: bool | None = None
    ik_seed_from: str | None = None  # name of the step whose goal seeds this step's IK
    cartesian: bool = False  # short straight-ish approach/retreat; planners handle it the same way
    meta: dict = field(default_factory=dict)


def pick_cycle_steps(target: Box, platform: Box, slot: int, yaw: float = 0.0) -> list[Step]:
    """The pure step list of one pick-and-place cycle for ``target`` into platform slot ``slot``."""
    grasp = grasp_pose(target, yaw)
    ee_offset_z = target.center[2] - grasp[0][2]
    carry_lift = attachment(target, grasp, ignore=("table",))
    carry = replace(carry_lift, ignore=())
    carry_place = replace(carry_lift, ignore=("platform",))
    place = place_pose(platform, slot, target, yaw, ee_offset_z)
    preplace = preplace_pose(platform, slot, target, yaw, ee_offset_z)
    t = (target.name,)
    return [
        Step("pregrasp", "move", pregrasp_pose(target, yaw)),
        Step("grasp", "move", grasp, ignore=t, ik_seed_from="pregrasp", cartesian=True),
        Step("close", "gripper", close_gripper=True, meta={"target": target.name}),
        Step("lift", "move", lift_pose(target, yaw), carry=carry_lift, ignore=t, ik_seed_from="grasp", cartesian=True),
        Step("preplace", "move", preplace, carry=carry, ignore=t),
        Step("place", "move", place, carry=carry_place, ignore=t, ik_seed_from="preplace", cartesian=True),
        Step("open", "gripper", close_gripper=False),
        Step("retreat", "move", preplace, ignore=t, ik_seed_from="place", cartesian=True),
        Step("home", "move", joint_goal=tuple(home_q)),
    ]


def placed_box(target: Box, platform: Box, slot: int) -> Box:
    """Where the target is assumed to be after placing (an obstacle for later cycles)."""
    x, y = slot_xy(platform, slot)
    z = platform.top - PLATFORM_PADDING + target.size[2] / 2
    return Box(target.name, "placed", (x, y, z), target.size)


def update_after_place(boxes: list[Box], target: Box, platform: Box, slot: int) -> list[Box]:
    """The box list with ``target`` moved onto the platform slot."""
    return [placed_box(target, platform, slot) if b.name == target.name else b for b in boxes]


def order_targets(boxes: list[Box]) -> list[Box]:
    """Targets in pick order: closest to the platform side (largest y) first, then nearest x."""
    return sorted((b for b in boxes if b.kind == "target"), key=lambda b: (-b.center[1], b.center[0]))


def platform_of(boxes: list[Box]) -> Box | None:
    return next((b for b in boxes if b.kind == "platform"), None)


def on_platform(box: Box, platform: Box) -> bool:
    """Whether ``box``'s centre lies over the platform's footprint (perception sees a placed cube there)."""
    return all(abs(box.center[i] - platform.center[i]) <= platform.size[i] / 2 for i in (0, 1))


def remaining_targets(boxes: list[Box]) -> list[Box]:
    """Targets still to pick, in pick order: every target not already on the platform."""
    platform = platform_of(boxes)
    return [t for t in order_targets(boxes) if platform is None or not on_platform(t, platform)]


def count_on_platform(boxes: list[Box]) -> int:
    platform = platform_of(boxes)
    return 0 if platform is None else sum(1 for b in boxes if b.kind == "target" and on_platform(b, platform))
