"""Time-optimal parameterization of joint paths (toppra), with a trapezoidal fallback.

``time_parameterize(path, v_max, a_max, dt)``: collinear waypoints are merged, a cubic spline (zero end
velocity) is fitted through the remaining waypoints re-densified to ``spline_step`` rad, and TOPPRA finds
the fastest timing under per-joint velocity and acceleration limits (scaled by ``TOPPRA_LIMIT_SCALE`` to
absorb the grid discretization). The result is sampled every ``dt``
seconds. If toppra fails (or its samples break the limits by more than the tolerance), every segment
between corners is timed with a synchronized rest-to-rest trapezoidal profile instead (exactly on the
path; slower); ``Trajectory.method`` says which one was used.

Units: rad, rad/s, rad/s^2, seconds from the start of the trajectory.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)
LIMIT_TOLERANCE = 1.05  # sampled |v|, |a| may exceed the limits by 5% (spline/grid discretization)
TOPPRA_LIMIT_SCALE = 0.85  # toppra gets 85% of the limits: its grid discretization overshoots by up to ~15%


@dataclass
class Trajectory:
    """A sampled joint trajectory: ``positions[i]`` and ``velocities[i]`` at ``times[i]``."""

    times: np.ndarray  # (N,)
    positions: np.ndarray  # (N, dof)
    velocities: np.ndarray  # (N, dof)
    method: str  # 'toppra' | 'trapezoidal' | 'none'
    compute_ms: float = 0.0
    reason: str = ""

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0

    def accelerations(self) -> np.ndarray:
        """Finite-difference accelerations of the samples."""
        if len(self.times) < 2:
            return np.zeros_like(self.velocities)
        return np.gradient(self.velocities, self.times, axis=0)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Linear interpolation of (q, qd) at time ``t`` (clamped to the ends)."""
        t = min(max(t, 0.0), self.duration)
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        i = min(max(i, 0), len(self.times) - 2)
        if len(self.times) < 2:
            return self.positions[0], self.velocities[0]
        f = (t - self.times[i]) / max(1e-12, self.times[i + 1] - self.times[i])
        q = self.positions[i] + f * (self.positions[i + 1] - self.positions[i])
        qd = self.velocities[i] + f * (self.velocities[i + 1] - self.velocities[i])
        return q, qd


def compress_path(path, tol: float = 1e-4) -> np.ndarray:
    """Drop waypoints lying on the straight joint-space line between their neighbours (within ``tol`` rad)."""
    pts = np.asarray(path, dtype=float)
    if len(pts) <= 2:
        return pts
    keep = [0]
    for i in range(1, len(pts) - 1):
        a, b = pts[keep[-1]], pts[i + 1]
        ab = b - a
        denom = float(ab @ ab)
        if denom < 1e-18:
            continue
        t = float((pts[i] - a) @ ab) / denom
        if np.linalg.norm(a + t * ab - pts[i]) > tol or not 0.0 <= t <= 1.0:
            keep.append(i)
    keep.append(len(pts) - 1)
    return pts[keep]


def densify(pts: np.ndarray, step: float) -> np.ndarray:
    out = [pts[0]]
    for a, b in itertools.pairwise(pts):
        n = max(1, math.ceil(float(np.max(np.abs(b - a))) / step))
        out.extend(a + (b - a) * (k / n) for k in range(1, n + 1))
    return np.asarray(out)


def _toppra(corners: np.ndarray, v_max: np.ndarray, a_max: np.ndarray, dt: float, spline_step: float) -> Trajectory:
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    ta.setup_logging("WARNING")
    way = densify(corners, spline_step)
    seg = np.linalg.norm(np.diff(way, axis=0), axis=1)
    ss = np.concatenate([[0.0], np.cumsum(seg)])
    path = ta.SplineInterpolator(ss, way, bc_type="clamped")
    vlim = np.column_stack([-v_max, v_max]) * TOPPRA_LIMIT_SCALE
    alim = np.column_stack([-a_max, a_max]) * TOPPRA_LIMIT_SCALE
    pc_vel = constraint.JointVelocityConstraint(vlim)
    pc_acc = constraint.JointAccelerationConstraint(alim, discretization_scheme=constraint.DiscretizationType.Interpolation)
    n_grid = int(min(600, max(50, 3 * len(way))))
    instance = algo.TOPPRA(
        [pc_vel, pc_acc], path, gridpoints=np.linspace(0, ss[-1], n_grid + 1), parametrizer="ParametrizeSpline"
    )
    jnt = instance.compute_trajectory(0.0, 0.0)
    if jnt is None:
        raise RuntimeError("toppra: infeasible parameterization")
    duration = float(jnt.duration)
    times = np.arange(0.0, duration, dt)
    times = np.append(times, duration)
    return Trajectory(times, np.asarray(jnt(times)), np.asarray(jnt(times, 1)), "toppra")


def _trapezoid_s(t: float, v: float, a: float, total: float) -> tuple[float, float]:
    """Position/velocity along a rest-to-rest trapezoid of length ``total`` (1 here) at time t."""
    t_acc = v / a
    if a * t_acc * t_acc >= total:  # triangular
        t_acc = math.sqrt(total / a)
        v = a * t_acc
    d_acc = 0.5 * a * t_acc * t_acc
    t_flat = (total - 2 * d_acc) / v
    if t < t_acc:
        return 0.5 * a * t * t, a * t
    if t < t_acc + t_flat:
        return d_acc + v * (t - t_acc), v
    td = min(t - t_acc - t_flat, t_acc)
    return d_acc + v * t_flat + v * td - 0.5 * a * td * td, v - a * td


def _trapezoid_duration(v: float, a: float, total: float) -> float:
    t_acc = v / a
    if a * t_acc * t_acc >= total:
        return 2 * math.sqrt(total / a)
    return 2 * t_acc + (total - a * t_acc * t_acc) / v


def trapezoidal(corners: np.ndarray, v_max: np.ndarray, a_max: np.ndarray, dt: float) -> Trajectory:
    """Synchronized rest-to-rest trapezoidal timing of every straight segment between ``corners``."""
    times, pos, vel = [0.0], [corners[0]], [np.zeros_like(corners[0])]
    t0 = 0.0
    for a, b in itertools.pairwise(corners):
        d = b - a
        moving = np.abs(d) > 1e-12
        if not np.any(moving):
            continue
        vs = float(np.min(v_max[moving] / np.abs(d[moving])))  # path-parameter limits (s in [0, 1])
        acc = float(np.min(a_max[moving] / np.abs(d[moving])))
        dur = _trapezoid_duration(vs, acc, 1.0)
        for t in np.append(np.arange(dt, dur, dt), dur):
            s, sd = _trapezoid_s(float(t), vs, acc, 1.0)
            times.append(t0 + float(t))
            pos.append(a + s * d)
            vel.append(sd * d)
        vel[-1] = np.zeros_like(d)
        t0 += dur
    return Trajectory(np.asarray(times), np.asarray(pos), np.asarray(vel), "trapezoidal")


def within_limits(traj: Trajectory, v_max, a_max, tol: float = LIMIT_TOLERANCE) -> bool:
    """Sampled velocities and (finite-difference) accelerations within ``tol`` x the limits."""
    v_ok = np.all(np.abs(traj.velocities) <= np.asarray(v_max) * tol + 1e-9)
    a_ok = np.all(np.abs(traj.accelerations()) <= np.asarray(a_max) * tol + 1e-6)
    return bool(v_ok and a_ok)


def time_parameterize(
    path, v_max, a_max, dt: float = 1.0 / 240.0, spline_step: float = 0.05, use_toppra: bool = True
) -> Trajectory:
    """Fastest timing of ``path`` (list of joint vectors) under |qd| <= v_max and |qdd| <= a_max."""
    t0 = time.perf_counter()
    v_max = np.asarray(v_max, dtype=float)
    a_max = np.asarray(a_max, dtype=float)
    corners = compress_path(path)
    if len(corners) < 2 or (float(np.max(np.abs(corners[-1] - corners[0]))) < 1e-9 and len(corners) == 2):
        q = np.asarray(path[0], dtype=float)[None, :]
        return Trajectory(np.zeros(1), q, np.zeros_like(q), "none", (time.perf_counter() - t0) * 1e3, "no motion")
    reason = ""
    if use_toppra:
        try:
            traj = _toppra(corners, v_max, a_max, dt, spline_step)
            if within_limits(traj, v_max, a_max) and np.allclose(traj.positions[-1], corners[-1], atol=1e-4):
                traj.compute_ms = (time.perf_counter() - t0) * 1e3
                return traj
            reason = "toppra result violated limits or missed the goal"
        except Exception as exc:  # toppra raises assorted errors on degenerate input
            reason = f"toppra failed: {exc}"
        log.warning("%s; falling back to trapezoidal timing", reason)
    traj = trapezoidal(corners, v_max, a_max, dt)
    traj.compute_ms = (time.perf_counter() - t0) * 1e3
    traj.reason = reason or "trapezoidal requested"
    return traj
