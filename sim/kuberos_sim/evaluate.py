"""The evaluation: deployment strategies x fleet sizes x workload rates, each run for real, and the table.

    python -m kuberos_sim.evaluate                      # the full matrix into sim/results/
    python -m kuberos_sim.evaluate --strategies edge-dedicated --robots 1 --rates 6 --cycles 2 --out /tmp/x

For every combination: write the site inventory and the strategy's RosDeployment (kuberos_sim.scenario),
render them with the deploy playbook, start the rendered deployment with the simulation runtime (one network
namespace per node, link delays from the inventory, CPU quotas per node class), start each robot's physics on
its robot's host, wait until every robot's coordinator finished its pick cycles (or the time limit), and
reduce the modules' result records to one row (kuberos_sim.metrics). Rows go to `results.json`, the table to
`results.md`, the plots to PNGs, all in --out, with the command, commit and machine.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time

from kuberos_pnp import common

from kuberos_sim import metrics, scenario

PHYSICS = "python3 -m kuberos_pnp.robot"


def rendered_inventory(rendered: str):
    """The resource model deploy placed against, read back from the deployment record it rendered."""
    import glob

    import yaml

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_record

    (path,) = glob.glob(os.path.join(rendered, "manifests", "*", "configmap-kuberos-record-*.yaml"))
    with open(path, encoding="utf-8") as handle:
        return parse_record(yaml.safe_load(handle)).inventory


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


def run_one(
    strategy: str, robots: int, rate: float, cycles: int, out: str, seed: int, time_limit: float, cpu_scale: float
) -> dict:
    from kuberos_sim.runtime import Runtime

    name = f"{strategy}-r{robots}-t{rate:g}"
    directory = os.path.join(out, "runs", name)
    os.makedirs(directory, exist_ok=True)
    inventory = scenario.site_inventory(robots)
    inventory_file = scenario.write_yaml(os.path.join(directory, "inventory.yml"), inventory)
    spec_file = scenario.write_yaml(os.path.join(directory, "pick-and-place.yml"), scenario.strategy_spec(strategy, rate, cycles))
    rendered = os.path.join(directory, "rendered")
    scenario.render(spec_file, inventory_file, rendered, os.path.join(directory, "render.log"))
    model = rendered_inventory(rendered)
    tiers = {node: model.nodes[node].tier for node in model.nodes}
    with Runtime(rendered, model, os.path.join(directory, "run"), cpu_scale=cpu_scale) as runtime:
        runtime.start()
        env = robot_env(runtime)
        for robot in scenario.robot_names(robots):
            runtime.start_on(
                robot,
                f"physics-{robot}",
                [*PHYSICS.split(), "--ros-args", "-p", f"seed:={seed}", "-p", f"objects:={cycles}"],
                {**env, "KUBEROS_ROBOT_NAME": robot, "KUBEROS_NODE_NAME": robot},
                cgroup="hardware",
            )
        started = time.monotonic()
        cpu_start = runtime.cpu_seconds()
        finished = wait_for_cycles(runtime, robots, cycles, time_limit)
        window = time.monotonic() - started
        cpu_end = runtime.cpu_seconds()
        records = collect(runtime)
        fabric = runtime.fabric_stats()
    cpu = cpu_by_tier(cpu_start, cpu_end, tiers)
    row = {
        "strategy": strategy,
        "rate_per_min": rate,
        **metrics.summarize(records, cpu, window, robots),
        "finished": finished,
        "commit": git_commit(),
    }
    with open(os.path.join(directory, "records.json"), "w", encoding="utf-8") as handle:
        json.dump({"row": row, "records": records, "fabric": fabric}, handle, indent=1, default=str)
    return row


def robot_env(runtime) -> dict[str, str]:
    """The ROS environment of the fleet's modules (discovery servers, domain), for the robots' physics."""
    return {
        k: v
        for k, v in runtime.fleet_env().items()
        if k in ("ROS_DISCOVERY_SERVER", "ROS_DOMAIN_ID", "RMW_IMPLEMENTATION", "KUBEROS_FLEET")
    }


def wait_for_cycles(runtime, robots: int, cycles: int, time_limit: float) -> bool:
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
    robots, rate)."""
    try:
        with open(os.path.join(out, "results.json"), encoding="utf-8") as handle:
            previous = json.load(handle)
        rows = previous["rows"]
    except (OSError, ValueError, KeyError):
        return {}
    for row in rows:
        row.setdefault("commit", previous.get("commit"))
    return {(r["strategy"], r["robots"], r["rate_per_min"]): r for r in rows if "error" not in r and r.get("cycles")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kuberos_sim.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--strategies", default=",".join(scenario.STRATEGIES), help="comma separated (default: all)")
    parser.add_argument("--robots", default="1,2,4,8", help="fleet sizes, comma separated (default: 1,2,4,8)")
    parser.add_argument("--rates", default="4,12", help="tasks per minute per robot, comma separated (default: 4,12)")
    parser.add_argument("--cycles", type=int, default=3, help="pick cycles per robot (= objects on its table; default 3)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--time-limit", type=float, default=240, help="seconds per run before it is cut off (default 240)")
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
    args.out = os.path.abspath(args.out)  # the deploy playbook resolves relative render paths elsewhere
    os.makedirs(args.out, exist_ok=True)
    header = {
        "command": " ".join(["python -m kuberos_sim.evaluate", *(argv if argv is not None else sys.argv[1:])]),
        "commit": git_commit(),  # of this invocation; each row has the commit it ran with
        "machine": machine(),
        "date": f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M UTC}",
        "cycles_per_robot": args.cycles,
        "seed": args.seed,
        "cpu_scale": args.cpu_scale,
    }
    done = previous_rows(args.out) if args.resume else {}
    rows = []
    for strategy in strategies:
        for robots in sizes:
            for rate in rates:
                if (strategy, robots, rate) in done:
                    rows.append(done[(strategy, robots, rate)])
                    continue
                progress(f"{strategy}, {robots} robot(s), {rate:g} tasks/min")
                try:
                    row = run_one(strategy, robots, rate, args.cycles, args.out, args.seed, args.time_limit, args.cpu_scale)
                except (RuntimeError, OSError) as error:
                    progress(f"  failed: {error}")
                    row = {"strategy": strategy, "robots": robots, "rate_per_min": rate, "error": str(error)[:500]}
                rows.append(row)
                progress(
                    "  "
                    + ", ".join(
                        f"{k}={v}"
                        for k, v in row.items()
                        if k in ("success_rate", "plan_p50_ms", "plan_p95_ms", "cycle_p50_s", "rtf_min")
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
