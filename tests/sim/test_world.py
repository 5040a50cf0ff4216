"""RobotWorld: seeded determinism, camera model, gripper attachment."""

from __future__ import annotations

import numpy as np
import pytest
from kuberos_pnp import world as W
from scipy.spatial.transform import Rotation

pytestmark = pytest.mark.sim  # pure, but kept in the host lane: tests/unit/test_lanes.py's example of a host-lane file of seconds


def _run(seed: int) -> tuple[list, np.ndarray]:
    w = W.RobotWorld(seed, n_objects=3)
    try:
        w.set_joint_targets(np.array(W.HOME_Q) + 0.1)
        w.step(120)
        return [o.position for o in w.object_states()], w.joint_positions()
    finally:
        w.close()


def test_same_seed_same_world():
    a_objs, a_q = _run(5)
    b_objs, b_q = _run(5)
    assert a_objs == b_objs
    assert np.array_equal(a_q, b_q)
    c_objs, _ = _run(6)
    assert c_objs != a_objs


def test_layout_is_valid():
    for seed in range(20):
        cubes, obstacle = W.sample_layout(seed, 4)
        for i, c in enumerate(cubes):
            assert np.hypot(c[0] - obstacle[0], c[1] - obstacle[1]) >= W.MIN_OBSTACLE_CLEARANCE
            for d in cubes[i + 1 :]:
                assert np.hypot(c[0] - d[0], c[1] - d[1]) >= W.MIN_CUBE_SPACING


def test_camera_intrinsics_project_known_points():
    w = W.RobotWorld(2, n_objects=3)
    try:
        f = w.camera(with_segmentation=True)
        assert f.rgb.shape == (f.height, f.width, 3) and f.rgb.dtype == np.uint8
        assert f.depth.shape == (f.height, f.width) and f.depth.dtype == np.float32
        rot = Rotation.from_quat(f.quat_xyzw).as_matrix()
        assert np.allclose(
            rot[:, 2],
            np.subtract(W.CAMERA_TARGET, W.CAMERA_EYE) / np.linalg.norm(np.subtract(W.CAMERA_TARGET, W.CAMERA_EYE)),
            atol=1e-6,
        )  # z forward
        assert rot[2, 1] < 0  # y (down in the image) points down in the world
        for o in w.object_states():
            if o.kind != "target":
                continue
            top = np.add(o.position, (0.0, 0.0, o.size[2] / 2))
            pc = rot.T @ (top - np.array(f.position))
            u = f.K[0, 0] * pc[0] / pc[2] + f.K[0, 2]
            v = f.K[1, 1] * pc[1] / pc[2] + f.K[1, 2]
            assert f.segmentation[round(v), round(u)] == w.object_body(o.name)
            assert abs(float(f.depth[round(v), round(u)]) - pc[2]) < 0.01
    finally:
        w.close()


def test_gripper_attaches_only_near_object():
    w = W.RobotWorld(3, n_objects=2)
    try:
        assert w.set_gripper(True) is False  # nothing between the fingers at home
        w.set_gripper(False)
        assert w.grasped() is None
        assert w.objects_on_platform() == 0
        lo, hi = w.platform_region()
        assert np.all(hi > lo)
    finally:
        w.close()
