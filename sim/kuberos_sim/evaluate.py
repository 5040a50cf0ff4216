"""The evaluation: deployment strategies x fleet sizes x workload rates, each run for real, and the table.

    python -m kuberos_sim.evaluate                      # the full matrix into sim/results/
    python -m kuberos_sim.evaluate --strategies edge-dedicated --robots 1 --rates 6 --cycles 2 --out /tmp/x
    python -m kuberos_sim.evaluate --seeds 1-3          # every combination with seeds 1, 2 and 3

For every combination and seed: write the site inventory and the strategy's RosDeployment
(kuberos_sim.scenario), render them with the deploy playbook, start the rendered deployment with the simulation
runtime (one network namespace per node, link delays from the inventory, CPU quotas per node class), start each
robot's physics on its robot's host once every motion planner is ready, wait until every robot's coordinator is
ready (planner and controller
matched, scene and joint states arrived; at most --startup-limit), then until every robot finished its pick
cycles (at most --time-limit from then), and reduce the modules' result records to one row
(kuberos_sim.metrics). The seed chooses each robot's scene (cube and obstacle positions), the planners' OMPL
seeds and the coordinator's IK restarts. The time and CPU figures cover the workload only: the window starts
once every robot is ready, so the modules' start-up (imports, worker processes, discovery) is reported apart
(`startup_s`). Rows (one per seed) go to `results.json`, the table (median and min-max over the seeds) to
`results.md`, the plots to PNGs, all in --out, with the command, commit and machine.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import os
import platform
import shutil
import subprocess
import sys
import time

from kuberos_pnp import common

from kuberos_sim import metrics, scenario

PHYSICS = "python3 -m kuberos_pnp.robot"
STARTUP_LIMIT = 600.0  # s for every robot's coordinator to find its planner, controller, scene and joint states
BURST_LINGER_S = 240.0  # edge-burst: s after the last cycle for the scale-down, the drain and the VMs' release


def rendered_inventory(rendered: str):
    """The resource model deploy placed against, read back from the deployment record it rendered."""
    from kuberos_sim.scaler import load_record

    return load_record(rendered).inventory


def git_commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=scenario.ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            cpu = next(line.split(":", 1)[1].strip() for line in handle if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{os.cpu_count()} cores ({cpu}), {memory:.0f} GiB, {platform.system()} {platform.release()}"


def progress(message: str) -> None:
    print(f"[{datetime.datetime.now():%H:%M:%S}] {message}", flush=True)


def run_name(strategy: str, robots: int, rate: float, seed: int) -> str:
    return f"{strategy}-r{robots}-t{rate:g}-s{seed}"


def run_one(
    strategy: str,
    robots: int,
    rate: float,
    cycles: int,
    out: str,
    seed: int,
    time_limit: float,
    cpu_scale: float,
    startup_limit: float = STARTUP_LIMIT,
) -> dict:
    from kuberos_sim.cloud import SimCloud
    from kuberos_sim.runtime import Runtime
    from kuberos_sim.runtime.runtime import machine_cpu_seconds
    from kuberos_sim.scaler import SimScaler, load_record

    directory = os.path.join(out, "runs", run_name(strategy, robots, rate, seed))
    # A rerun into the same directory starts clean: the figures are read from the processes' logs, which append.
    shutil.rmtree(os.path.join(directory, "run"), ignore_errors=True)
    os.makedirs(directory, exist_ok=True)
    inventory = scenario.site_inventory(robots, strategy)
    inventory_file = scenario.write_yaml(os.path.join(directory, "inventory.yml"), inventory)
    spec = scenario.strategy_spec(strategy, rate, cycles, seed=seed, startup_timeout=startup_limit)
    spec_file = scenario.write_yaml(os.path.join(directory, "pick-and-place.yml"), spec)
    rendered = os.path.join(directory, "rendered")
    scenario.render(spec_file, inventory_file, rendered, os.path.join(directory, "render.log"))
    model = rendered_inventory(rendered)
    tiers = {node: model.nodes[node].tier for node in model.nodes}
    with Runtime(rendered, model, os.path.join(directory, "run"), cpu_scale=cpu_scale) as runtime:
        launched = time.monotonic()
        runtime.start()
        # The robots' physics starts once every planner runs its worker processes: on this one machine the
        # physics of 8 robots, catching up with the wall clock, otherwise starves the modules' start (planners
        # took more than a minute to start their workers), which a real site's separate computers do not see.
        planners_ready = wait_for_planners(runtime, planner_count(runtime), startup_limit)
        env = robot_env(runtime)
        for robot in scenario.robot_names(robots):
            runtime.start_on(
                robot,
                f"physics-{robot}",
                [*PHYSICS.split(), "--ros-args", "-p", f"seed:={seed}", "-p", f"objects:={cycles}"],
                {**env, "KUBEROS_ROBOT_NAME": robot, "KUBEROS_NODE_NAME": robot},
                cgroup="hardware",
            )
        ready, not_ready = wait_for_ready(runtime, robots, max(30.0, startup_limit + 30 - (time.monotonic() - launched)))
        burst = SimCloud(runtime, scenario.FLEET, latency_ms=scenario.CLOUD_RTT_MS) if strategy == "edge-burst" else None
        scaler = SimScaler(runtime, load_record(rendered), cloud=burst).start() if strategy in scenario.SCALED else None
        started = time.monotonic()
        cpu_start, machine_start, fabric_start = runtime.cpu_seconds(), machine_cpu_seconds(), runtime.fabric_cpu_seconds()
        finished = wait_for_cycles(runtime, robots, cycles, time_limit) if ready else False
        window = time.monotonic() - started
        cpu_end, machine_end, fabric_end = runtime.cpu_seconds(), machine_cpu_seconds(), runtime.fabric_cpu_seconds()
        records = collect(runtime)
        fabric = runtime.fabric_stats()
        if burst is not None:  # after the peak: the scaler goes on until the VMs are drained and released
            wait_for_release(burst, BURST_LINGER_S)
        if scaler is not None:
            scaler.stop()
        if burst is not None:
            burst.release_all()
    if burst is not None:
        tiers.update({name: "cloud" for name in burst.vms})  # the hosts the run's VMs were
    cpu = cpu_by_tier(cpu_start, cpu_end, tiers)
    startup_cpu = cpu_by_tier({}, cpu_start, tiers)
    sim_seconds = sum(max(0.0, cpu_end[k] - cpu_start.get(k, 0.0)) for k in cpu_end)
    fabric_seconds = max(0.0, fabric_end - fabric_start)
    outside = machine_end["busy"] - machine_start["busy"] - sim_seconds - fabric_seconds
    row = {
        "strategy": strategy,
        "rate_per_min": rate,
        "seed": seed,
        **metrics.summarize(records, cpu, window, robots),
        "robots_ready": len(ready),
        "startup_s": round(started - launched, 1),
        "planners_ready_s": planners_ready,
        "startup_cpu_s": round(sum(v for k, v in startup_cpu.items() if k != "sim"), 1),
        # CPU outside the run's cgroups during the window: the fabric, and everything else on this machine (this
        # process, the kernel's work not charged to a group, other people's work: a row measured beside a busy
        # neighbour is not comparable), and the cores a hypervisor took away (steal).
        "cpu_fabric_cores": round(fabric_seconds / window, 3) if window > 0 else None,
        "cpu_outside_cores": round(max(0.0, outside) / window, 3) if window > 0 else None,
        "cpu_steal_cores": round((machine_end["steal"] - machine_start["steal"]) / window, 3) if window > 0 else None,
        "finished": finished and not not_ready,
        "commit": git_commit(),
    }
    if not_ready:
        row["not_ready"] = not_ready
    if scaler is not None:
        row["scaling"] = scaling_summary(scaler, window)
    if burst is not None:
        row["burst"] = burst_summary(burst, scaler, records, window)
    with open(os.path.join(directory, "records.json"), "w", encoding="utf-8") as handle:
        json.dump({"row": row, "records": records, "fabric": fabric}, handle, indent=1, default=str)
    return row


def wait_for_release(burst, limit: float) -> None:
    """Until every VM the burst launched is released (its instances scaled down and drained, the fleet quiet for
    the release time), or ``limit`` seconds."""
    if not burst.live():
        return
    progress(f"  after the peak: waiting up to {limit:.0f} s for the cloud VMs to be released")
    deadline = time.monotonic() + limit
    while burst.live() and time.monotonic() < deadline:
        time.sleep(1.0)


def burst_summary(burst, scaler, records: list[dict], window: float) -> dict:
    """VMs provisioned and released (times in seconds since every robot was ready), the planner instances that ran on
    them, and the planning latency of the requests those planners answered."""
    found = burst.summary()
    vms = set(burst.vms)
    plans = [r for r in records if r.get("kind") == "plan" and r.get("planner_node") in vms]
    served = [r["latency_ms"] for r in plans if r.get("latency_ms") is not None and r.get("reason") != "timeout"]
    found.update(
        {
            "window_s": round(window, 1),
            "instances_on_vms": sorted(name for name, node in scaler.placed.items() if node in vms),
            "plans_served_from_vms": len(served),
            "vm_plan_p50_ms": None if not served else round(metrics.percentile(served, 50), 1),
        }
    )
    return found


def scaling_summary(scaler, window: float) -> dict:
    """The planner's instances over the run (time-weighted mean, most), the steps taken and the timeline."""
    points = [(t["t"], t["instances"]) for t in scaler.timeline]
    weighted = sum((b[0] - a[0]) * a[1] for a, b in itertools.pairwise(points))
    span = points[-1][0] - points[0][0] if len(points) > 1 else 0.0
    return {
        "instances_mean": round(weighted / span, 2) if span > 0 else (points[0][1] if points else None),
        "instances_max": max((p[1] for p in points), default=None),
        "steps": [e for t in scaler.timeline for e in t["events"]],
        "errors": scaler.errors,
        "timeline": [{k: t[k] for k in ("t", "instances", "running", "value", "vms")} for t in scaler.timeline],
        "window_s": round(window, 1),
    }


def robot_env(runtime) -> dict[str, str]:
    """The ROS environment of the fleet's modules (discovery servers, domain), for the robots' physics."""
    return {
        k: v
        for k, v in runtime.fleet_env().items()
        if k in ("ROS_DISCOVERY_SERVER", "ROS_DOMAIN_ID", "RMW_IMPLEMENTATION", "KUBEROS_FLEET")
    }


def planner_count(runtime) -> int:
    """How many motion-planner processes the rendered deployment runs."""
    return sum(
        1
        for d in runtime.rendered.deployments.values()
        if d.pod_labels.get("kuberos.io/module") == "motion-planner" and d.replicas
    )


def wait_for_planners(runtime, planners: int, limit: float) -> float | None:
    """Until `planners` planners logged `planner_ready` (worker processes started, subscriptions made), at most
    `limit` s; the seconds it took, None if not all within the limit."""
    started = time.monotonic()
    last = -1
    while time.monotonic() - started < limit:
        count = sum(1 for r in collect(runtime) if r.get("kind") == "planner_ready")
        if count != last:
            progress(f"  {count}/{planners} motion planners ready")
            last = count
        if count >= planners:
            return round(time.monotonic() - started, 1)
        problem = runtime.check()
        if problem:
            raise RuntimeError(problem)
        time.sleep(1.0)
    return None


def readiness(records: list[dict], robots: int) -> tuple[list[str], dict[str, str]]:
    """The robots whose coordinator logged them ready, and those it gave up on at start (robot -> reason)."""
    ready = sorted({r["robot"] for r in records if r.get("kind") == "ready"})
    gave_up = {r["robot"]: r.get("reason", "") for r in records if r.get("kind") == "idle" and r.get("startup")}
    names = scenario.robot_names(robots)
    return [n for n in names if n in ready], {n: gave_up[n] for n in names if n in gave_up and n not in ready}


def wait_for_ready(runtime, robots: int, limit: float) -> tuple[list[str], dict[str, str]]:
    """Until every robot is ready or given up (`ready`/`idle` records of the coordinators), at most `limit` s.
    Returns the ready robots and the others with why (a robot nobody answered for within `limit` too)."""
    deadline = time.monotonic() + limit
    last = None
    while True:
        ready, gave_up = readiness(collect(runtime), robots)
        if (len(ready), len(gave_up)) != last:
            progress(f"  {len(ready)}/{robots} robots ready" + (f", {len(gave_up)} given up" if gave_up else ""))
            last = (len(ready), len(gave_up))
        if len(ready) + len(gave_up) == robots:
            return ready, gave_up
        if time.monotonic() > deadline:
            missing = {n: f"not ready within {limit:.0f} s" for n in scenario.robot_names(robots) if n not in ready}
            return ready, {**missing, **gave_up}
        problem = runtime.check()
        if problem:
            raise RuntimeError(problem)
        time.sleep(1.0)


def wait_for_cycles(runtime, robots: int, cycles: int, time_limit: float) -> bool:
    """Until every robot ran its cycles (or has no target left, or was given up at start), at most `time_limit` s.
    True when every robot got there."""
    deadline = time.monotonic() + time_limit
    last = -1
    while time.monotonic() < deadline:
        records = collect(runtime)
        done_robots = {r["robot"] for r in records if r.get("kind") == "idle"}
        counts: dict[str, int] = {}
        for r in records:
            if r.get("kind") == "cycle":
                counts[r["robot"]] = counts.get(r["robot"], 0) + 1
        done = sum(1 for robot in scenario.robot_names(robots) if counts.get(robot, 0) >= cycles or robot in done_robots)
        total = sum(counts.values())
        if total != last:
            progress(f"  {total}/{robots * cycles} pick cycles done")
            last = total
        if done == robots:
            time.sleep(1.0)  # one more physics report with the final state
            return True
        problem = runtime.check()
        if problem:
            raise RuntimeError(problem)
        time.sleep(1.0)
    return False


def collect(runtime) -> list[dict]:
    records = []
    for log in runtime.logs():
        try:
            with open(log, encoding="utf-8", errors="replace") as handle:
                records.extend(common.read_results(handle.read()))
        except OSError:
            continue
    return records


def cpu_by_tier(start: dict, end: dict, tiers: dict[str, str]) -> dict[str, float]:
    """CPU seconds used between two readings per node class; the physics (`hardware` cgroups) as `sim`."""
    used: dict[str, float] = {}
    for key, seconds in end.items():
        host, group = key
        tier = "sim" if group == "hardware" else tiers.get(host, "edge")
        used[tier] = used.get(tier, 0.0) + max(0.0, seconds - start.get(key, 0.0))
    return used


def previous_rows(out: str) -> dict[tuple, dict]:
    """Rows of an earlier invocation into the same directory that ran without error and ran cycles, by (strategy,
    robots, rate, seed); a row without a seed ran with the invocation's one."""
    try:
        with open(os.path.join(out, "results.json"), encoding="utf-8") as handle:
            previous = json.load(handle)
        rows = previous["rows"]
    except (OSError, ValueError, KeyError):
        return {}
    default_seed = (previous.get("seeds") or [previous.get("seed", 1)])[0]
    for row in rows:
        row.setdefault("commit", previous.get("commit"))
        row.setdefault("seed", default_seed)
    return {
        (r["strategy"], r["robots"], r["rate_per_min"], r["seed"]): r
        for r in rows
        if "error" not in r and r.get("cycles") and r.get("robots_ready", r["robots"]) == r["robots"]
    }


def seed_list(text: str) -> list[int]:
    """`1-3` -> [1, 2, 3]; `1,4,9` and `1-3,7` as they read."""
    seeds: list[int] = []
    for part in text.split(","):
        if not part.strip():
            continue
        low, _, high = part.strip().partition("-")
        seeds.extend(range(int(low), int(high or low) + 1))
    if not seeds:
        raise ValueError(f"no seed in {text!r}")
    return list(dict.fromkeys(seeds))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kuberos_sim.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--strategies", default=",".join(scenario.MATRIX),
        help=f"comma separated, of {', '.join(scenario.STRATEGIES)} (default: {', '.join(scenario.MATRIX)})",
    )  # fmt: skip
    parser.add_argument("--robots", default="1,2,4,8", help="fleet sizes, comma separated (default: 1,2,4,8)")
    parser.add_argument("--rates", default="4,12", help="tasks per minute per robot, comma separated (default: 4,12)")
    parser.add_argument("--cycles", type=int, default=3, help="pick cycles per robot (= objects on its table; default 3)")
    parser.add_argument(
        "--seeds", default=None, help="seeds, e.g. 1-3 or 1,4,9: every combination runs once per seed (default 1)"
    )
    parser.add_argument("--seed", type=int, default=None, help="one seed (the same as --seeds N)")
    parser.add_argument(
        "--time-limit",
        type=float,
        default=240,
        help="seconds per run, from every robot ready, before it is cut off (default 240)",
    )
    parser.add_argument(
        "--startup-limit",
        type=float,
        default=STARTUP_LIMIT,
        help=f"seconds for every robot to become ready before the run starts without it (default {STARTUP_LIMIT:g})",
    )
    parser.add_argument("--cpu-scale", type=float, default=0.125, help="cgroup cores per inventory CPU (default 0.125)")
    parser.add_argument("--out", default=os.path.join(scenario.ROOT, "sim", "results"))
    parser.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows of --out/results.json that ran pick cycles without error; run the others",
    )
    args = parser.parse_args(argv)
    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    unknown = [s for s in strategies if s not in scenario.STRATEGIES]
    if unknown:
        parser.error(f"unknown strategies {', '.join(unknown)}; choose from {', '.join(scenario.STRATEGIES)}")
    try:
        sizes = [int(x) for x in args.robots.split(",")]
        rates = [float(x) for x in args.rates.split(",")]
    except ValueError as error:
        parser.error(f"--robots and --rates take comma-separated numbers: {error}")
    if args.seeds is not None and args.seed is not None:
        parser.error("--seed and --seeds: give one of them")
    try:
        seeds = seed_list(args.seeds) if args.seeds is not None else [args.seed if args.seed is not None else 1]
    except ValueError:
        parser.error(f"--seeds {args.seeds!r}: expected numbers and ranges such as 1-3 or 1,4,9")
    args.out = os.path.abspath(args.out)  # the deploy playbook resolves relative render paths elsewhere
    os.makedirs(args.out, exist_ok=True)
    header = {
        "command": " ".join(["python -m kuberos_sim.evaluate", *(argv if argv is not None else sys.argv[1:])]),
        "commit": git_commit(),  # of this invocation; each row has the commit it ran with
        "machine": machine(),
        "date": f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M UTC}",
        "cycles_per_robot": args.cycles,
        "seeds": seeds,
        "cpu_scale": args.cpu_scale,
        "time_limit_s": args.time_limit,
        "startup_limit_s": args.startup_limit,
    }
    done = previous_rows(args.out) if args.resume else {}
    rows = []
    for strategy in strategies:
        for robots in sizes:
            for rate in rates:
                for seed in seeds:
                    if (strategy, robots, rate, seed) in done:
                        rows.append(done[(strategy, robots, rate, seed)])
                        continue
                    progress(f"{strategy}, {robots} robot(s), {rate:g} tasks/min, seed {seed}")
                    try:
                        row = run_one(
                            strategy,
                            robots,
                            rate,
                            args.cycles,
                            args.out,
                            seed,
                            args.time_limit,
                            args.cpu_scale,
                            args.startup_limit,
                        )
                    except (RuntimeError, OSError) as error:
                        progress(f"  failed: {error}")
                        row = {
                            "strategy": strategy,
                            "robots": robots,
                            "rate_per_min": rate,
                            "seed": seed,
                            "error": str(error)[:500],
                        }
                    rows.append(row)
                    progress(
                        "  "
                        + ", ".join(
                            f"{k}={v}"
                            for k, v in row.items()
                            if k
                            in (
                                "success_rate",
                                "plan_p50_ms",
                                "plan_p95_ms",
                                "cycle_p50_s",
                                "rtf_min",
                                "startup_s",
                                "robots_ready",
                            )
                        )
                    )
                    with open(os.path.join(args.out, "results.json"), "w", encoding="utf-8") as handle:
                        json.dump({**header, "rows": rows}, handle, indent=1)
    from kuberos_sim import report

    report.write(args.out, {**header, "rows": rows})
    progress(f"results in {args.out}: results.md, results.json, *.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
