#!/usr/bin/env python3
"""Benchmark of ``scheduler.place_modules`` on synthetic fleets.

For each size N (robots) it builds, in plain data:

* an inventory of N robots (fleets of 50 robots, each robot an onboard node with CPU, memory
  and a gripper), 20 edge nodes and 10 cloud nodes (some with GPUs), sized so that everything
  places;
* one RosDeployment per fleet with the four modules of a pick-and-place app: perception
  (edge, then cloud; max_latency 20 ms), motion-planner (cloud; max_latency 200 ms),
  controller (onboard) and task-coordinator (shared, 4 robots per instance, edge).

Only ``place_modules(deployments, inventory)`` is timed (median and minimum of ``--repeat``
runs), each run on a freshly built ``Inventory`` as in a real deploy (the Inventory caches each
fleet's edge/cloud node list on first use; a second, "warm" call on the same object is reported
apart). Parsing the inventory and the specs is timed once and reported separately. Peak Python
memory of one placement call is measured with tracemalloc in a separate, untimed run, and each
size runs in a fresh subprocess pinned to CPU 0 so that its max RSS (getrusage) is its own.

    .venv/bin/python bench/bench_scheduler.py                      # 100, 1000, 10000 robots
    .venv/bin/python bench/bench_scheduler.py --sizes 1000 --repeat 9
"""

from __future__ import annotations

import argparse
import gc
import itertools
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

from workload import pick_and_place  # bench/ is on sys.path when a benchmark runs

REPO = Path(__file__).resolve().parent.parent
COLLECTIONS = REPO / ".collections"

ROBOTS_PER_FLEET = 50
EDGE_NODES = 20
CLOUD_NODES = 10
MODULES = ("perception", "motion-planner", "controller", "task-coordinator")
ROBOTS_PER_SHARED_INSTANCE = 4

MAX_SIZE = 30_000  # the fixed 20 edge nodes' capacity (1000 CPUs each) fits about 37,000 robots
MAX_REPEAT = 50
MIN_REPEAT_WHEN_SLOW = 3

TARGET_ROBOTS = 1000
TARGET_SECONDS = 1.0
TARGET_PEAK_MB = 200.0


# -- synthetic input -----------------------------------------------------------------------
def fleet_names(robots: int) -> list[str]:
    return [f"fleet-{i:03d}" for i in range(math.ceil(robots / ROBOTS_PER_FLEET))]


def make_inventory(robots: int) -> dict:
    """The plain-data inventory ``inventory.load_inventory`` accepts."""
    hosts: dict[str, dict] = {}
    groups: dict[str, list[str]] = {"robots": [], "edge": [], "cloud": []}
    fleets = fleet_names(robots)
    for i in range(robots):
        name = f"robot-{i:05d}"
        hosts[name] = {
            "kuberos_fleet": fleets[i // ROBOTS_PER_FLEET],
            "kuberos_cpu": 4,
            "kuberos_memory": "8Gi",
            "kuberos_devices": ["gripper", "camera"],
        }
        groups["robots"].append(name)
    # Synthetic and deliberately large: 10,000 robots put 10,000 perception instances, 2,500
    # task coordinators and 400 discovery servers on the edge, and 10,000 planners in the cloud.
    for i in range(EDGE_NODES):
        name = f"edge-{i:02d}"
        hosts[name] = {"kuberos_cpu": 1000, "kuberos_memory": "2Ti", "kuberos_pods": 5000, "kuberos_gpu": 2 if i % 4 == 0 else 0}
        groups["edge"].append(name)
    for i in range(CLOUD_NODES):
        name = f"cloud-{i:02d}"
        hosts[name] = {"kuberos_cpu": 4000, "kuberos_memory": "16Ti", "kuberos_pods": 5000, "kuberos_gpu": 8 if i < 4 else 0}
        groups["cloud"].append(name)
    return {"hosts": hosts, "groups": groups, "default_latency_ms": {"edge": 5, "cloud": 50}}


def make_spec(fleet: str) -> dict:
    """One pick-and-place RosDeployment for ``fleet``, as loaded YAML."""
    return pick_and_place(f"pnp-{fleet}", fleet, "shared", ROBOTS_PER_SHARED_INSTANCE)


def expected_instances(robots: int) -> int:
    dedicated = 3 * robots
    shared = sum(
        math.ceil(min(ROBOTS_PER_FLEET, robots - f * ROBOTS_PER_FLEET) / ROBOTS_PER_SHARED_INSTANCE)
        for f in range(len(fleet_names(robots)))
    )
    return dedicated + shared


def check_placement(placement, robots: int) -> None:
    """Fail loudly if the placement is not the complete one the synthetic input should give."""
    want = expected_instances(robots)
    got = len(placement.instances)
    if got != want:
        raise SystemExit(f"bench: placed {got} instances for {robots} robots, expected {want}")
    tiers = {"perception": "edge", "motion-planner": "cloud", "controller": "onboard", "task-coordinator": "edge"}
    served = dict.fromkeys(MODULES, 0)
    for inst in placement.instances:
        if inst.tier != tiers[inst.module]:
            raise SystemExit(f"bench: {inst.name} placed on {inst.tier} ({inst.node}), expected {tiers[inst.module]}")
        served[inst.module] += len(inst.robots)
    if any(count != robots for count in served.values()):
        raise SystemExit(f"bench: robots served per module {served}, expected {robots} each")


# -- one size, in a fresh process ----------------------------------------------------------
def max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kilobytes on Linux


def run_worker(robots: int, repeat: int, budget: float) -> dict:
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    sys.path.insert(0, str(COLLECTIONS))
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import inventory, scheduler, spec

    rss_imports = max_rss_mb()
    raw_inventory = make_inventory(robots)
    raw_specs = [make_spec(fleet) for fleet in fleet_names(robots)]

    start = time.perf_counter()
    model = inventory.load_inventory(raw_inventory)
    inventory_s = time.perf_counter() - start
    start = time.perf_counter()
    deployments = [spec.parse_rosdeployment(data, f"<spec {data['metadata']['targetFleet']}>") for data in raw_specs]
    specs_s = time.perf_counter() - start
    rss_inputs = max_rss_mb()

    def fresh():
        # Inventory caches each fleet's edge/cloud nodes (tier_nodes) on first use. A deploy loads the
        # inventory and places once, so every timed run gets a new Inventory (built untimed).
        return inventory.Inventory(model.nodes, model.robots)

    # Untimed warm-up that also checks the result is the full, correct placement.
    placement = scheduler.place_modules(deployments, fresh())
    check_placement(placement, robots)
    placed = len(placement.instances)
    del placement

    times: list[float] = []
    warm: list[float] = []
    runs = repeat
    for index in range(repeat):
        cold_model = fresh()
        gc.collect()
        start = time.perf_counter()
        result = scheduler.place_modules(deployments, cold_model)
        times.append(time.perf_counter() - start)
        del result
        gc.collect()
        start = time.perf_counter()
        result = scheduler.place_modules(deployments, cold_model)  # tier_nodes cache already filled
        warm.append(time.perf_counter() - start)
        del result, cold_model
        if index == 0 and (times[0] + warm[0]) * repeat > budget:
            runs = min(repeat, max(MIN_REPEAT_WHEN_SLOW, int(budget // max(times[0] + warm[0], 1e-9))))
        if len(times) >= runs:
            break

    cold_model = fresh()
    gc.collect()
    tracemalloc.start()
    result = scheduler.place_modules(deployments, cold_model)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    del result, cold_model

    return {
        "robots": robots,
        "fleets": len(raw_specs),
        "nodes": len(model.nodes),
        "placed": placed,
        "runs": len(times),
        "times": times,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "warm_times": warm,
        "warm_median_s": statistics.median(warm),
        "peak_mb": peak / 1024**2,
        "max_rss_mb": max_rss_mb(),
        "rss_imports_mb": rss_imports,
        "rss_inputs_mb": rss_inputs,
        "inventory_s": inventory_s,
        "specs_s": specs_s,
        "cpus": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
    }


# -- driver --------------------------------------------------------------------------------
def positive_size(text: str) -> int:
    value = int(text.replace(",", "").replace("_", ""))
    if not 1 <= value <= MAX_SIZE:
        raise argparse.ArgumentTypeError(f"{text} is not a size from 1 to {MAX_SIZE}")
    return value


def repeat_count(text: str) -> int:
    value = int(text)
    if not 1 <= value <= MAX_REPEAT:
        raise argparse.ArgumentTypeError(f"{text} is not a repeat count from 1 to {MAX_REPEAT}")
    return value


def positive_seconds(text: str) -> float:
    value = float(text)
    if not 0 < value <= 86400:
        raise argparse.ArgumentTypeError(f"{text} is not a number of seconds from 0 to 86400")
    return value


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=(
            "Time kuberos scheduler.place_modules on synthetic fleets: N robots (fleets of 50) x 4 pick-and-place "
            "modules over N onboard + 20 edge + 10 cloud nodes. Each size runs in a fresh subprocess pinned to CPU 0; "
            "prints a markdown table of median/min seconds, tracemalloc peak and max RSS, and the growth ratios."
        ),
        epilog=(
            f"Target (from the issue): {TARGET_ROBOTS} robots x 4 modules under {TARGET_SECONDS:g} s median and "
            f"under {TARGET_PEAK_MB:g} MB peak memory on one core. A growth ratio near 10 per 10x robots is linear."
        ),
    )
    parser.add_argument(
        "--sizes",
        type=positive_size,
        nargs="+",
        default=[100, 1000, 10000],
        metavar="N",
        help=f"robot counts to benchmark, 1..{MAX_SIZE} (default: 100 1000 10000)",
    )
    parser.add_argument(
        "--repeat",
        type=repeat_count,
        default=5,
        metavar="R",
        help=f"timed placement runs per size, 1..{MAX_REPEAT}; the median is reported (default: 5)",
    )
    parser.add_argument(
        "--budget",
        type=positive_seconds,
        default=120.0,
        metavar="SECONDS",
        help=(
            "if R runs of a size would exceed this many seconds (judged from the first run), do fewer, "
            f"but at least {MIN_REPEAT_WHEN_SLOW} (default: 120)"
        ),
    )
    parser.add_argument(
        "--timeout",
        type=positive_seconds,
        default=1800.0,
        metavar="SECONDS",
        help="kill a size's subprocess after this many seconds (default: 1800)",
    )
    parser.add_argument("--json", action="store_true", help="also print the raw per-size results as JSON")
    parser.add_argument("--worker", type=positive_size, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def run_size(robots: int, args: argparse.Namespace) -> dict:
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--worker",
        str(robots),
        "--repeat",
        str(args.repeat),
        "--budget",
        str(args.budget),
    ]
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=args.timeout, check=False)
    except subprocess.TimeoutExpired:
        raise SystemExit(f"bench: {robots} robots did not finish within {args.timeout:g} s") from None
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise SystemExit(f"bench: the worker for {robots} robots failed (exit {proc.returncode})")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def ratio(results: dict[int, dict], big: int, small: int) -> str:
    if big in results and small in results and results[small]["median_s"] > 0:
        return f"{results[big]['median_s'] / results[small]['median_s']:.2f}"
    return "n/a"


def render(results: dict[int, dict]) -> str:
    lines = [
        "| robots | instances placed | runs | median s | min s | peak MB (tracemalloc) | max RSS MB |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for robots, r in sorted(results.items()):
        lines.append(
            f"| {robots:,} | {r['placed']:,} | {r['runs']} | {r['median_s']:.4f} | {r['min_s']:.4f} "
            f"| {r['peak_mb']:.1f} | {r['max_rss_mb']:.1f} |"
        )
    sizes = sorted(results)
    if len(sizes) > 1:
        lines.append("")
    for small, big in itertools.pairwise(sizes):
        lines.append(
            f"- growth time({big:,})/time({small:,}) = {ratio(results, big, small)} "
            f"(size ratio {big / small:g}; linear = size ratio)"
        )
    lines += [
        "",
        "Not timed above: parsing (once per size), and placement again on the same Inventory (warm tier_nodes cache):",
        "",
        "| robots | fleets | nodes | load_inventory s | parse_rosdeployment s (all fleets) | warm median s "
        "| RSS after imports MB | RSS after inputs MB |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for robots, r in sorted(results.items()):
        lines.append(
            f"| {robots:,} | {r['fleets']} | {r['nodes']:,} | {r['inventory_s']:.4f} | {r['specs_s']:.4f} "
            f"| {r['warm_median_s']:.4f} | {r['rss_imports_mb']:.1f} | {r['rss_inputs_mb']:.1f} |"
        )
    if TARGET_ROBOTS in results:
        r = results[TARGET_ROBOTS]
        ok_time = r["median_s"] < TARGET_SECONDS
        ok_mem = r["peak_mb"] < TARGET_PEAK_MB and r["max_rss_mb"] < TARGET_PEAK_MB
        lines += [
            "",
            f"Target {TARGET_ROBOTS:,} robots x 4 modules: median {r['median_s']:.4f} s "
            f"({'meets' if ok_time else 'MISSES'} < {TARGET_SECONDS:g} s), peak {r['peak_mb']:.1f} MB tracemalloc / "
            f"{r['max_rss_mb']:.1f} MB max RSS ({'meets' if ok_mem else 'MISSES'} < {TARGET_PEAK_MB:g} MB).",
        ]
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        print(json.dumps(run_worker(args.worker, args.repeat, args.budget)))
        return 0
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    results: dict[int, dict] = {}
    for robots in sorted(set(args.sizes)):
        print(f"bench: {robots:,} robots ...", file=sys.stderr, flush=True)
        results[robots] = run_size(robots, args)
        print(f"bench: {robots:,} robots: median {results[robots]['median_s']:.4f} s", file=sys.stderr, flush=True)
    print(render(results))
    if args.json:
        print("\n```json\n" + json.dumps(results, indent=1) + "\n```")
    return 0


if __name__ == "__main__":
    sys.exit(main())
