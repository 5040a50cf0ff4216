#!/usr/bin/env python3
"""Controller takeover benchmark: from the leading replica's SIGKILL to the new leader's first completed pass.

On a dedicated local control plane (its own ports and state directory; 10 robots in one fleet, 4 edge and
2 cloud kwok nodes by default) it deploys a pick-and-place app with ``playbooks/deploy.yml`` and starts two
controller replicas with ``playbooks/controller.yml`` (local processes, grace ``--grace`` seconds, the
role's Lease timings: 6 s lease, 4 s renew deadline, 1 s retry). Then, trial after trial:

1. the leader is read from the Lease ``kuberos-system/kuberos-controller`` (identity ``host_pid``);
2. every other trial ("node failing"), an edge node that hosts module pods is killed the way
   bench_controller.py kills one (kwok's heartbeats stop, Ready=Unknown) right before the leader: the
   dead leader has moved nothing, the new leader must;
3. the leader is killed with SIGKILL (it cannot release the Lease). The clock starts right before the
   kill (epoch time);
4. the surviving replica logs ``first pass as leader completed at <epoch>`` when its first reconcile pass
   as leader ends; takeover = that epoch minus the kill's. Both are this machine's clock;
5. for a node-failing trial, the pods are polled until every instance runs exactly once, Running and
   Ready, on the node its record says, and none is left on the dead node; then the node comes back;
6. at the end of every trial, with every pod settled, the instances of the record are counted: lost
   (no live pod, or none Running and Ready, or not on the record's node) and duplicated (more than one
   live pod). The killed replica is started again with the playbook before the next trial.

    .venv/bin/python bench/bench_controller_ha.py                       # 12 trials
    .venv/bin/python bench/bench_controller_ha.py --trials 10 --json bench/results/controller-ha.json

The cluster is removed at the end, also on failure, unless ``--keep-cluster``. The result is printed as
Markdown; with ``--json`` the raw trials and the summary keys (``trials``, ``takeover_p50_s``,
``takeover_p95_s``, ``modules_lost``, ``modules_duplicated``) are written too.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import signal
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench_controller import (  # bench/ is on sys.path when a benchmark runs
    FLEET,
    ControllerProcess,
    FailoverCluster,
    by_instance,
    kill_node,
    list_pods,
    loadavg,
    pick_node,
    pod_node,
    pod_ready,
    restore_node,
    wait_node_back,
    wait_steady,
    write_inventory,
)
from bench_deploy import REPO, check, log, machine, playbook
from workload import pick_and_place

sys.path[:0] = [str(REPO / ".collections")]  # the record's reader

SPEC_NAME = "bench-takeover"
PORTS = {
    "apiserver": 47443,
    "etcd_client": 43379,
    "etcd_peer": 43380,
    "controller_manager": 47257,
    "scheduler": 47259,
    "kwok": 47247,
}
LEASE = ("kuberos-controller", "kuberos-system")
FIRST_PASS = re.compile(r"first pass as leader completed at (\d+\.\d+)")
TARGET_P95_S = 10.0


class TakeoverCluster(FailoverCluster):
    """The failover benchmark's cluster on this benchmark's own ports."""

    def __init__(self, inventory: Path, state_dir: Path, timeout: float):
        super().__init__(inventory, state_dir, timeout)
        self.vars = json.dumps(
            {"local_cluster_state_dir": str(state_dir), "local_cluster_ports": PORTS, "local_cluster_timeout": int(timeout)}
        )


class Replicas(ControllerProcess):
    """Two replicas; their logs are controller.log and controller-2.log."""

    def logs(self) -> list[Path]:
        return sorted(self.state_dir.glob("controller*.log"))

    def sizes(self) -> dict[Path, int]:
        return {path: path.stat().st_size for path in self.logs()}

    def since(self, sizes: dict[Path, int]) -> str:
        text = ""
        for path in self.logs():
            with open(path, "rb") as handle:
                handle.seek(sizes.get(path, 0))
                text += handle.read().decode(errors="replace")
        return text

    def pids(self) -> list[int]:
        found = []
        for path in self.state_dir.glob("controller*.pid"):
            try:
                pid = int(path.read_text().strip())
                if b"kuberos_controller" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    found.append(pid)
            except (OSError, ValueError):
                continue
        return sorted(found)


def leader(coordination) -> str:
    try:
        return coordination.read_namespaced_lease(*LEASE).spec.holder_identity or ""
    except Exception:
        return ""


def wait_leader(coordination, replicas: Replicas, deadline: float) -> int:
    prefix = socket.gethostname() + "_"
    while time.monotonic() < deadline:
        holder = leader(coordination)
        if holder.startswith(prefix) and int(holder[len(prefix) :]) in replicas.pids():
            return int(holder[len(prefix) :])
        time.sleep(0.2)
    raise TimeoutError(f"no running replica holds the Lease (holder {leader(coordination)!r}, replicas {replicas.pids()})")


def record_placement(core) -> dict[str, str]:
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_record

    configmap = core.read_namespaced_config_map(f"kuberos-record-{SPEC_NAME}", f"kuberos-{FLEET}")
    return parse_record(core.api_client.sanitize_for_serialization(configmap)).placement.pinned()


def count_faults(core, placed: dict[str, str] | None = None, instances: dict | None = None) -> tuple[list[str], list[str]]:
    """(lost, duplicated) instances of the record right now (or of the record and pods given)."""
    placed = record_placement(core) if placed is None else placed
    instances = by_instance(list_pods(core)) if instances is None else instances
    lost, duplicated = [], []
    for name, node in sorted(placed.items()):
        live = [p for p in instances.get(name, []) if not p["metadata"].get("deletionTimestamp")]
        if len(live) > 1:
            duplicated.append(name)
        elif not live or not pod_ready(live[0]) or pod_node(live[0]) != node:
            lost.append(name)
    return lost, duplicated


def converged(core, dead: str) -> bool:
    """Nothing placed on or left on the dead node, and every instance once, Running and Ready, where placed."""
    placed = record_placement(core)
    if dead in placed.values():
        return False
    pods = list_pods(core)
    if any(pod_node(p) == dead for p in pods):
        return False
    return count_faults(core, placed, by_instance(pods)) == ([], [])


def trial(index: int, core, coordination, replicas: Replicas, node: str | None, args) -> dict:
    deadline = time.monotonic() + args.timeout
    old = wait_leader(coordination, replicas, deadline)
    sizes = replicas.sizes()
    outcome: dict = {"trial": index, "kind": "node failing" if node else "idle", "killed_pid": old, "node": node}
    if node:
        kill_node(core, node)
    killed_at = time.time()
    os.kill(old, signal.SIGKILL)
    log(f"trial {index}: killed the leader (pid {old})" + (f" right after {node} went down" if node else ""))
    passed = None
    while time.monotonic() < deadline:
        found = FIRST_PASS.findall(replicas.since(sizes))
        if found:
            passed = float(found[0])
            break
        time.sleep(0.1)
    if passed is None:
        raise TimeoutError(
            f"trial {index}: no new leader's first pass within {args.timeout:g} s:\n{replicas.since(sizes)[-3000:]}"
        )
    outcome["takeover_s"] = round(passed - killed_at, 3)
    outcome["new_leader"] = leader(coordination)
    if node:
        start = time.monotonic()
        while not converged(core, node):
            if time.monotonic() > deadline:
                raise TimeoutError(f"trial {index}: the modules of {node} did not settle elsewhere")
            time.sleep(args.poll)
        outcome["modules_back_s"] = round(time.time() - killed_at, 3)
        outcome["converge_after_kill_s"] = round(time.monotonic() - start, 3)
        restore_node(core, node)
        wait_node_back(core, node, deadline, args.poll)
    wait_steady(core, len(record_placement(core)), deadline, args.poll)
    lost, duplicated = count_faults(core)
    outcome.update(lost=lost, duplicated=duplicated)
    log(
        f"trial {index}: takeover {outcome['takeover_s']:.2f} s"
        + (f", modules of {node} settled {outcome['modules_back_s']:.1f} s after the kill" if node else "")
        + f"; lost {len(lost)}, duplicated {len(duplicated)}"
    )
    return outcome


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    rank = q * (len(ordered) - 1)
    low = int(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def summary(trials: list[dict]) -> dict:
    takeovers = [t["takeover_s"] for t in trials if "takeover_s" in t]
    if not takeovers:
        return {"trials": 0}
    failing = [t["takeover_s"] for t in trials if t["kind"] == "node failing"]
    return {
        "trials": len(takeovers),
        "takeover_p50_s": round(statistics.median(takeovers), 2),
        "takeover_p95_s": round(percentile(takeovers, 0.95), 2),
        "takeover_max_s": round(max(takeovers), 2),
        "takeover_node_failing_p50_s": round(statistics.median(failing), 2) if failing else None,
        "modules_back_p50_s": round(statistics.median([t["modules_back_s"] for t in trials if "modules_back_s" in t]), 2)
        if failing
        else None,
        "modules_lost": sum(len(t["lost"]) for t in trials),
        "modules_duplicated": sum(len(t["duplicated"]) for t in trials),
    }


def markdown(data: dict) -> str:
    s, m = data["summary"], data["machine"]
    lines = [
        f"### Controller takeover ({data['date']})",
        "",
        f"- Command: `{data['command']}`",
        f"- Machine: {m['nproc']} cores ({m['cpu']}), memory {m['memory']}, Python {m['python']}, kernel {m['kernel']};"
        f" commit {m['commit']}; load before {data['load_before']}, after {data.get('load_after')}",
        f"- Fleet: {data.get('instances', '?')} instances (modules and discovery servers) on {data.get('nodes', '?')} kwok nodes;"
        f" 2 replicas, lease 6 s, renew deadline 4 s, retry 1 s, grace {data['args']['grace']:g} s",
        "",
        "| trial | kind | takeover (s) | modules settled after the kill (s) | lost | duplicated |",
        "|---|---|---|---|---|---|",
    ]
    for t in data["trials"]:
        lines.append(
            f"| {t['trial']} | {t['kind']} | {t['takeover_s']:.2f} | {t.get('modules_back_s', '-')} | {len(t['lost'])} |"
            f" {len(t['duplicated'])} |"
        )
    if s.get("trials"):
        verdict = "met" if s["takeover_p95_s"] < TARGET_P95_S else "MISSED"
        lines += [
            "",
            f"Takeover p50 {s['takeover_p50_s']:.2f} s, p95 {s['takeover_p95_s']:.2f} s (target p95 < {TARGET_P95_S:g} s:"
            f" {verdict}), max {s['takeover_max_s']:.2f} s over {s['trials']} trials; modules lost {s['modules_lost']},"
            f" duplicated {s['modules_duplicated']}.",
        ]
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], epilog="Ports: " + ", ".join(f"{k} {v}" for k, v in PORTS.items())
    )
    parser.add_argument("--trials", type=int, default=12, help="leader kills, at least 10; default 12")
    parser.add_argument("--grace", type=float, default=5.0, help="the controller's grace, seconds; default 5")
    parser.add_argument("--robots", type=int, default=10, help="robots in the fleet; default 10")
    parser.add_argument("--edge", type=int, default=4, help="edge nodes; default 4")
    parser.add_argument("--cloud", type=int, default=2, help="cloud nodes; default 2")
    parser.add_argument("--poll", type=float, default=0.2, help="poll interval, seconds; default 0.2")
    parser.add_argument("--calm", type=float, default=3.0, help="seconds between trials once all is settled; default 3")
    parser.add_argument("--timeout", type=float, default=120.0, help="bound of every trial, seconds; default 120")
    parser.add_argument("--keep-cluster", action="store_true", help="leave the controller, the cluster and the work dir")
    parser.add_argument("--json", type=Path, help="also write the summary keys and every trial")
    args = parser.parse_args(argv)
    if args.trials < 10:
        parser.error("--trials must be at least 10")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="kuberos-bench-takeover-"))
    inventory = write_inventory(work / "inventory", args.robots, args.edge, args.cloud)
    spec = work / f"{SPEC_NAME}.yml"
    spec.write_text(json.dumps(pick_and_place(SPEC_NAME, FLEET), indent=2) + "\n")
    cluster = TakeoverCluster(inventory, work / "cluster", args.timeout)
    replicas = Replicas(cluster, work / "controller", args.grace, replicas=2)
    commit = os.popen(f"git -C {REPO} rev-parse --short HEAD").read().strip()
    data: dict = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "command": " ".join([".venv/bin/python", "bench/bench_controller_ha.py", *(sys.argv[1:] if argv is None else argv)]),
        "machine": machine(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "commit": commit,
        "load_before": loadavg(),
        "trials": [],
    }
    ok = False
    try:
        log(f"work dir {work}; starting the cluster")
        cluster.start()
        core = cluster.core()
        from kubernetes import client

        coordination = client.CoordinationV1Api(core.api_client)
        data["nodes"] = len(core.list_node(label_selector="kuberos.io/role").items)
        check(
            playbook("deploy.yml", inventory, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={work / 'render'}",
                     "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", timeout=args.timeout + 300),
            "deploy.yml",
        )  # fmt: skip
        data["instances"] = len(record_placement(core))
        wait_steady(core, data["instances"], time.monotonic() + args.timeout, args.poll)
        edge_nodes = [f"edge-{i:02d}" for i in range(args.edge)]
        last_killed: dict[str, int] = {}
        for index in range(1, args.trials + 1):
            replicas.start()  # both replicas (the one killed last trial starts again)
            wait_leader(coordination, replicas, time.monotonic() + args.timeout)
            time.sleep(args.calm)  # the new follower has listed and watches
            node = None
            if index % 2 == 0:
                node = pick_node(list_pods(core), edge_nodes, last_killed)
                last_killed[node] = index
            data["trials"].append(trial(index, core, coordination, replicas, node, args))
        ok = True
    finally:
        data["load_after"] = loadavg()
        data["summary"] = summary(data["trials"])
        if args.keep_cluster:
            log(f"kept: KUBECONFIG={cluster.kubeconfig}; work dir {work}")
        else:
            replicas.stop()
            cluster.stop()
            if ok:
                shutil.rmtree(work, ignore_errors=True)
            else:
                log(f"work dir kept: {work}")
        if args.json:
            keys = ("trials", "takeover_p50_s", "takeover_p95_s", "modules_lost", "modules_duplicated")
            out = {k: data["summary"].get(k) for k in keys}
            out.update({k: v for k, v in data.items() if k != "trials"}, trials_detail=data["trials"])
            args.json.write_text(json.dumps(out, indent=2, default=str) + "\n")
    print(markdown(data))
    s = data["summary"]
    good = ok and s.get("trials", 0) >= 10 and s["modules_lost"] == 0 and s["modules_duplicated"] == 0
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
