"""Perception: one frame finds every target (within grasping tolerance), the obstacle and the platform."""

from __future__ import annotations

import numpy as np
import pytest
from kuberos_pnp import perception_core as P
from kuberos_pnp import world as W

# pure computation, no hosts nor processes: the api lane (tests/conftest.py), beside the host lane


@pytest.mark.parametrize("seed,n", [(0, 2), (1, 3), (4, 4), (7, 3), (11, 4)])
def test_finds_targets_and_obstacle(seed, n):
    w = W.RobotWorld(seed, n_objects=n)
    try:
        boxes, stats = P.perceive(w.camera())
        truth = w.object_states()
    finally:
        w.close()
    kinds = [b.kind for b in boxes]
    assert kinds.count("target") == n
    assert kinds.count("obstacle") == 1
    assert kinds.count("platform") == 1 and kinds.count("table") == 1
    targets = [b for b in boxes if b.kind == "target"]
    for o in (o for o in truth if o.kind == "target"):
        err = min(np.linalg.norm(np.subtract(b.center, o.position)) for b in targets)
        assert err < 0.012, (o.name, err)
    obstacle = next(b for b in boxes if b.kind == "obstacle")
    true_ob = next(o for o in truth if o.kind == "obstacle")
    lo, hi = np.subtract(obstacle.center, np.divide(obstacle.size, 2)), np.add(obstacle.center, np.divide(obstacle.size, 2))
    t_lo = np.subtract(true_ob.position, np.divide(true_ob.size, 2))
    t_hi = np.add(true_ob.position, np.divide(true_ob.size, 2))
    assert np.all(lo <= t_lo + 0.01) and np.all(hi >= t_hi - 0.01)  # padded box covers the obstacle
    table = next(b for b in boxes if b.kind == "table")
    assert abs(table.top - W.TABLE_TOP) < 0.005
    assert stats["total_ms"] < 200


def test_depth_to_points_roundtrip():
    K = W.camera_intrinsics(160, 120, 60.0)
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    pts, cols = P.depth_to_points(depth, K, (0, 0, 0), (0, 0, 0, 1), stride=4, max_range=3.0)
    assert cols is None and pts.dtype == np.float32
    assert np.allclose(pts[:, 2], 2.0)
    pts2, _ = P.depth_to_points(depth, K, (0, 0, 0), (0, 0, 0, 1), stride=1, max_range=1.5)
    assert len(pts2) == 0
    pts3, _ = P.depth_to_points(depth, K, (0, 0, 0), (0, 0, 0, 1), stride=1, max_range=3.0, voxel_size=0.2)
    assert 0 < len(pts3) < 120 * 160


def test_box_roundtrip():
    b = P.Box("target_0", "target", (1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    assert P.Box.from_dict(b.to_dict()) == b
