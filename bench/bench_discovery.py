"""Discovery under faults, measured: a discovery server restarted, a robot cut off from the edge (docs/connectivity.md).

Real rclpy processes and the rendered discovery servers in network namespaces on a bridge that floods no multicast
(tests/netlab.py), through the procedures the tests assert on (tests/discovery_faults.py):

- restart: the fleet's servers killed (SIGKILL) and started again after ``--down`` seconds, as a kubelet restarts a
  container (the rendered server then waits out its lease before it serves), ``--repeat`` times each variant: one
  server; the same serving at once (``_at_once``: as rendered before the start delay); one server with its backup
  (``-b``); two servers restarted in turn; two linked servers (each connects to the other) restarted in turn; two
  servers restarted together (one node running both), also serving at once. move (``--only move``): the servers
  named by their Services' addresses (translated as kube-proxy does) and each started again in another namespace
  (a replaced pod: a new address behind the same Service's), stopped (SIGTERM: a goodbye) or killed, in turn or
  together; announcing their Service's address (as rendered) or every address of their own namespace
  (``_pod_address``: as rendered before). Figures, for restart and move: seconds until a participant started
  afterwards meets one that ran before (new meets old; None: not within 60 s), until one that ran before meets one
  started afterwards (old meets new), and the messages a pair matched before lost meanwhile;
- cut: a robot cut off from the edge for ``--cut`` seconds (the cluster's DNS with it): its modules naming the
  fleet's edge server by DNS name (as the collection rendered before), by its Service's address (as rendered now),
  also naming a server on the robot, or naming only a server on the robot that is linked to the edge server.
  Figures: messages the matched onboard pair lost, seconds until an onboard listener started during the cut hears
  the onboard talker (during the cut, or after the link is back), and until an edge listener hears the robot again.

Run as root: .venv/bin/python bench/bench_discovery.py [--repeat 3] [--json bench/results/discovery.json]
(--only restart|move|cut). Every wait is bounded; the namespaces and processes are removed at the end.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), os.path.join(ROOT, ".collections")]

import discovery_faults as faults  # noqa: E402
from netlab import Lab, Processes  # noqa: E402


def run_one(roles: tuple[str, ...], procedure, **options) -> dict:
    lab = Lab()
    directory = tempfile.mkdtemp(prefix="kuberos-bench-discovery-")
    procs = None
    try:
        lab.create_bridge()
        for role in roles:
            lab.add(role)
        procs = Processes(lab, directory)
        figures = procedure(lab, procs, **options)
    finally:
        if procs:
            procs.close()
        lab.close()
    print(json.dumps(figures), flush=True)
    return figures


def summary(rows: list[dict], key: str) -> dict:
    values = [r[key] for r in rows if r[key] is not None]
    return {
        "runs": len(rows),
        "met": len(values),
        "median_s": round(statistics.median(values), 2) if values else None,
        "max_s": max(values) if values else None,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--down", type=float, default=1.0, help="seconds the restarted server is down")
    parser.add_argument("--cut", type=float, default=30.0, help="seconds the robot is cut off")
    parser.add_argument("--only", choices=("restart", "move", "cut"))
    parser.add_argument("--json", help="write the results here")
    parser.add_argument(
        "--connectivity",
        help="also fill onboard_messages_lost_during and discovery_restart_rematch_s of this file "
        "(bench/results/connectivity.json, whose other keys bench_connectivity.py measures on real nodes)",
    )
    args = parser.parse_args()
    if os.geteuid() != 0:
        parser.error("network namespaces need root")
    results: dict = {
        "machine": f"{platform.node()} {os.cpu_count()} cores",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip(),
        "command": " ".join(["bench/bench_discovery.py", *sys.argv[1:]]),
    }
    runs = range(args.repeat)
    restarts = {}
    if args.only in (None, "restart"):
        restarts |= {
            "restart_one_server": {"servers": 1},
            "restart_one_server_at_once": {"servers": 1, "delay_s": 0},
            "restart_one_server_backup": {"servers": 1, "backup": True},
            "restart_two_servers_in_turn": {"servers": 2},
            "restart_two_linked_servers_in_turn": {"servers": 2, "linked": True},
            "restart_two_servers_together": {"servers": 2, "together": True},
            "restart_two_servers_together_at_once": {"servers": 2, "together": True, "delay_s": 0},
        }
    if args.only in (None, "move"):
        for name, options in {
            "move_one_server_stopped": {"servers": 1, "stop": signal.SIGTERM},
            "move_two_linked_servers_in_turn_stopped": {"servers": 2, "linked": True, "stop": signal.SIGTERM},
            "move_two_linked_servers_in_turn_killed": {"servers": 2, "linked": True},
            "move_two_linked_servers_together_stopped": {"servers": 2, "linked": True, "together": True, "stop": signal.SIGTERM},
        }.items():
            restarts[name] = {**options, "moved": True}
            restarts[f"{name}_pod_address"] = {**options, "moved": True, "announce_service": False}
    if restarts:
        for name, options in restarts.items():
            options = {"backup": False, **options, "down_s": args.down}
            rows = [run_one(faults.RESTART_ROLES, faults.restart_server, **options) for _ in runs]
            crashed = [r for r in rows if r["crashed"]]
            rows = [r for r in rows if not r["crashed"]]
            results[name] = {
                "runs": rows,
                "crashed_on_restart": len(crashed),
                "new_meets_old": summary(rows, "new_meets_old_s"),
                "old_meets_new": summary(rows, "old_meets_new_s"),
                "matched_pair_lost": sum(r["matched_pair_lost"] for r in rows),
            }
    if args.only in (None, "cut"):
        variants = {
            "cut_edge_server_by_dns_name": {"robot_server": "none", "dns": True},
            "cut_edge_server": {"robot_server": "none"},
            "cut_robot_server_listed": {"robot_server": "listed"},
            "cut_robot_server_linked": {"robot_server": "linked"},
        }
        for name, options in variants.items():
            rows = [run_one(faults.CUT_ROLES, faults.cut_off_robot, cut_s=args.cut, **options) for _ in runs]
            results[name] = {
                "runs": rows,
                "onboard_lost_during": sum(r["onboard_lost_during"] for r in rows),
                "started_during": summary(rows, "started_during_first_message_s"),
                "started_during_after_reconnect": summary(rows, "started_during_first_message_after_reconnect_s"),
                "edge_rematch": summary(rows, "edge_rematch_after_reconnect_s"),
            }
    print(json.dumps({k: v for k, v in results.items() if not isinstance(v, dict)} | {
        k: {kk: vv for kk, vv in v.items() if kk != "runs"} for k, v in results.items() if isinstance(v, dict)
    }, indent=1))  # fmt: skip
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            handle.write(json.dumps(results, indent=1) + "\n")
    if args.connectivity:
        fill_connectivity(args.connectivity, results)
    return 0


def fill_connectivity(path: str, results: dict) -> None:
    """The keys of the connectivity results this benchmark measures, from the configuration the collection renders
    (servers named by address, two servers per fleet); the rest of the file stays as bench_connectivity wrote it."""
    with open(path, encoding="utf-8") as handle:
        found = json.load(handle)
    cut, restart = results.get("cut_edge_server"), results.get("restart_two_servers_in_turn")
    measured = found.setdefault("measured_by", {})
    if cut:
        found["onboard_messages_lost_during"] = cut["onboard_lost_during"]
        measured["onboard_messages_lost_during"] = f"{results['command']} ({results['date']}): cut_edge_server"
    if restart and restart["new_meets_old"]["met"] == restart["new_meets_old"]["runs"]:
        found["discovery_restart_rematch_s"] = restart["new_meets_old"]["max_s"]
        measured["discovery_restart_rematch_s"] = f"{results['command']} ({results['date']}): restart_two_servers_in_turn"
    for key in measured:
        found.get("not_measured", {}).pop(key, None)
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(json.dumps(found, indent=1, default=str) + "\n")


if __name__ == "__main__":
    sys.exit(main())
