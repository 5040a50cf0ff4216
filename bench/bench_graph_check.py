"""The live graph check's time for a 10-robot and a 100-robot fleet (docs/software.md, "Declared topics").

Real rclpy and Fast DDS on loopback: a fast-discovery-server, and one process holding every robot's modules
(bench/ros_fleet_graph.py: per robot a perception node publishing ``detections`` best effort at 10 Hz, a planner
subscribing it and publishing ``plan`` reliable, a coordinator subscribing that). The declarations come from a
RosDeployment through ``kuberos.topics.expectations``, as the deploy gives them; the probe
(``ros_graph_probe --topics --json``) is the program the check pod runs, started as a process here the way the pod
starts it. Per fleet size and repeat (alternating sizes): wall seconds from the probe's start to its exit, the
seconds until every declared endpoint was discovered, and the rate window (fixed, ``--window``). Also the ratio of
the 100-robot to the 10-robot time.

Run: .venv/bin/python bench/bench_graph_check.py [--repeat 3] [--window 3] [--json bench/results/graph_check.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, ".collections")]

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import expectations  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import ros_environment  # noqa: E402

PROBE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe"
FLEET = os.path.join(ROOT, "bench", "ros_fleet_graph.py")
SPEC = """\
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata: {name: graph-bench, targetFleet: bench}
rosModules:
- name: perception
  image: reg/perception:1
  launch: perceive
  topics:
    publishes:
    - {name: detections, type: std_msgs/msg/String, qos: {reliability: best_effort}, rate: {min: 5, max: 20}}
- name: planner
  image: reg/planner:1
  launch: plan
  topics:
    subscribes:
    - {name: detections, type: std_msgs/msg/String, qos: {reliability: best_effort}}
    publishes:
    - {name: plan, type: std_msgs/msg/String}
- name: coordinator
  image: reg/coordinator:1
  launch: coordinate
  topics:
    subscribes:
    - {name: plan, type: std_msgs/msg/String}
"""


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def run_one(robots: int, window: float, timeout: float) -> dict:
    python = os.path.join(sys.prefix, "bin", "python3")
    port = _free_udp_port()
    with tempfile.TemporaryDirectory(prefix="kuberos-bench-graph-") as logs:
        env = {
            **ros_environment(log_dir=logs),
            "ROS_DISCOVERY_SERVER": f"127.0.0.1:{port}",
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
            "ROS_DOMAIN_ID": str(30 + port % 60),
            "PYTHONPATH": os.path.join(ROOT, ".collections"),
        }
        names = [f"robot-{i}" for i in range(1, robots + 1)]
        (deployment,) = load_rosdeployments(SPEC, "graph-bench.yml")
        declared = json.dumps([e.to_dict() for e in expectations(deployment.modules)])
        server = subprocess.Popen(["fast-discovery-server", "-i", "0", "-l", "127.0.0.1", "-p", str(port)], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)  # fmt: skip
        fleet = subprocess.Popen([python, FLEET, ",".join(names), "10"], env=env, stdout=subprocess.PIPE, text=True)
        try:
            if fleet.stdout.readline().strip() != "up":
                raise RuntimeError("the fleet's modules did not start")
            time.sleep(1.0)
            started = time.monotonic()
            done = subprocess.run(
                [python, "-m", PROBE, "--topics", "--json", "--timeout", f"{timeout:g}", "--window", f"{window:g}"],
                env={**env, "KUBEROS_ROBOTS": ",".join(names), "KUBEROS_TOPICS": declared, "ROS_SUPER_CLIENT": "TRUE"},
                capture_output=True, text=True, timeout=timeout + window + 120,
            )  # fmt: skip
            wall = time.monotonic() - started
        finally:
            for process in (fleet, server):
                process.kill()
                process.wait(10)
    report = json.loads(done.stdout.splitlines()[0]) if done.stdout.startswith("{") else {}
    rates = [t["rate"] for t in report.get("topics", []) if t.get("rate") is not None]
    return {
        "robots": robots,
        "topics_checked": len(report.get("topics", [])),
        "exit": done.returncode,
        "problems": report.get("problems", [done.stderr.strip()[-300:]])[:5],
        "wall_s": round(wall, 2),
        "discovery_s": report.get("discovery_s"),
        "probe_s": report.get("seconds"),
        "rate_median_hz": round(statistics.median(rates), 2) if rates else None,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", maxsplit=1)[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--window", type=float, default=3.0)
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--sizes", default="10,100")
    parser.add_argument("--json", default="")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    runs = []
    for repeat in range(args.repeat):
        for size in sizes:
            run = run_one(size, args.window, args.timeout)
            run["repeat"] = repeat
            runs.append(run)
            print(json.dumps(run), flush=True)
    summary = {}
    for size in sizes:
        mine = [r for r in runs if r["robots"] == size]
        summary[str(size)] = {
            "wall_s_median": statistics.median(r["wall_s"] for r in mine),
            "discovery_s_median": statistics.median(r["discovery_s"] or 0 for r in mine),
            "all_passed": all(r["exit"] == 0 for r in mine),
            "topics_checked": mine[0]["topics_checked"],
        }
    if len(sizes) == 2:
        small, large = (summary[str(s)]["wall_s_median"] for s in sizes)
        summary["ratio_wall"] = round(large / small, 2) if small else None
    result = {
        "benchmark": "graph_check",
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "command": " ".join(["bench/bench_graph_check.py", *sys.argv[1:]]),
        "commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip(),
        "window_s": args.window,
        "summary": summary,
        "runs": runs,
    }
    print(json.dumps(result["summary"], indent=2))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(result, handle, indent=2)
            handle.write("\n")
    return 0 if all(r["exit"] == 0 for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
