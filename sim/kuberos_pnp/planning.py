"""OMPL motion planning for the Panda arm against perceived boxes, several planners in parallel.

Collision model (``CollisionModel``): a private PyBullet ``p.DIRECT`` client with the same Panda URDF at
the same base pose as ``world``, the robot's own chassis as a fixed box, one static box per perceived
``Box`` and, when carrying, the grasped box rigidly attached to the grasp link. A configuration is valid
when it is inside the joint limits and no arm link (or the carried box) is closer than ``margin`` to any
box (``getClosestPoints``). Self-collision: only the pairs joint limits do not already exclude are checked
(hand/fingers and carried box against links 0-3 and the chassis); the remaining pairs of a Panda within its
limits cannot meet.

Parallel planning (``Planner``): OMPL's Python state-validity callback holds the GIL, so threads would
not run in parallel. ``Planner(parallel=N)`` keeps N worker processes (``spawn`` context, started once,
each with its own collision model). Every ``plan`` call sends the same problem to all workers, each with
a different planner from ``planners`` (round robin); the first exact solution wins, the others are told
to stop through a shared event (OMPL termination condition) and their answers are drained. The winner
simplifies its path, interpolates it to ``max_step`` rad and validates every state before replying.

Determinism: each worker seeds OMPL's RNG once at start (``seed + worker index``); OMPL cannot be
reseeded per query. With ``deterministic=True`` the planner waits for all workers and takes the lowest
index that solved, which is reproducible for the same sequence of queries; the default takes the first
answer (fastest, but which worker wins depends on timing).

Frames/units: joint vectors in rad (7 arm joints, world.ARM_JOINTS order); poses in the robot frame.
PRM is not offered: its roadmap thread calls the Python validity checker concurrently and deadlocks.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing as mp
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pybullet as p
import pybullet_data
from pybullet_utils import bullet_client

from . import world as W
from .perception_core import Box

DEFAULT_PLANNERS = ("RRTConnect", "BKPIECE1", "RRTConnect", "KPIECE1")
SUPPORTED_PLANNERS = ("RRTConnect", "RRT", "KPIECE1", "BKPIECE1", "LBKPIECE1")
DEFAULT_MARGIN = 0.005
CHECK_RESOLUTION_RAD = 0.02  # OMPL motion validation step (rad, in joint space)
MAX_STEP_RAD = 0.02  # returned paths: no joint moves more than this between consecutive states
HAND_LINKS = (7, 8, 9, 10, 11)
BASE_SIDE_LINKS = (-1, 0, 1, 2, 3)
IK_POS_TOL = 0.004
IK_ANGLE_TOL = 0.03
READY_Q = (0.0, 0.3, 0.0, -2.0, 0.0, 2.3, 0.785)  # hand down over the table: a good IK start for top-down poses


@dataclass(frozen=True)
class Attached:
    """A box carried by the hand: its size and its pose in the grasp-link (``world.EE_LINK``) frame."""

    box: Box
    ee_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ee_quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    ignore: tuple[str, ...] = ()  # boxes the carried object may touch (e.g. its support when lifting)

    def to_dict(self) -> dict:
        return {
            "box": self.box.to_dict(),
            "ee_position": list(self.ee_position),
            "ee_quat_xyzw": list(self.ee_quat_xyzw),
            "ignore": list(self.ignore),
        }

    @staticmethod
    def from_dict(d: dict) -> Attached:
        return Attached(Box.from_dict(d["box"]), tuple(d["ee_position"]), tuple(d["ee_quat_xyzw"]), tuple(d["ignore"]))


@dataclass
class PlanResult:
    """Outcome of one planning query; ``path`` is a list of 7-vectors (rad), dense (<= MAX_STEP_RAD)."""

    solved: bool
    path: list[list[float]] = field(default_factory=list)
    planner: str = ""
    planning_time_s: float = 0.0
    attempts: int = 0
    reason: str = ""
    worker: int = -1


# --- collision model -------------------------------------------------------------------------------------
class CollisionModel:
    """Arm + boxes in a private PyBullet client, for validity checks, FK and IK."""

    def __init__(self, margin: float = DEFAULT_MARGIN) -> None:
        self.margin = margin
        self._p = bullet_client.BulletClient(connection_mode=p.DIRECT)
        self._p.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.arm = self._p.loadURDF(W.PANDA_URDF, W.ARM_BASE_POSITION, W.ARM_BASE_QUAT, useFixedBase=True)
        for j in W.FINGER_JOINTS:
            self._p.resetJointState(self.arm, j, W.FINGER_OPEN)
        info = [self._p.getJointInfo(self.arm, j) for j in W.ARM_JOINTS]
        self.lower = np.array([i[8] for i in info])
        self.upper = np.array([i[9] for i in info])
        self.chassis = self._make_box(W.CHASSIS_CENTER, W.CHASSIS_SIZE)
        self._bodies: dict[str, int] = {}
        self._box_key: tuple = ()
        self._attached: Attached | None = None
        self._attached_body: int | None = None

    # scene --------------------------------------------------------------------------------------------
    def _make_box(self, center, size) -> int:
        col = self._p.createCollisionShape(p.GEOM_BOX, halfExtents=[s / 2 for s in size])
        return self._p.createMultiBody(0.0, col, -1, center)

    def set_scene(self, boxes: list[Box], ignore: tuple[str, ...] = (), attached: Attached | None = None) -> None:
        """Obstacles = ``boxes`` minus ``ignore``; ``attached`` is carried by the hand."""
        key = (tuple((b.name, b.center, b.size) for b in boxes if b.name not in ignore),)
        if key != self._box_key:
            for body in self._bodies.values():
                self._p.removeBody(body)
            self._bodies = {b.name: self._make_box(b.center, b.size) for b in boxes if b.name not in ignore}
            self._box_key = key
        if self._attached_body is not None and (attached is None or attached.box.size != self._attached.box.size):
            self._p.removeBody(self._attached_body)
            self._attached_body = None
        if attached is not None and self._attached_body is None:
            self._attached_body = self._make_box((0, 0, -5), attached.box.size)
            for link in HAND_LINKS:
                self._p.setCollisionFilterPair(self._attached_body, self.arm, -1, link, 0)
        self._attached = attached

    # kinematics ---------------------------------------------------------------------------------------
    def set_q(self, q) -> None:
        for j, v in zip(W.ARM_JOINTS, q, strict=True):
            self._p.resetJointState(self.arm, j, float(v))

    def fk(self, q=None) -> tuple[np.ndarray, np.ndarray]:
        """Grasp-link position and quaternion (xyzw) in the robot frame."""
        if q is not None:
            self.set_q(q)
        s = self._p.getLinkState(self.arm, W.EE_LINK, computeForwardKinematics=True)
        return np.array(s[4]), np.array(s[5])

    def _place_attached(self) -> None:
        if self._attached is None or self._attached_body is None:
            return
        pos, orn = self.fk()
        wp, wo = self._p.multiplyTransforms(pos, orn, self._attached.ee_position, self._attached.ee_quat_xyzw)
        self._p.resetBasePositionAndOrientation(self._attached_body, wp, wo)

    # validity -----------------------------------------------------------------------------------------
    def in_limits(self, q) -> bool:
        q = np.asarray(q)
        return bool(np.all(q >= self.lower - 1e-9) and np.all(q <= self.upper + 1e-9))

    def is_valid(self, q) -> bool:
        """Joint limits and clearance >= margin to every box, chassis, and self pairs (see module doc)."""
        if not self.in_limits(q):
            return False
        self.set_q(q)
        return self._collision_free()

    def _near(self, a: int, b: int, link_a: int | None = None, link_b: int | None = None) -> bool:
        kw: dict[str, int] = {}
        if link_a is not None:
            kw["linkIndexA"] = link_a
        if link_b is not None:
            kw["linkIndexB"] = link_b
        return bool(self._p.getClosestPoints(a, b, self.margin, **kw))

    def _collision_free(self) -> bool:
        for body in self._bodies.values():
            if self._near(self.arm, body):
                return False
        for link in range(4, 12):  # links 0-3 sit on the chassis by construction
            if self._near(self.arm, self.chassis, link_a=link):
                return False
        for hand in (8, 9, 10):
            for low in BASE_SIDE_LINKS:
                if self._near(self.arm, self.arm, hand, low):
                    return False
        if self._attached_body is not None:
            self._place_attached()
            ignore = set(self._attached.ignore) if self._attached else set()
            for name, body in self._bodies.items():
                if name not in ignore and self._near(self._attached_body, body):
                    return False
            if self._near(self._attached_body, self.chassis):
                return False
            for link in range(0, 7):
                if self._near(self._attached_body, self.arm, link_b=link):
                    return False
        return True

    def path_valid(self, path, max_step: float = MAX_STEP_RAD / 2) -> tuple[bool, int]:
        """Dense check: every state and interpolated states at most ``max_step`` apart. (ok, bad index)"""
        for i, q in enumerate(densify(path, max_step)):
            if not self.is_valid(q):
                return False, i
        return True, -1

    # IK -------------------------------------------------------------------------------------------------
    def ik(
        self,
        position,
        quat_xyzw,
        seed_q,
        restarts: int = 24,
        rng: np.random.Generator | None = None,
        check_collision: bool = True,
    ) -> np.ndarray | None:
        """Joint vector reaching the grasp-link pose, verified by FK and (optionally) collision-free.

        Starts from ``seed_q``, then ``READY_Q``, then random restarts; returns the valid solution closest to ``seed_q``
        among the first few found, or None.
        """
        rng = rng or np.random.default_rng(0)
        seed_q = np.asarray(seed_q, dtype=float)
        ranges = [*list(self.upper - self.lower), 0.04, 0.04]
        lower = [*list(self.lower), 0.0, 0.0]
        upper = [*list(self.upper), 0.04, 0.04]
        best, best_d, found = None, math.inf, 0
        for attempt in range(restarts + 1):
            start = seed_q if attempt == 0 else np.asarray(READY_Q) if attempt == 1 else rng.uniform(self.lower, self.upper)
            q = self._ik_from(start, position, quat_xyzw, lower, upper, ranges, seed_q)
            if q is None or (check_collision and not self.is_valid(q)):
                continue
            d = float(np.linalg.norm(q - seed_q))
            if d < best_d:
                best, best_d = q, d
            found += 1
            if found >= 3 or (attempt == 0 and d < 1.0):
                break
        return best

    def _ik_from(self, start, position, quat, lower, upper, ranges, rest) -> np.ndarray | None:
        self.set_q(start)
        q = np.asarray(start, dtype=float)
        for _ in range(4):
            sol = self._p.calculateInverseKinematics(
                self.arm,
                W.EE_LINK,
                position,
                quat,
                lowerLimits=lower,
                upperLimits=upper,
                jointRanges=ranges,
                restPoses=[*list(rest), 0.04, 0.04],
                maxNumIterations=200,
                residualThreshold=1e-6,
            )
            q = np.clip(np.array(sol[:7]), self.lower, self.upper)
            if self._pose_error_ok(q, position, quat):
                return q
        return None

    def _pose_error_ok(self, q, position, quat) -> bool:
        pos, orn = self.fk(q)
        if np.linalg.norm(pos - np.asarray(position)) > IK_POS_TOL:
            return False
        dot = abs(float(np.dot(orn, np.asarray(quat) / np.linalg.norm(quat))))
        return 2 * math.acos(min(1.0, dot)) < IK_ANGLE_TOL

    def close(self) -> None:
        try:
            self._p.disconnect()
        except p.error:
            pass


def densify(path, max_step: float) -> list[np.ndarray]:
    """Linear interpolation so that no joint moves more than ``max_step`` between states."""
    path = [np.asarray(q, dtype=float) for q in path]
    if len(path) < 2:
        return path
    out = [path[0]]
    for a, b in itertools.pairwise(path):
        n = max(1, math.ceil(float(np.max(np.abs(b - a))) / max_step))
        out.extend(a + (b - a) * (k / n) for k in range(1, n + 1))
    return out


# --- one OMPL query (runs inside a worker) -------------------------------------------------------------
def solve_once(model: CollisionModel, request: dict, planner_name: str, should_stop) -> PlanResult:
    """Plan one query with one OMPL planner in this process; ``should_stop()`` cancels it."""
    from ompl import base as ob
    from ompl import geometric as og

    t0 = time.perf_counter()
    boxes = [Box.from_dict(b) for b in request["boxes"]]
    attached = Attached.from_dict(request["attached"]) if request.get("attached") else None
    model.margin = request.get("margin", DEFAULT_MARGIN)
    model.set_scene(boxes, tuple(request.get("ignore", ())), attached)
    start, goal = np.asarray(request["start"]), np.asarray(request["goal"])
    if not model.is_valid(start):
        return PlanResult(False, reason="start state in collision", planner=planner_name)
    if not model.is_valid(goal):
        return PlanResult(False, reason="goal state in collision", planner=planner_name)
    space = ob.RealVectorStateSpace(7)
    bounds = ob.RealVectorBounds(7)
    for i in range(7):
        bounds.setLow(i, float(model.lower[i]))
        bounds.setHigh(i, float(model.upper[i]))
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    si.setStateValidityChecker(lambda s: model.is_valid([s[i] for i in range(7)]))
    si.setStateValidityCheckingResolution(CHECK_RESOLUTION_RAD / space.getMaximumExtent())
    si.setup()
    s, g = space.allocState(), space.allocState()
    for i in range(7):
        s[i], g[i] = float(start[i]), float(goal[i])
    pdef = ob.ProblemDefinition(si)
    pdef.setStartAndGoalStates(s, g)
    planner = getattr(og, planner_name)(si)
    planner.setProblemDefinition(pdef)
    planner.setup()
    remaining = max(0.01, request["time_budget_s"] - (time.perf_counter() - t0))
    ptc = ob.plannerOrTerminationCondition(
        ob.timedPlannerTerminationCondition(remaining), ob.PlannerTerminationCondition(should_stop)
    )
    planner.solve(ptc)
    if not pdef.hasExactSolution():
        return PlanResult(
            False,
            planner=planner_name,
            planning_time_s=time.perf_counter() - t0,
            reason="cancelled" if should_stop() else "no exact solution within budget",
        )
    path = pdef.getSolutionPath()
    simplify(og, si, path)
    states = [[path.getState(k)[i] for i in range(7)] for k in range(path.getStateCount())]
    dense = [q.tolist() for q in densify(states, MAX_STEP_RAD)]
    ok, bad = model.path_valid(dense)
    elapsed = time.perf_counter() - t0
    if not ok:
        return PlanResult(False, planner=planner_name, planning_time_s=elapsed, reason=f"dense check failed at {bad}")
    return PlanResult(True, dense, planner_name, elapsed, 1, "ok")


def simplify(og, si, path) -> None:
    """Deterministic-given-RNG simplification: shortcut, vertex reduction, rope shortcut."""
    ps = og.PathSimplifier(si)
    ps.reduceVertices(path)
    ps.partialShortcutPath(path)
    ps.ropeShortcutPath(path)
    ps.collapseCloseVertices(path)


# --- worker processes ----------------------------------------------------------------------------------
def _worker_main(index: int, conn, cancel, seed: int, planners: tuple[str, ...]) -> None:
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_ERROR)
    ou.RNG.setSeed(int(seed) + index)
    model = CollisionModel()
    planner_name = planners[index % len(planners)]
    conn.send(("ready", index))
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            break
        if msg is None:
            break
        req_id, request = msg
        try:
            res = solve_once(model, request, planner_name, cancel.is_set)
        except Exception as exc:  # report, never kill the pool
            res = PlanResult(False, planner=planner_name, reason=f"error: {exc!r}")
        res.worker = index
        conn.send((req_id, res))
    model.close()
    os._exit(0)  # skip nanobind's leak report at interpreter shutdown


class IkSolver:
    """Inverse kinematics checked against a scene, in this process: a collision model and a seeded random source
    for the restarts. The Planner uses one; so does the coordinator (one per robot), which turns goal poses into
    joint goals.

    The collision model holds one scene at a time, so setting the scene and solving in it is one step under
    ``lock``: a solver shared by threads (the coordinator's robots once shared one) would otherwise check a
    solution against whichever scene another thread set last, and hand the planner a goal that collides in
    its own scene."""

    def __init__(self, margin: float = DEFAULT_MARGIN, seed: int = 0) -> None:
        self.model = CollisionModel(margin)
        self.rng = np.random.default_rng(seed)
        self.lock = threading.RLock()

    def ik(
        self,
        position,
        quat_xyzw,
        seed_q,
        boxes: list[Box] | None = None,
        ignore: tuple[str, ...] = (),
        attached: Attached | None = None,
    ) -> np.ndarray | None:
        """IK (see ``CollisionModel.ik``) checked against ``boxes`` minus ``ignore``."""
        with self.lock:
            self.model.set_scene(boxes or [], ignore, attached)
            return self.model.ik(position, quat_xyzw, seed_q, rng=self.rng)


class Planner:
    """A persistent pool of planning processes plus a local collision model for IK and checks."""

    def __init__(
        self,
        parallel: int = 4,
        planners: tuple[str, ...] = DEFAULT_PLANNERS,
        seed: int = 0,
        deterministic: bool = False,
        margin: float = DEFAULT_MARGIN,
    ) -> None:
        for name in planners:
            if name not in SUPPORTED_PLANNERS:
                raise ValueError(f"unsupported planner {name!r}; choose from {SUPPORTED_PLANNERS}")
        self.parallel = max(1, int(parallel))
        self.planners = tuple(planners)
        self.deterministic = deterministic
        self.margin = margin
        self._ik = IkSolver(margin, seed)
        self.model = self._ik.model
        ctx = mp.get_context("spawn")
        self._cancel = ctx.Event()
        self._conns = []
        self._procs = []
        for i in range(self.parallel):
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=_worker_main,
                args=(i, child, self._cancel, seed * 1000 + 1, self.planners),
                daemon=True,
                name=f"kuberos-planner-{i}",
            )
            proc.start()
            self._conns.append(parent)
            self._procs.append(proc)
        for conn in self._conns:
            conn.recv()  # ("ready", i)
        self._req = 0

    def worker_planners(self) -> list[str]:
        return [self.planners[i % len(self.planners)] for i in range(self.parallel)]

    def plan(
        self,
        start_q,
        goal_q,
        boxes: list[Box],
        attached: Attached | None = None,
        time_budget_s: float = 1.0,
        ignore: tuple[str, ...] = (),
        seed: int | None = None,
    ) -> PlanResult:
        """Joint-space plan from ``start_q`` to ``goal_q`` avoiding ``boxes`` (minus ``ignore``).

        Returns within ``time_budget_s`` plus the time to simplify/validate the winner and to drain the
        cancelled workers (typically a few ms). ``seed`` is accepted for API symmetry; OMPL seeds are per
        worker process (see module doc).
        """
        del seed
        t0 = time.perf_counter()
        self._req += 1
        request = {
            "start": [float(v) for v in start_q],
            "goal": [float(v) for v in goal_q],
            "boxes": [b.to_dict() for b in boxes],
            "attached": attached.to_dict() if attached else None,
            "ignore": list(ignore),
            "time_budget_s": float(time_budget_s),
            "margin": self.margin,
        }
        if np.max(np.abs(np.asarray(start_q) - np.asarray(goal_q))) < 1e-6:
            return PlanResult(True, [list(map(float, start_q))], "trivial", 0.0, 0, "start equals goal")
        self._cancel.clear()
        for conn in self._conns:
            conn.send((self._req, request))
        results = self._collect(self._req)
        winner = self._pick(results)
        winner.planning_time_s = time.perf_counter() - t0
        winner.attempts = len(results)
        if not winner.solved:
            winner.reason = "; ".join(sorted({f"{r.planner}: {r.reason}" for r in results}))
        return winner

    def _collect(self, req_id: int) -> list[PlanResult]:
        pending = {i: conn for i, conn in enumerate(self._conns)}
        results: list[PlanResult] = []
        while pending:
            ready = mp.connection.wait(list(pending.values()))
            for conn in ready:
                rid, res = conn.recv()
                if rid != req_id:
                    continue
                results.append(res)
                pending = {i: c for i, c in pending.items() if c is not conn}
                if res.solved and not self.deterministic:
                    self._cancel.set()
        return results

    def _pick(self, results: list[PlanResult]) -> PlanResult:
        solved = [r for r in results if r.solved]
        if not solved:
            return PlanResult(False, planner=",".join(self.worker_planners()), reason="")
        if self.deterministic:
            return min(solved, key=lambda r: r.worker)
        return min(solved, key=lambda r: r.planning_time_s)

    def ik(
        self,
        position,
        quat_xyzw,
        seed_q,
        boxes: list[Box] | None = None,
        ignore: tuple[str, ...] = (),
        attached: Attached | None = None,
    ) -> np.ndarray | None:
        """IK (see ``IkSolver.ik``) with this planner's margin."""
        self.model.margin = self.margin
        return self._ik.ik(position, quat_xyzw, seed_q, boxes, ignore, attached)

    def plan_pose(
        self,
        start_q,
        position,
        quat_xyzw,
        boxes: list[Box],
        attached: Attached | None = None,
        time_budget_s: float = 1.0,
        ignore: tuple[str, ...] = (),
        ik_seed=None,
    ) -> PlanResult:
        """IK for the grasp-link pose (seeded by ``ik_seed`` or ``start_q``), then ``plan``."""
        t0 = time.perf_counter()
        goal = self.ik(position, quat_xyzw, start_q if ik_seed is None else ik_seed, boxes, ignore, attached)
        if goal is None:
            return PlanResult(False, planner="ik", planning_time_s=time.perf_counter() - t0, reason="no IK solution")
        res = self.plan(start_q, goal, boxes, attached, max(0.05, time_budget_s - (time.perf_counter() - t0)), ignore)
        res.planning_time_s = time.perf_counter() - t0
        return res

    def check_path(
        self, path, boxes: list[Box], attached: Attached | None = None, ignore: tuple[str, ...] = ()
    ) -> tuple[bool, int]:
        """Dense validity of a path in the local model."""
        with self._ik.lock:
            self.model.set_scene(boxes, ignore, attached)
            return self.model.path_valid(path)

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=2.0)
            if proc.is_alive():
                proc.terminate()
        self._conns, self._procs = [], []
        self.model.close()

    def __enter__(self) -> Planner:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
