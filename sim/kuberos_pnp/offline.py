"""The whole pick-and-place loop without ROS: camera -> perception -> planning -> toppra -> physics.

    python -m kuberos_pnp.offline --seed 1 --robots 10 --objects 3 [--cycles 3] [--parallel 2] [--json out.json]

For each robot (an independent ``RobotWorld`` with seed ``seed + r``) the head camera is read once, the
boxes are perceived, and every target is picked and placed on the platform (at most ``--cycles`` per
robot). Every motion step is planned with ``planning.Planner``, timed with
``trajectory.time_parameterize`` and executed by stepping the physics in simulated time, feeding
``set_joint_targets`` from the trajectory each step. A cycle succeeds when the ground-truth count of
objects on the platform went up by one. The summary reports the success rate, p50/p95 planning time
per query and the real-time factor of the physics stepping (simulated time / wall time spent stepping,
planning excluded).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from . import perception_core, tasks, trajectory
from . import world as W
from .perception_core import Box
from .planning import Planner, PlanResult

SETTLE_TOL = 0.01  # rad: the arm is considered at the goal below this tracking error
MAX_SETTLE_S = 0.5
GRIPPER_S = 0.15


@dataclass
class CycleReport:
    robot_seed: int
    target: str
    success: bool
    planning_s: list[float] = field(default_factory=list)
    planners: list[str] = field(default_factory=list)
    exec_sim_s: float = 0.0
    step_wall_s: float = 0.0
    toppra_ms: list[float] = field(default_factory=list)
    fallbacks: int = 0
    reason: str = ""


class Executor:
    """Runs trajectories and gripper commands on a RobotWorld in simulated time."""

    def __init__(self, world: W.RobotWorld) -> None:
        self.world = world
        self.sim_s = 0.0
        self.wall_s = 0.0

    def _step(self, n: int = 1) -> None:
        t0 = time.perf_counter()
        self.world.step(n)
        self.wall_s += time.perf_counter() - t0
        self.sim_s += n * self.world.time_step

    def run(self, traj: trajectory.Trajectory) -> float:
        """Follow ``traj`` (one physics step per control tick), then settle; returns final tracking error."""
        dt = self.world.time_step
        n = int(np.ceil(traj.duration / dt))
        for k in range(1, n + 1):
            q, qd = traj.sample(k * dt)
            self.world.set_joint_targets(q, qd)
            self._step()
        goal = traj.positions[-1]
        self.world.set_joint_targets(goal)
        err = float(np.max(np.abs(self.world.joint_positions() - goal)))
        for _ in range(int(MAX_SETTLE_S / dt)):
            if err < SETTLE_TOL:
                break
            self._step()
            err = float(np.max(np.abs(self.world.joint_positions() - goal)))
        return err

    def gripper(self, closed: bool) -> bool:
        ok = self.world.set_gripper(closed)
        self._step(int(GRIPPER_S / self.world.time_step))
        return ok

    def wait(self, seconds: float) -> None:
        self._step(int(seconds / self.world.time_step))


def plan_step(planner: Planner, step: tasks.Step, q, boxes: list[Box], goals: dict, budget: float) -> PlanResult:
    """Plan one motion step from ``q``; retries once with twice the budget."""
    res = PlanResult(False, reason="not planned")
    for attempt in range(2):
        b = budget * (1 + attempt)
        if step.joint_goal is not None:
            res = planner.plan(q, step.joint_goal, boxes, step.carry, b, step.ignore)
        else:
            seed = goals.get(step.ik_seed_from, q)
            res = planner.plan_pose(q, step.pose[0], step.pose[1], boxes, step.carry, b, step.ignore, ik_seed=seed)
        if res.solved:
            return res
    return res


def choose_yaw(planner: Planner, target: Box, q, boxes: list[Box]) -> tuple[float, np.ndarray | None]:
    """First grasp yaw for which pregrasp and grasp have IK solutions (cubes: 90-degree symmetric).

    Returns the yaw and the pregrasp joint goal (None if no yaw works).
    """
    for yaw in tasks.GRASP_YAWS:
        pos, quat = tasks.pregrasp_pose(target, yaw)
        pre = planner.ik(pos, quat, q, boxes)
        if pre is None:
            continue
        gpos, gquat = tasks.grasp_pose(target, yaw)
        if planner.ik(gpos, gquat, pre, boxes, ignore=(target.name,)) is not None:
            return yaw, pre
    return tasks.GRASP_YAWS[0], None


def run_cycle(
    world: W.RobotWorld, planner: Planner, ex: Executor, boxes: list[Box], target: Box, platform: Box, slot: int, budget: float
) -> CycleReport:
    """One pick-and-place cycle; on any failure the arm is sent home and the cycle reported failed."""
    report = CycleReport(world.seed, target.name, False)
    before = world.objects_on_platform()
    sim0, wall0 = ex.sim_s, ex.wall_s
    yaw, pre_q = choose_yaw(planner, target, world.joint_positions(), boxes)
    goals: dict[str, np.ndarray] = {}
    lim = world.joint_limits
    for step in tasks.pick_cycle_steps(target, platform, slot, yaw):
        if step.kind == "gripper":
            ok = ex.gripper(bool(step.close_gripper))
            if step.close_gripper and not ok:
                report.reason = "nothing between the fingers"
                break
            continue
        if step.name == "pregrasp" and pre_q is not None:
            step = replace(step, joint_goal=tuple(pre_q))
        res = plan_step(planner, step, world.joint_positions(), boxes, goals, budget)
        report.planning_s.append(res.planning_time_s)
        report.planners.append(res.planner)
        if not res.solved:
            report.reason = f"{step.name}: {res.reason}"
            break
        traj = trajectory.time_parameterize(res.path, lim.velocity, lim.acceleration, dt=world.time_step)
        report.toppra_ms.append(traj.compute_ms)
        report.fallbacks += traj.method == "trapezoidal"
        ex.run(traj)
        goals[step.name] = np.asarray(res.path[-1])
    if report.reason:
        recover(world, planner, ex, boxes, budget)
    ex.wait(0.2)
    report.success = not report.reason and world.objects_on_platform() == before + 1
    if not report.success and not report.reason:
        report.reason = "object not on the platform"
    report.exec_sim_s = ex.sim_s - sim0
    report.step_wall_s = ex.wall_s - wall0
    return report


def recover(world: W.RobotWorld, planner: Planner, ex: Executor, boxes: list[Box], budget: float) -> None:
    """Open the gripper and go home (ignoring the table contact of a dropped object)."""
    ex.gripper(False)
    res = planner.plan(world.joint_positions(), tasks.home_q, boxes, None, 2 * budget)
    if res.solved:
        lim = world.joint_limits
        ex.run(trajectory.time_parameterize(res.path, lim.velocity, lim.acceleration, dt=world.time_step))


def run_robot(
    seed: int, n_objects: int, max_cycles: int, planner: Planner, budget: float, log=print
) -> tuple[list[CycleReport], dict]:
    world = W.RobotWorld(seed, n_objects)
    try:
        t0 = time.perf_counter()
        frame = world.camera()
        cam_ms = (time.perf_counter() - t0) * 1e3
        boxes, pstats = perception_core.perceive(frame)
        platform = tasks.platform_of(boxes)
        targets = tasks.order_targets(boxes)
        info = {
            "seed": seed,
            "camera_ms": cam_ms,
            "perception_ms": pstats["total_ms"],
            "targets_seen": len(targets),
            "targets_true": world.n_targets(),
        }
        ex = Executor(world)
        reports = []
        if platform is None:
            return [CycleReport(seed, "-", False, reason="platform not perceived")], info
        for slot, target in enumerate(targets[:max_cycles]):
            rep = run_cycle(world, planner, ex, boxes, target, platform, slot, budget)
            reports.append(rep)
            if rep.success:
                boxes = tasks.update_after_place(boxes, target, platform, slot)
            log(
                f"seed {seed} {target.name}: {'OK ' if rep.success else 'FAIL'} plan "
                f"[{', '.join(f'{t * 1e3:.0f}' for t in rep.planning_s)}] ms, exec {rep.exec_sim_s:.2f} s sim "
                f"({rep.step_wall_s:.2f} s wall){'' if rep.success else ' - ' + rep.reason}"
            )
        info["on_platform"] = world.objects_on_platform()
        return reports, info
    finally:
        world.close()


def summarize(reports: list[CycleReport], infos: list[dict]) -> dict:
    plans = np.array([t for r in reports for t in r.planning_s]) if reports else np.zeros(0)
    toppra_ms = np.array([t for r in reports for t in r.toppra_ms]) if reports else np.zeros(0)
    sim_s = sum(r.exec_sim_s for r in reports)
    wall_s = sum(r.step_wall_s for r in reports)
    ok = sum(r.success for r in reports)
    return {
        "cycles": len(reports),
        "successes": ok,
        "success_rate": ok / len(reports) if reports else 0.0,
        "robots": len(infos),
        "planning_queries": len(plans),
        "planning_p50_ms": float(np.percentile(plans, 50) * 1e3) if len(plans) else None,
        "planning_p95_ms": float(np.percentile(plans, 95) * 1e3) if len(plans) else None,
        "toppra_p50_ms": float(np.percentile(toppra_ms, 50)) if len(toppra_ms) else None,
        "toppra_fallbacks": int(sum(r.fallbacks for r in reports)),
        "exec_sim_s": sim_s,
        "step_wall_s": wall_s,
        "real_time_factor": sim_s / wall_s if wall_s else None,
        "perception_ms_mean": float(np.mean([i["perception_ms"] for i in infos])) if infos else None,
        "camera_ms_mean": float(np.mean([i["camera_ms"] for i in infos])) if infos else None,
        "targets_missed_by_perception": int(sum(i["targets_true"] - i["targets_seen"] for i in infos)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--robots", type=int, default=1, help="independent worlds, seeds seed..seed+robots-1")
    ap.add_argument("--objects", type=int, default=3, help="target cubes per world (1-4)")
    ap.add_argument("--cycles", type=int, default=4, help="max pick cycles per robot")
    ap.add_argument("--parallel", type=int, default=2, help="planner worker processes")
    ap.add_argument("--budget", type=float, default=1.0, help="planning time budget per query (s)")
    ap.add_argument("--deterministic", action="store_true", help="wait for all planners, lowest worker wins")
    ap.add_argument("--json", help="write the reports and summary here")
    args = ap.parse_args(argv)
    reports: list[CycleReport] = []
    infos: list[dict] = []
    with Planner(parallel=args.parallel, seed=args.seed, deterministic=args.deterministic) as planner:
        for r in range(args.robots):
            reps, info = run_robot(args.seed + r, args.objects, args.cycles, planner, args.budget)
            reports += reps
            infos.append(info)
    summary = summarize(reports, infos)
    print("summary: " + json.dumps(summary, indent=None, default=float))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"summary": summary, "robots": infos, "cycles": [asdict(r) for r in reports]}, fh, indent=1)
    return 0 if summary["success_rate"] >= 0.95 else 1


if __name__ == "__main__":
    sys.exit(main())
