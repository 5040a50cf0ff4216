"""Depth image to point cloud to axis-aligned boxes: the perception core, no ROS.

Frames/units: points and boxes are in the robot base frame (metres). The camera pose is the optical frame
(x right, y down, z forward) in the robot frame, as ``world.CameraFrame`` documents; ``K`` uses
pixel-index coordinates (centre of pixel (u, v) is (u, v)).

Pipeline of ``segment``: crop to the workspace, find the table as the dominant horizontal plane (z
histogram), take the points above it, cluster them by footprint (connected components of an xy occupancy grid), fit an
axis-aligned box per cluster that rests on the table, and classify by colour: red = target, green =
platform, anything else = obstacle. The table itself is returned as a box too, so the planner avoids it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

# Robot-frame region where the table and everything to manipulate lie: (min xyz, max xyz).
DEFAULT_WORKSPACE = ((0.50, -0.70, 0.20), (1.30, 0.70, 1.20))
ABOVE_TABLE = 0.006  # points closer than this to the table plane belong to the table
MIN_CLUSTER_POINTS = 6
OBSTACLE_PADDING = 0.01  # added to every side of obstacle/platform boxes (pixel footprint + safety)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box in the robot frame: ``center`` and full ``size`` in metres."""

    name: str
    kind: str  # 'target' | 'obstacle' | 'table' | 'platform'
    center: tuple[float, float, float]
    size: tuple[float, float, float]

    @property
    def top(self) -> float:
        return self.center[2] + self.size[2] / 2

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> Box:
        return Box(str(d["name"]), str(d["kind"]), tuple(map(float, d["center"])), tuple(map(float, d["size"])))


def depth_to_points(
    depth: np.ndarray,
    K: np.ndarray,
    camera_position,
    camera_quat_xyzw,
    stride: int = 2,
    max_range: float = 2.5,
    rgb: np.ndarray | None = None,
    voxel_size: float | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Back-project a metric depth image to robot-frame points.

    Every ``stride``-th pixel in both directions is used; pixels at or beyond ``max_range`` (including the
    far plane) are dropped. With ``voxel_size`` the cloud is further downsampled to one point per occupied
    voxel (the first pixel that fell into it). Returns ``(points (N,3) float32, colors (N,3) uint8 or None)``.
    """
    h, w = depth.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[::stride, ::stride].astype(np.float64)
    keep = (z > 0) & (z < max_range)
    u, v, z = u[keep], v[keep], z[keep]
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    rot = Rotation.from_quat(camera_quat_xyzw).as_matrix()
    pts = np.column_stack([x, y, z]) @ rot.T + np.asarray(camera_position, dtype=np.float64)
    cols = None if rgb is None else rgb[::stride, ::stride][keep].astype(np.uint8)
    if voxel_size:
        _, first = np.unique(np.floor(pts / voxel_size).astype(np.int64), axis=0, return_index=True)
        first.sort()
        pts = pts[first]
        cols = None if cols is None else cols[first]
    return pts.astype(np.float32), cols


def estimate_table_height(points: np.ndarray, bin_size: float = 0.005) -> float:
    """Height of the dominant horizontal plane: the fullest z bin, refined by the median near it."""
    z = points[:, 2]
    bins = np.arange(z.min(), z.max() + bin_size, bin_size)
    hist, edges = np.histogram(z, bins=bins)
    peak = edges[int(np.argmax(hist))] + bin_size / 2
    near = z[np.abs(z - peak) < bin_size * 1.5]
    return float(np.median(near))


def classify_colors(colors: np.ndarray) -> np.ndarray:
    """'target' for red, 'platform' for green, 'obstacle' otherwise, for every row of an (N, 3) colour array."""
    c = colors.astype(np.float64)
    r, g, b = c[:, 0], c[:, 1], c[:, 2]
    kinds = np.full(len(c), "obstacle", dtype=object)
    kinds[(g > 70) & (g > 1.4 * r) & (g > 1.4 * b)] = "platform"
    kinds[(r > 70) & (r > 1.8 * g) & (r > 1.8 * b)] = "target"
    return kinds


def cluster_points(points: np.ndarray, voxel: float) -> list[np.ndarray]:
    """Cluster points above the table by their footprint: 8-connected components of the occupied xy grid.

    Everything rests on the table, so clustering the top-down projection keeps an object's sparsely
    sampled vertical faces together with its top. The grid is closed by one cell to bridge sampling gaps.
    Returns index arrays into ``points``, one per cluster.
    """
    if len(points) == 0:
        return []
    origin = points[:, :2].min(axis=0) - 2 * voxel
    idx = np.floor((points[:, :2] - origin) / voxel).astype(np.int64)
    grid = np.zeros(idx.max(axis=0) + 3, dtype=bool)
    grid[idx[:, 0], idx[:, 1]] = True
    grid = ndimage.binary_closing(grid, structure=np.ones((3, 3)))
    labels, n = ndimage.label(grid, structure=np.ones((3, 3)))
    point_labels = labels[idx[:, 0], idx[:, 1]]
    order = np.argsort(point_labels, kind="stable")
    splits = np.searchsorted(point_labels[order], np.arange(1, n + 1))
    return [g for g in np.split(order, splits[1:]) if len(g)]


def fit_box(points: np.ndarray, table_height: float, pad: float) -> tuple[tuple, tuple]:
    """Axis-aligned box around ``points`` resting on the table, grown by ``pad`` on every side but the bottom."""
    lo = points.min(axis=0).astype(np.float64)
    hi = points.max(axis=0).astype(np.float64)
    lo[:2] -= pad
    hi[:2] += pad
    hi[2] += pad
    lo[2] = table_height
    return tuple(float(c) for c in (lo + hi) / 2), tuple(float(s) for s in hi - lo)


def table_box(points: np.ndarray, table_height: float) -> Box:
    """The table as a box from the floor to its top, spanning the table-plane inliers."""
    inliers = points[np.abs(points[:, 2] - table_height) < ABOVE_TABLE]
    lo = np.percentile(inliers[:, :2], 0.5, axis=0) - 0.02
    hi = np.percentile(inliers[:, :2], 99.5, axis=0) + 0.02
    center = ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, table_height / 2)
    size = (hi[0] - lo[0], hi[1] - lo[1], table_height)
    return Box("table", "table", tuple(float(c) for c in center), tuple(float(s) for s in size))


def crop(points: np.ndarray, colors: np.ndarray | None, workspace) -> tuple[np.ndarray, np.ndarray | None]:
    lo, hi = np.asarray(workspace[0]), np.asarray(workspace[1])
    keep = np.all((points >= lo) & (points <= hi), axis=1)
    return points[keep], None if colors is None else colors[keep]


def segment(
    points: np.ndarray,
    colors: np.ndarray,
    table_height: float | None = None,
    workspace=DEFAULT_WORKSPACE,
    voxel: float = 0.01,
    min_points: int = MIN_CLUSTER_POINTS,
) -> list[Box]:
    """Boxes for the table, the platform, every obstacle and every (red) target seen in one cloud.

    Names are stable for a given scene: ``target_i``/``obstacle_i`` are sorted by y then x.
    Target boxes are unpadded (their centre is what matters for grasping); obstacle and platform boxes
    are padded by ``OBSTACLE_PADDING``.
    """
    points, colors = crop(points, colors, workspace)
    if len(points) == 0:
        return []
    height = estimate_table_height(points) if table_height is None else float(table_height)
    boxes = [table_box(points, height)]
    above = points[:, 2] > height + ABOVE_TABLE
    pts, cols = points[above], colors[above]
    found: dict[str, list[tuple[tuple, tuple]]] = {"target": [], "obstacle": [], "platform": []}
    # Colour first, then footprint: a cube standing on the platform is a cluster of its own, not part of it.
    kinds = classify_colors(cols)
    for kind in found:
        of_kind = np.flatnonzero(kinds == kind)
        for members in cluster_points(pts[of_kind], voxel):
            if len(members) < min_points:
                continue
            pad = 0.0 if kind == "target" else OBSTACLE_PADDING
            found[kind].append(fit_box(pts[of_kind[members]], height, pad))
    for kind in ("platform", "obstacle", "target"):
        ordered = sorted(found[kind], key=lambda cs: (round(cs[0][1], 2), cs[0][0]))
        for i, (center, size) in enumerate(ordered):
            name = kind if kind == "platform" and i == 0 else f"{kind}_{i}"
            boxes.append(Box(name, kind, center, size))
    return boxes


def perceive(frame, stride: int = 1, voxel_size: float | None = None) -> tuple[list[Box], dict]:
    """One camera frame (``world.CameraFrame``-like) to boxes, with timing stats in milliseconds."""
    t0 = time.perf_counter()
    pts, cols = depth_to_points(
        frame.depth, frame.K, frame.position, frame.quat_xyzw, stride=stride, rgb=frame.rgb, voxel_size=voxel_size
    )
    t1 = time.perf_counter()
    boxes = segment(pts, cols, voxel=0.01 * stride, min_points=max(2, MIN_CLUSTER_POINTS // stride**2))
    t2 = time.perf_counter()
    return boxes, {"points": len(pts), "cloud_ms": (t1 - t0) * 1e3, "segment_ms": (t2 - t1) * 1e3, "total_ms": (t2 - t0) * 1e3}
