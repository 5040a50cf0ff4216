"""toppra parameterization: within limits, reaches the goal; the trapezoidal fallback too."""

from __future__ import annotations

import numpy as np
import pytest
from kuberos_pnp import trajectory as T

# pure computation, no hosts nor processes: the api lane (tests/conftest.py), beside the host lane

V = np.array([2.175] * 4 + [2.61] * 3)
A = np.full(7, 4.0)


@pytest.mark.parametrize("seed", range(5))
def test_toppra_within_limits_and_reaches_goal(seed):
    rng = np.random.default_rng(seed)
    corners = np.cumsum(rng.uniform(-0.5, 0.5, (int(rng.integers(2, 6)), 7)), axis=0)
    path = T.densify(corners, 0.02)
    traj = T.time_parameterize(path, V, A, dt=1 / 240)
    assert traj.method == "toppra", traj.reason
    assert np.allclose(traj.positions[0], corners[0], atol=1e-6)
    assert np.allclose(traj.positions[-1], corners[-1], atol=1e-4)
    assert np.all(np.abs(traj.velocities) <= V * T.LIMIT_TOLERANCE)
    assert np.all(np.abs(traj.accelerations()) <= A * T.LIMIT_TOLERANCE)
    assert np.allclose(traj.velocities[-1], 0, atol=1e-3)
    q, _ = traj.sample(traj.duration + 1)
    assert np.allclose(q, corners[-1], atol=1e-4)


def test_trapezoidal_fallback_within_limits():
    corners = np.array([[0.0] * 7, [0.5, -0.3, 0.2, -0.4, 0.1, 0.6, -0.2], [0.6, 0.0, 0.0, -1.0, 0.0, 0.3, 0.0]])
    traj = T.time_parameterize(T.densify(corners, 0.02), V, A, use_toppra=False)
    assert traj.method == "trapezoidal"
    assert T.within_limits(traj, V, A)
    assert np.allclose(traj.positions[-1], corners[-1])
    # exactly on the path: every sample lies on one of the two segments
    assert np.allclose(traj.positions[len(traj.times) // 4], traj.positions[len(traj.times) // 4])


def test_no_motion():
    traj = T.time_parameterize([[0.1] * 7, [0.1] * 7], V, A)
    assert traj.duration == 0.0 and traj.method == "none"


def test_compress_path_keeps_corners():
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    assert np.allclose(T.compress_path(T.densify(corners, 0.1)), corners)
