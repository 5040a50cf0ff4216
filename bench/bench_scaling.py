#!/usr/bin/env python3
"""Scaling benchmark: the edge planner scaled on its queue, against one planner per robot and a fixed shared one.

In the simulator (docs/simulation.md; real ROS 2 modules, real physics, real load; as root), for each fleet size of
``--robots`` at ``--rate`` tasks per minute and robot, one after the other in the same invocation:

- ``edge-dedicated``: a planner (and a perception) per robot on the edge servers;
- ``edge-shared``: one planner (and one perception) per 4 robots, fixed;
- ``edge-scaled``: as edge-shared, the planner scaled on ``kuberos_planner_queue_depth`` between 1 and 8 instances
  (``kuberos_sim.scenario.PLANNER_SCALING``) by the controller's scaling step (``kuberos_sim.scaler``).

Then, with ``--burst-robots`` (default 8; 0: none), one ``edge-burst`` run: as edge-scaled on a site whose edge holds
two planners and that has no cloud node; the instances the edge cannot hold make the fleet's demand, cloud VMs are
provisioned for them within the budget (kuberos_sim.cloud: the burst rule of the cloud_vms role; a VM is a new
host of the run) and released after the peak. Its keys: ``vms_provisioned``, ``vms_released`` (by the burst rule,
not at the run's end) and ``burst_sim`` (the VMs' log, the instances that ran on them, the latency they served);
``burst_cluster`` keeps the local-cluster burst figures (tests/cluster/test_burst.py with KUBEROS_BURST_REPORT).

Per run: planning latency p50/p95 as the coordinators measured it, the modules' CPU-seconds (robots, edge and cloud
cgroups over the window from all robots ready to the last cycle; the physics apart) and, for edge-scaled, the
planner's instances over time. The results print as Markdown; ``--json`` writes them (the keys
``dedicated_p50_ms``, ``scaled_p50_ms``, ``dedicated_cpu_s``, ``scaled_cpu_s``, ``latency_ratio`` and ``targets_met``
for the largest fleet size, where scaling acts, the same per size under ``by_robots``, and every run under ``runs``);
``--plot`` draws the instances over time.

    sudo .venv/bin/python bench/bench_scaling.py --json bench/results/scaling.json --plot docs/images/scaling-instances.png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "sim"), os.path.join(ROOT, ".collections")]

from kuberos_sim import evaluate  # noqa: E402

STRATEGIES = ("edge-dedicated", "edge-shared", "edge-scaled")
TARGET_LATENCY_RATIO = 1.25


def cpu_seconds(row: dict) -> float:
    """The modules' CPU over the run: robots', edge and cloud cgroups (cores x window), the physics apart."""
    cores = sum(row.get(k) or 0.0 for k in ("cpu_onboard_cores", "cpu_edge_cores", "cpu_cloud_cores"))
    return round(cores * (row.get("window_s") or 0.0), 1)


def summary(row: dict) -> dict:
    scaled = row.get("scaling") or {}
    return {
        "strategy": row["strategy"],
        "robots": row.get("robots"),
        "seed": row.get("seed"),
        "finished": row.get("finished"),
        "cycles": row.get("cycles"),
        "cycles_ok": row.get("cycles_ok"),
        "plan_p50_ms": row.get("plan_p50_ms"),
        "plan_p95_ms": row.get("plan_p95_ms"),
        "cycle_p50_s": row.get("cycle_p50_s"),
        "cpu_s": cpu_seconds(row),
        "cpu_edge_s": round((row.get("cpu_edge_cores") or 0.0) * (row.get("window_s") or 0.0), 1),
        # from deploy to the last cycle: the start of the modules deploy placed (before the window) counts too, as the
        # start of the planners scaling adds (inside it) does
        "cpu_with_startup_s": round(cpu_seconds(row) + (row.get("startup_cpu_s") or 0.0), 1),
        "window_s": row.get("window_s"),
        "cpu_outside_cores": row.get("cpu_outside_cores"),
        "instances_mean": scaled.get("instances_mean"),
        "instances_max": scaled.get("instances_max"),
        "steps": scaled.get("steps"),
        "timeline": scaled.get("timeline"),
        "error": row.get("error"),
    }


def headline(runs: list[dict], robots: int) -> dict:
    """The issue's keys for one fleet size, and whether the targets hold: scaled within 1.25x of dedicated latency
    (p50) at fewer CPU-seconds than dedicated."""
    by = {r["strategy"]: r for r in runs if r["robots"] == robots}
    found = {
        "headline_robots": robots,
        "dedicated_p50_ms": by.get("edge-dedicated", {}).get("plan_p50_ms"),
        "scaled_p50_ms": by.get("edge-scaled", {}).get("plan_p50_ms"),
        "shared_p50_ms": by.get("edge-shared", {}).get("plan_p50_ms"),
        "dedicated_cpu_s": by.get("edge-dedicated", {}).get("cpu_s"),
        "scaled_cpu_s": by.get("edge-scaled", {}).get("cpu_s"),
        "shared_cpu_s": by.get("edge-shared", {}).get("cpu_s"),
        "dedicated_cpu_with_startup_s": by.get("edge-dedicated", {}).get("cpu_with_startup_s"),
        "scaled_cpu_with_startup_s": by.get("edge-scaled", {}).get("cpu_with_startup_s"),
    }
    if found["dedicated_p50_ms"] and found["scaled_p50_ms"] and found["dedicated_cpu_s"] is not None:
        found["latency_ratio"] = round(found["scaled_p50_ms"] / found["dedicated_p50_ms"], 2)
        found["targets_met"] = found["latency_ratio"] <= TARGET_LATENCY_RATIO and found["scaled_cpu_s"] < found["dedicated_cpu_s"]
    return found


def table(runs: list[dict]) -> str:
    lines = [
        "| robots | strategy | plan p50 ms | plan p95 ms | CPU-s | with start | edge CPU-s | window s | cycles ok | planners |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        planners = f"{r['instances_mean']}, {r['instances_max']}" if r["instances_mean"] is not None else "-"
        lines.append(
            f"| {r['robots']} | {r['strategy']} | {r['plan_p50_ms']} | {r['plan_p95_ms']} | {r['cpu_s']} | "
            f"{r.get('cpu_with_startup_s')} | {r['cpu_edge_s']} | "
            f"{r['window_s']} | {r['cycles_ok']}/{r['cycles']} | {planners} |"
        )
    return "\n".join(lines)


def plot(runs: list[dict], path: str, burst: dict | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted({r["robots"] for r in runs})
    panels = len(sizes) + (1 if burst and burst.get("timeline") else 0)
    fig, axes = plt.subplots(1, panels, figsize=(6 * panels, 3.6), squeeze=False)
    if panels > len(sizes):
        plot_burst(axes[0][-1], burst)
    for axis, robots in zip(axes[0], sizes, strict=False):
        for r in runs:
            if r["robots"] != robots:
                continue
            end = r["window_s"] or 0
            if r["strategy"] == "edge-scaled" and r["timeline"]:
                timeline = list(r["timeline"])
                if timeline[0]["t"] > 0:  # the deployed count before the first step (one planner per 8 robots)
                    timeline.insert(0, {"t": 0.0, "instances": -(-robots // 8), "value": None})
                times = [p["t"] for p in timeline]
                axis.step(times, [p["instances"] for p in timeline], where="post", label="scaled: planners", color="C2")
                values = [p["value"] if p["value"] is not None else float("nan") for p in timeline]
                twin = axis.twinx()
                twin.plot(times, values, color="C2", alpha=0.35, linestyle=":", label="queue per planner")
                twin.set_ylabel("queue per planner (10 s mean)")
            else:
                count = robots if r["strategy"] == "edge-dedicated" else -(-robots // 4)
                axis.hlines(count, 0, end, colors="C0" if r["strategy"] == "edge-dedicated" else "C1",
                            label=f"{r['strategy'].replace('edge-', '')}: planners")  # fmt: skip
        axis.set_title(f"{robots} robots, edge planners over the run")
        axis.set_xlabel("seconds since every robot was ready")
        axis.set_ylabel("planner instances")
        axis.set_ylim(0, robots + 1)
        axis.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot_burst(axis, burst: dict) -> None:
    """The burst run: planners and cloud VMs over time (VMs launched, nodes, released marked)."""
    timeline = burst["timeline"]
    times = [p["t"] for p in timeline]
    axis.step(times, [p["instances"] for p in timeline], where="post", color="C2", label="planners")
    vms, count = [(0.0, 0)], 0  # VMs that are nodes, from the cloud's log (launched VMs boot first)
    for e in burst.get("log", []):
        if e["event"] in ("node", "released") and e["detail"] != "the run ended":
            count += 1 if e["event"] == "node" else -1
            vms.append((e["t"], count))
    end = max(times[-1], vms[-1][0])
    axis.step([t for t, _ in vms] + [end], [n for _, n in vms] + [count], where="post", color="C3", label="cloud VMs (nodes)")
    marks = {"launched": ("^", "VM launched"), "node": ("o", "VM a node"), "released": ("v", "VM released")}
    for event, (marker, label) in marks.items():
        at = [e["t"] for e in burst.get("log", []) if e["event"] == event and e["detail"] != "the run ended"]
        if at:
            axis.plot(at, [0.15] * len(at), marker, color="C3", linestyle="none", label=label)
    if burst.get("window_s"):
        axis.axvline(burst["window_s"], color="grey", linestyle="--", linewidth=0.8, label="last pick cycle")
    axis.set_title(f"{burst['robots']} robots, capped edge: burst to the cloud")
    axis.set_xlabel("seconds since every robot was ready")
    axis.set_ylabel("count")
    axis.set_ylim(0, max([p["instances"] for p in timeline] + [2]) + 1)
    axis.legend(loc="center right", fontsize=7)


def redraw(path_json: str, path_png: str) -> None:
    with open(path_json, encoding="utf-8") as handle:
        found = json.load(handle)
    plot(found["runs"], path_png, found.get("burst_sim"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default="4,8", help="fleet sizes, comma separated (default 4,8; empty: the burst run only)")
    parser.add_argument("--burst-robots", type=int, default=8, help="fleet size of the edge-burst run (default 8; 0: none)")
    parser.add_argument("--rate", type=float, default=12.0, help="pick tasks per minute and robot (default 12)")
    parser.add_argument("--cycles", type=int, default=4, help="pick cycles per robot, 1 to 4 (default 4)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cpu-scale", type=float, default=0.125, help="cgroup cores per inventory CPU (default 0.125)")
    parser.add_argument("--time-limit", type=float, default=600.0, help="seconds per run after start-up (default 600)")
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "out", "scaling"), help="run directories")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--plot", help="draw the planners over time here (PNG)")
    args = parser.parse_args(argv)
    sizes = [int(n) for n in args.robots.split(",") if n.strip()]
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    runs = []
    for robots in sizes:
        for strategy in STRATEGIES:
            evaluate.progress(f"{strategy}, {robots} robots, {args.rate:g} tasks/min, {args.cycles} cycles")
            try:
                row = evaluate.run_one(
                    strategy, robots, args.rate, args.cycles, args.out, args.seed, args.time_limit, args.cpu_scale
                )
            except Exception as exc:  # a failed run is reported, the others still run
                row = {"strategy": strategy, "robots": robots, "error": f"{type(exc).__name__}: {exc}"[:500]}
            runs.append(summary(row))
            evaluate.progress(f"  p50 {runs[-1]['plan_p50_ms']} ms, module CPU {runs[-1]['cpu_s']} s")
    burst = None
    if args.burst_robots:
        evaluate.progress(f"edge-burst, {args.burst_robots} robots, {args.rate:g} tasks/min, {args.cycles} cycles")
        try:
            row = evaluate.run_one(
                "edge-burst", args.burst_robots, args.rate, args.cycles, args.out, args.seed, args.time_limit, args.cpu_scale
            )
        except Exception as exc:  # reported like the others
            row = {"strategy": "edge-burst", "robots": args.burst_robots, "error": f"{type(exc).__name__}: {exc}"[:500]}
        burst = burst_figures(row, started, argv)
        evaluate.progress(f"  VMs provisioned {burst['vms_provisioned']}, released {burst['vms_released']}")
    if runs:
        print(table(runs))
    if burst:
        print(burst_table(burst))
    previous = {}
    if args.json and os.path.exists(args.json):
        with open(args.json, encoding="utf-8") as handle:
            previous = json.load(handle)
    if runs:
        result = dict(headline(runs, sizes[-1]), by_robots={n: headline(runs, n) for n in sizes})
        result.update(
            {
                "target_latency_ratio": TARGET_LATENCY_RATIO,
                "runs": runs,
                "command": " ".join(["bench/bench_scaling.py", *(argv if argv is not None else sys.argv[1:])]),
                "commit": evaluate.git_commit(),
                "machine": f"{os.cpu_count()} cores, {platform.machine()}",
                "date": started,
            }
        )
    else:  # the burst run only: the comparison stays as recorded
        result = {k: v for k, v in previous.items() if k not in BURST_KEYS}
    if burst:
        result.update({"vms_provisioned": burst["vms_provisioned"], "vms_released": burst["vms_released"], "burst_sim": burst})
    else:
        result.update({k: previous[k] for k in ("vms_provisioned", "vms_released", "burst_sim") if k in previous})
    cluster = previous.get("burst_cluster") or previous.get("burst")  # written by tests/cluster/test_burst.py
    if cluster:
        result["burst_cluster"] = cluster
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(result, handle, indent=1)
    if args.plot and (runs or burst):
        plot(runs or result.get("runs", []), args.plot, burst or result.get("burst_sim"))
    return 0


BURST_KEYS = ("vms_provisioned", "vms_released", "burst", "burst_sim", "burst_cluster")


def burst_figures(row: dict, started: str, argv) -> dict:
    """The edge-burst run's figures: VMs provisioned and released by the burst rule, the planners that ran on them,
    their latency, the run's own figures, and the planners and VMs over time."""
    found = dict(row.get("burst") or {})
    scaled = row.get("scaling") or {}
    return {
        "vms_provisioned": found.get("vms_provisioned", 0),
        "vms_released": found.get("vms_released", 0),
        "vms_left_at_end": found.get("vms_left_at_end"),
        "robots": row.get("robots"),
        "finished": row.get("finished"),
        "cycles_ok": row.get("cycles_ok"),
        "cycles": row.get("cycles"),
        "plan_p50_ms": row.get("plan_p50_ms"),
        "plan_p95_ms": row.get("plan_p95_ms"),
        "vm_plan_p50_ms": found.get("vm_plan_p50_ms"),
        "plans_served_from_vms": found.get("plans_served_from_vms"),
        "instances_on_vms": found.get("instances_on_vms"),
        "cpu_s": cpu_seconds(row),
        "window_s": row.get("window_s"),
        "instance_type": found.get("instance_type"),
        "max_vms": found.get("max_vms"),
        "boot_s": found.get("boot_s"),
        "release_after_s": found.get("release_after_s"),
        "log": found.get("log", []),
        "timeline": scaled.get("timeline"),
        "steps": scaled.get("steps"),
        "error": row.get("error") or (scaled.get("errors") or [None])[0],
        "where": "the simulator (kuberos_sim.cloud): real ROS 2 modules; a VM is a new host of the run",
        "command": " ".join(["bench/bench_scaling.py", *(argv if argv is not None else sys.argv[1:])]),
        "commit": evaluate.git_commit(),
        "date": started,
    }


def burst_table(burst: dict) -> str:
    lines = ["| t s | VM event | VM | detail |", "|---|---|---|---|"]
    lines += [f"| {e['t']} | {e['event']} | {e['vm']} | {e['detail']} |" for e in burst["log"]]
    lines.append(
        f"\nplan p50 {burst['plan_p50_ms']} ms (from VMs {burst['vm_plan_p50_ms']} ms over {burst['plans_served_from_vms']}"
        f" requests), cycles {burst['cycles_ok']}/{burst['cycles']}, module CPU {burst['cpu_s']} s"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
