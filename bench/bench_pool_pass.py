#!/usr/bin/env python3
"""Robot pool benchmark: how long ``playbooks/pool.yml`` takes to free a reserved robot, and to give it back, when
one or several production deployments run modules for it.

On a dedicated local control plane (its own ports and state directory; ``--robots`` robots, kwok nodes) it deploys
N production deployments of the pick-and-place workload (four dedicated modules per robot each, and a robot
discovery server), then reserves ``robot-000`` with ``playbooks/pool.yml`` (the pass: one rollout per deployment at
its current revision, soak ``--soak`` s) and gives it back. Each step is timed from the start of
``ansible-playbook`` to its exit, and checked: after the reservation no production object is left for the robot,
after the release every one is back, and every other object of the namespace (the other robots' and the fleet's
discovery servers) keeps its resourceVersion throughout. The sizes alternate (1, N, 1, N...) so that both see the
same machine; the ratio N : 1 is what to compare. Results print as Markdown and go to
``bench/results/pool_pass.json`` with ``--json``. Every wait is bounded; the cluster is removed at the end.

    .venv/bin/python bench/bench_pool_pass.py --json bench/results/pool_pass.json   (make bench-pool)
    .venv/bin/python bench/bench_pool_pass.py --robots 4 --deployments 2 --rounds 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench_deploy import FLEET, Cluster, check, command_line, log, machine, playbook, write_inventory
from workload import pick_and_place

NAMESPACE = f"kuberos-{FLEET}"
ROBOT = "robot-000"
ROBOT_LABEL = "robot.kuberos.io/name"


def write_specs(directory: Path, count: int) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in range(count):
        path = directory / f"pool-bench-{index}.yml"
        path.write_text(json.dumps(pick_and_place(f"pool-bench-{index}", FLEET, "dedicated"), indent=2) + "\n")
        paths.append(path)
    return paths


def versions(cluster: Cluster) -> dict[str, str]:
    """Every Deployment and Service of the fleet's namespace: name -> resourceVersion."""
    apps, core = cluster.apps(), cluster.core()
    found = {
        f"Deployment/{d.metadata.name}": d.metadata.resource_version for d in apps.list_namespaced_deployment(NAMESPACE).items
    }
    found.update(
        {f"Service/{s.metadata.name}": s.metadata.resource_version for s in core.list_namespaced_service(NAMESPACE).items}
    )
    return found


def robot_objects(cluster: Cluster) -> list[str]:
    """The Deployments that run modules (or a discovery server) for ROBOT."""
    listed = cluster.apps().list_namespaced_deployment(NAMESPACE, label_selector=f"{ROBOT_LABEL}={ROBOT}").items
    return sorted(d.metadata.name for d in listed)


def timed_pool(inventory: Path, cluster: Cluster, args, *extra: str) -> float:
    settings = {"kuberos_kubeconfig": str(cluster.kubeconfig), "rosdeployment_rollout_soak": args.soak,
                "robot": ROBOT, "owner": "bench"}  # fmt: skip
    start = time.monotonic()
    check(playbook("pool.yml", inventory, "-e", json.dumps(settings), *extra, timeout=args.timeout), "the pool's pass")
    return round(time.monotonic() - start, 2)


def one_round(inventory: Path, cluster: Cluster, work: Path, count: int, args) -> dict:
    specs = write_specs(work / f"specs-{count}", count)
    for spec in specs:
        settings = {"kuberos_kubeconfig": str(cluster.kubeconfig), "rosdeployment_file": str(spec),
                    "kuberos_render_dir": str(work / "render" / spec.stem)}  # fmt: skip
        check(playbook("deploy.yml", inventory, "-e", json.dumps(settings), timeout=args.timeout), f"deploying {spec.name}")
    placed = robot_objects(cluster)
    before = versions(cluster)
    others = {k: v for k, v in before.items() if not any(k == f"Deployment/{name}" for name in placed)}
    reserve_s = timed_pool(inventory, cluster, args, "-e", "hold=1h")
    left = robot_objects(cluster)
    during = versions(cluster)
    release_s = timed_pool(inventory, cluster, args, "-e", "state=absent")
    back = robot_objects(cluster)
    after = versions(cluster)
    for spec in specs:
        settings = {"kuberos_kubeconfig": str(cluster.kubeconfig), "rosdeployment_file": str(spec)}
        check(playbook("undeploy.yml", inventory, "-e", json.dumps(settings), timeout=args.timeout), f"removing {spec.name}")
    return {
        "deployments": count,
        "robot_objects": len(placed),
        "reserve_s": reserve_s,
        "release_s": release_s,
        "freed": left == [],
        "returned": back == placed,
        "others_untouched": all(during.get(k) == v and after.get(k) == v for k, v in others.items()),
    }


def markdown(data: dict) -> str:
    m = data["machine"]
    lines = [
        f"### The pool's pass, {data['robots']} robots ({m['date']}, commit {m['commit']})",
        "",
        f"Machine: {m['nproc']} cores ({m['cpu']}), {m['memory']}, Python {m['python']}, load {m['load']}.",
        f"Command: `{data['command']}`. Soak {data['soak']} s; sizes alternate, {data['rounds']} round(s) each.",
        "",
        "| production deployments on the robot | its objects | reserve, robot freed (s, median) "
        "| release, robot back (s, median) | freed, back, others untouched |",
        "|---|---|---|---|---|",
    ]
    for size in data["sizes"]:
        s = data["by_size"][str(size)]
        lines.append(f"| {size} | {s['robot_objects']} | {s['reserve_s']} | {s['release_s']} | {s['freed']}, {s['returned']}, "
                     f"{s['others_untouched']} |")  # fmt: skip
    lines += ["", f"Ratio {data['sizes'][-1]} : {data['sizes'][0]} deployments: reserve {data['ratio_reserve']}, "
                  f"release {data['ratio_release']}."]  # fmt: skip
    return "\n".join(lines)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--deployments", type=int, default=4, help="the larger size (the smaller is 1)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--soak", type=float, default=1.0)
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds any one step may take")
    parser.add_argument("--json", type=Path, help="write the results here (bench/results/pool_pass.json)")
    args = parser.parse_args(argv)
    if not 2 <= args.robots <= 200:
        parser.error("--robots must be 2 to 200")
    if not 2 <= args.deployments <= 10:
        parser.error("--deployments must be 2 to 10")
    if not 1 <= args.rounds <= 5:
        parser.error("--rounds must be 1 to 5")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="kuberos-bench-pool-"))
    inventory = write_inventory(work / "inventory", args.robots, gpus=False)
    cluster = Cluster(inventory, work / "cluster", args.timeout)
    sizes = [1, args.deployments]
    data = {
        "robots": args.robots, "sizes": sizes, "rounds": args.rounds, "soak": args.soak, "machine": machine(),
        "command": command_line(argv, "bench/bench_pool_pass.py"),
    }  # fmt: skip
    runs: dict[int, list[dict]] = {size: [] for size in sizes}
    try:
        log(f"work dir {work}; starting the cluster")
        cluster.start()
        for round_number in range(args.rounds):
            for size in sizes:
                run = one_round(inventory, cluster, work / f"round-{round_number}", size, args)
                log(f"round {round_number + 1}, {size} deployment(s): {run}")
                runs[size].append(run)
    finally:
        stopped = cluster.stop()
        if stopped.returncode != 0:
            log(f"stopping the cluster failed: {stopped.stdout[-2000:]}")
    data["runs"] = {str(size): found for size, found in runs.items()}
    data["by_size"] = {
        str(size): {
            "robot_objects": found[0]["robot_objects"],
            "reserve_s": round(statistics.median(r["reserve_s"] for r in found), 2),
            "release_s": round(statistics.median(r["release_s"] for r in found), 2),
            "freed": all(r["freed"] for r in found),
            "returned": all(r["returned"] for r in found),
            "others_untouched": all(r["others_untouched"] for r in found),
        }
        for size, found in runs.items()
    }
    small, large = data["by_size"][str(sizes[0])], data["by_size"][str(sizes[-1])]
    data["ratio_reserve"] = round(large["reserve_s"] / small["reserve_s"], 2)
    data["ratio_release"] = round(large["release_s"] / small["release_s"], 2)
    print(markdown(data))
    if args.json:
        args.json.write_text(json.dumps(data, indent=2) + "\n")
    ok = all(s["freed"] and s["returned"] and s["others_untouched"] for s in data["by_size"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
