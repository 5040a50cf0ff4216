"""Discovery traffic of a fleet, measured: bytes and packets that Fast DDS discovery puts on the network for N ROS 2
participants, with multicast (simple discovery), with the fleet's two discovery servers, and with the fleet's servers
plus each robot's own server (the collection's design, docs/connectivity.md).

The fleet: N participants on N / --per-robot robots (network namespaces on one bridge, tests/netlab.py), each robot one
process holding its participants (one rclpy context each), every participant with a publisher and a subscription on
its robot's topics (``/r<i>/t<k>``, a ring), and one participant on the edge (``edge-1``) subscribing to every robot's
``/r<i>/t0`` (an edge module that serves the fleet). No message is ever published: every packet is discovery, liveliness
or its acknowledgements. Where they run: the fleet's servers on ``edge-1`` and ``edge-2``; a robot's own server in the
robot's namespace (a pod on the robot's computer: its traffic with the robot's participants never crosses the robot's
link). Multicast: the bridge floods multicast to every port (as a switch without snooping does).

Counted from the bridge ports' counters (the host ends of the veth pairs): ``sent`` is what every namespace put on the
network (RX of its port), ``robot_links`` what crossed the robots' links both ways (RX + TX of the robots' ports, what
a robot's wireless link carries), in two windows from the start of the participants: ``startup`` (the first
--startup seconds: everyone meets) and ``steady`` (the next --steady seconds: announcements and liveliness). Also the
seconds until every subscription had its publisher (``matched_s``; None: not within the startup window).

Run as root: .venv/bin/python bench/bench_discovery_traffic.py [--sizes 10,50,200] [--json
bench/results/discovery_traffic.json]. Every wait is bounded; the namespaces and processes are removed at the end.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), os.path.join(ROOT, ".collections"), os.path.dirname(os.path.abspath(__file__))]

import bench_discovery  # noqa: E402
import discovery_faults as faults  # noqa: E402
from netlab import Lab, Processes  # noqa: E402

DESIGNS = ("multicast", "fleet-servers", "robot-servers")
SERVER_START_TIMEOUT = 60.0

# One robot's participants (argv: robot index, participants, edge: "1" for the edge's subscriber of every robot).
PARTICIPANTS = r"""
import sys, time
import rclpy
from rclpy.context import Context
from std_msgs.msg import String
robot, count, edge = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
nodes, wanted = [], []
def join(name, namespace):
    context = Context()
    rclpy.init(context=context)
    return rclpy.create_node(name, namespace=namespace, context=context)
if edge:
    node = join("fleet_view", "/edge")
    for r in range(robot):  # every robot's first topic
        node.create_subscription(String, f"/r{r}/t0", lambda m: None, 10)
        wanted.append((node, f"/r{r}/t0"))
    nodes.append(node)
else:
    for k in range(count):
        node = join(f"n{k}", f"/r{robot}")
        node.create_publisher(String, f"t{k}", 10)
        node.create_subscription(String, f"t{(k + 1) % count}", lambda m: None, 10)
        wanted.append((node, f"/r{robot}/t{(k + 1) % count}"))
        nodes.append(node)
print("ready", flush=True)
matched = set()
while True:
    for index, (node, topic) in enumerate(wanted):
        if index not in matched and node.count_publishers(topic) > 0:
            matched.add(index)
            print(f"matched {len(matched)}/{len(wanted)} {time.time():.3f}", flush=True)
    time.sleep(0.2)
"""


def counters(port: str) -> dict[str, int]:
    base = f"/sys/class/net/{port}/statistics"
    out = {}
    for key in ("rx_bytes", "rx_packets", "tx_bytes", "tx_packets"):
        with open(os.path.join(base, key), encoding="utf-8") as handle:
            out[key] = int(handle.read())
    return out


def delta(after: dict, before: dict, ports: list[str], keys: tuple[str, ...]) -> int:
    return sum(after[p][k] - before[p][k] for p in ports for k in keys)


def window(lab: Lab, robots: list[str], before: dict, after: dict) -> dict:
    ports = lab.ports
    robot_ports = [ports[list(lab.namespaces).index(r)] for r in robots]
    return {
        "sent_bytes": delta(after, before, ports, ("rx_bytes",)),
        "sent_packets": delta(after, before, ports, ("rx_packets",)),
        "robot_links_bytes": delta(after, before, robot_ports, ("rx_bytes", "tx_bytes")),
        "robot_links_packets": delta(after, before, robot_ports, ("rx_packets", "tx_packets")),
    }


def start_servers(procs: Processes, servers: list[tuple[str, str, int]]) -> None:
    """Discovery servers (name, role, id), started together, each up once it has said so."""
    started = [
        (
            name,
            procs.start(
                name,
                role,
                faults.server_command(server_id, False, delay_s=0),
                faults.server_env(server_id, procs.lab.addresses[role]),
            ),
        )
        for name, role, server_id in servers
    ]  # the rendered servers (their lease and announcements), serving at once: nothing ran before them
    deadline = time.monotonic() + SERVER_START_TIMEOUT
    for name, process in started:
        while "Server ID" not in process.output():
            if process.popen.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"discovery server {name} did not start:\n{process.tail()}")
            time.sleep(0.1)


def traffic(
    lab: Lab, procs: Processes, design: str, robots: list[str], per_robot: int, startup_s: float, steady_s: float
) -> dict:
    """One design's fleet in ``lab`` (namespaces edge-1, edge-2 and ``robots``): its servers, then its participants,
    counted over the two windows."""
    fleet = faults.discovery_servers([lab.addresses["edge-1"], lab.addresses["edge-2"]])
    if design == "multicast":
        lab.set_multicast_flood(True)
    else:
        servers = [("ds-0", "edge-1", 0), ("ds-1", "edge-2", 1)]
        if design == "robot-servers":
            servers += [(f"rs-{r}", r, 2) for r in robots]
        start_servers(procs, servers)

    def env(servers_list: str) -> dict[str, str]:
        out = faults.module_env(servers_list)
        if design == "multicast":
            out.pop("ROS_DISCOVERY_SERVER")
        return out

    ports = list(lab.ports)
    before = {p: counters(p) for p in ports}
    started = time.time()
    workers = []
    for index, robot in enumerate(robots):
        own = f";{lab.addresses[robot]}:{faults.PORT}" if design == "robot-servers" else ""
        command = [sys.executable, "-c", PARTICIPANTS, str(index), str(per_robot), "0"]
        workers.append(procs.start(f"robot-{robot}", robot, command, env(fleet + own)))
    edge = [sys.executable, "-c", PARTICIPANTS, str(len(robots)), "1", "1"]
    workers.append(procs.start("edge-view", "edge-1", edge, env(fleet)))
    time.sleep(max(0.0, started + startup_s - time.time()))
    middle = {p: counters(p) for p in ports}
    outputs = [w.output() for w in workers]
    time.sleep(steady_s)
    end = {p: counters(p) for p in ports}
    last = [re.findall(r"^matched (\d+)/(\d+) ([\d.]+)$", out, re.MULTILINE)[-1:] for out in outputs]
    complete = [float(line[0][2]) for line in last if line and line[0][0] == line[0][1]]
    return {
        "design": design,
        "participants": len(robots) * per_robot + 1,
        "robots": len(robots),
        "subscriptions": len(robots) * per_robot + len(robots),
        "subscriptions_matched": sum(int(line[0][0]) for line in last if line),
        "matched_s": round(max(complete) - started, 1) if len(complete) == len(workers) else None,
        "processes_alive": f"{sum(1 for w in workers if w.popen.poll() is None)}/{len(workers)}",
        "startup": window(lab, robots, before, middle),
        "steady": window(lab, robots, middle, end),
        "startup_s": startup_s,
        "steady_s": steady_s,
    }


def run_one(design: str, size: int, per_robot: int, startup_s: float, steady_s: float) -> dict:
    robots = [f"r{i}" for i in range(max(1, size // per_robot))]
    return bench_discovery.run_one(
        ("edge-1", "edge-2", *robots), traffic, design=design, robots=robots, per_robot=per_robot, startup_s=startup_s,
        steady_s=steady_s,
    )  # fmt: skip


def machine() -> dict:
    def text(*command: str) -> str:
        try:
            return subprocess.run(command, capture_output=True, text=True, check=False).stdout.strip()
        except OSError:
            return ""

    commit = text("git", "-C", ROOT, "rev-parse", "--short", "HEAD")
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "nproc": os.cpu_count(),
        "python": platform.python_version(),
        "kernel": platform.release(),
        "commit": commit,
        "dirty": bool(text("git", "-C", ROOT, "status", "--porcelain")),
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| participants (robots) | design | startup: sent KiB (packets) | steady: sent KiB/s (packets/s) | "
        "robot links, startup KiB | robot links, steady KiB/s | all matched after |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s, t = r["startup"], r["steady"]
        matched = (
            f"{r['matched_s']} s"
            if r["matched_s"] is not None
            else f"not all ({r['subscriptions_matched']}/{r['subscriptions']})"
        )
        lines.append(
            f"| {r['participants']} ({r['robots']}) | {r['design']} | {s['sent_bytes'] / 1024:.0f} ({s['sent_packets']}) | "
            f"{t['sent_bytes'] / 1024 / r['steady_s']:.1f} ({t['sent_packets'] / r['steady_s']:.0f}) | "
            f"{s['robot_links_bytes'] / 1024:.0f} | {t['robot_links_bytes'] / 1024 / r['steady_s']:.1f} | {matched} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", maxsplit=1)[0])
    parser.add_argument("--sizes", default="10,50,200", help="participants on the robots, comma-separated [%(default)s]")
    parser.add_argument("--per-robot", type=int, default=5, help="participants per robot [%(default)s]")
    parser.add_argument("--designs", default=",".join(DESIGNS), help="comma-separated, of " + ", ".join(DESIGNS))
    parser.add_argument("--startup", type=float, default=45.0, help="seconds of the startup window [%(default)s]")
    parser.add_argument("--steady", type=float, default=30.0, help="seconds of the steady window [%(default)s]")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_discovery_traffic: network namespaces need root", file=sys.stderr)
        return 2
    designs = [d for d in args.designs.split(",") if d]
    unknown = [d for d in designs if d not in DESIGNS]
    sizes = [int(s) for s in args.sizes.split(",") if s]
    if unknown or not sizes or min(sizes) < 1 or args.per_robot < 1:
        print(f"bench_discovery_traffic: designs of {DESIGNS}, sizes and --per-robot of 1 or more", file=sys.stderr)
        return 2
    rows = []
    for size in sizes:
        for design in designs:
            print(f"== {size} participants, {design}", file=sys.stderr, flush=True)
            rows.append(run_one(design, size, args.per_robot, args.startup, args.steady))
    print(table(rows))
    if args.json:
        command = "bench/bench_discovery_traffic.py " + " ".join(sys.argv[1:])
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump({"machine": machine(), "command": command, "rows": rows, "table": table(rows)}, handle, indent=1)
            handle.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
