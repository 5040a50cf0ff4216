#!/usr/bin/env python3
"""Connectivity benchmark: a robot that goes offline, and edge servers that die, on the real-node tier.

On a cluster of real nodes of its own (inventories/real-pods: robot-1, edge-1, edge-2, cloud-1; its own ports,
addresses and state directory; the API server's default toleration of an unreachable node shortened to
``--toleration`` seconds so that a pod without the platform's tolerations is evicted within the run), with
examples/pick-and-place.yml deployed and the controller running with the role's defaults (grace 5 s, its own probe
of the server nodes' kubelets every 1 s):

(1) robot-1 cut off the network (``RealNodes.partition``: every packet of its control link and its link to the
    other nodes dropped) until a pod without the platform's tolerations is evicted and ``--hold`` seconds more, then
    reconnected (``tests/real_tier.py cut_off_robot``, the procedure the real-node test asserts on): the robot's pods
    before and after (UIDs, restart counts), moves during the partition, how long after reconnecting the node was
    Ready and every module Running and Ready where placed;
(2) ``--failovers`` times: the kubelet of the edge or cloud node running the most modules stopped (its containers
    keep running, as on a machine whose kubelet died); the time from the stop until every module that ran there is
    Running and Ready on another node; moves of modules that were not on it (false moves); the kubelet started again.

Keys of ``--json`` (bench/results/connectivity.json) that this run does not measure are null, said in ``not_measured``,
unless the file already holds them from the run its ``measured_by`` names (those stay).

    .venv/bin/python bench/bench_connectivity.py --json bench/results/connectivity.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_controller_ha import percentile
from bench_deploy import REPO, log, machine

sys.path[:0] = [str(REPO / ".collections"), str(REPO / "tests")]
from real_tier import (  # noqa: E402  (the tests' driver of the real-node tier)
    RealCluster,
    cut_off_robot,
    events_of,
    new_events,
    node_ready,
    placed_instances,
    programs_configmap,
    running_where_placed,
    wait_for,
)

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import RealNodes, snapshot_host  # noqa: E402

PORTS = {"apiserver": 37443, "etcd_client": 37379, "etcd_peer": 37380, "controller_manager": 37257, "scheduler": 37259}
PORTS["kwok"] = 37247
BASE, TAG = 205, "ke"  # 10.205-207.x: apart from the tests' tiers and the other benchmarks'
SPEC = REPO / "examples" / "pick-and-place.yml"
NOT_MEASURED = {
    "onboard_messages_lost_during": "the robot's own ROS 2 traffic during a partition",
    "discovery_restart_rematch_s": "a discovery server restarted or moved",
    "rollout_downtime_with_prestage_s": "rollouts with images pre-pulled on a bandwidth-limited link",
    "rollout_downtime_without_prestage_s": "the same without pre-pulling",
}


def failover(real: RealCluster, namespace: str, placed: dict[str, str], trial: int) -> tuple[dict, dict[str, str]]:
    """Stop the kubelet of the server node that runs the most modules; time until they run elsewhere."""
    counts: dict[str, int] = {}
    for node in placed.values():
        if node != "robot-1":
            counts[node] = counts.get(node, 0) + 1
    victim = max(sorted(counts), key=counts.get)
    leaving = sorted(name for name, node in placed.items() if node == victim)
    moves = events_of(real.core, namespace, "ModuleMoved")
    nodes = RealNodes.from_state(real.plane(), {})
    assert nodes.stop_kubelet(victim)
    stopped = time.monotonic()

    def moved():
        running = running_where_placed(real.core, namespace, {})
        return running if running and all(running.get(name) not in (None, victim) for name in leaving) else None

    after = wait_for(moved, 300, f"{leaving} Running and Ready off {victim}", 0.2)
    seconds = round(time.monotonic() - stopped, 1)
    false_moves = [message for name, message in new_events(real.core, namespace, "ModuleMoved", moves) if name not in leaving]
    log(f"failover {trial}: {victim}'s kubelet stopped, {leaving} Running and Ready elsewhere after {seconds} s")
    started = real.start()
    if started.returncode != 0:
        raise SystemExit(f"bench: restarting {victim}'s kubelet failed:\n{started.stdout[-3000:]}")
    wait_for(lambda: node_ready(real.core, victim), 180, f"{victim} Ready again")
    now = {name: after.get(name, node) for name, node in placed.items()}
    return {"trial": trial, "node": victim, "modules": len(leaving), "seconds": seconds, "false_moves": false_moves}, now


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--failovers", type=int, default=3, help="edge or cloud kubelets stopped in turn [%(default)s]")
    parser.add_argument("--toleration", type=int, default=10, help="the API server's default toleration, s [%(default)s]")
    parser.add_argument("--hold", type=float, default=20.0, help="seconds offline after the control's eviction [%(default)s]")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("bench: real nodes need root")
    results: dict = {"machine": machine(), "command": " ".join(sys.argv), "not_measured": dict(NOT_MEASURED)}
    results.update(dict.fromkeys(NOT_MEASURED))
    before = snapshot_host()
    with tempfile.TemporaryDirectory(prefix="kuberos-bench-conn-") as work:
        work = Path(work)
        real = RealCluster(work / "c", PORTS, BASE, TAG, local_cluster_unreachable_toleration_s=args.toleration)
        controller = {"controller_kubeconfig": real.kubeconfig, "controller_state_dir": str(work / "ctl")}
        try:
            log("starting the real-node tier")
            done = real.start()
            if done.returncode != 0:
                raise SystemExit(f"bench: the tier did not start:\n{done.stdout[-4000:]}")
            real.connect()
            render = work / "render"
            done = real.deploy(str(SPEC), render)
            if done.returncode != 0:
                raise SystemExit(f"bench: deploy failed:\n{done.stdout[-4000:]}")
            placement = json.loads((render / "placement.json").read_text())
            namespace = placement["deployments"][0]["namespace"]
            placed = placed_instances(placement)
            wait_for(lambda: running_where_placed(real.core, namespace, placed), 300, "every module Running where placed")
            assert real.play("controller.yml", "-e", json.dumps(controller)).returncode == 0
            control = "connectivity-control"
            real.core.create_namespace({"metadata": {"name": control}})
            programs_configmap(real.core, control)
            status = f"kuberos-status-{placement['deployments'][0]['name']}"
            log(f"cutting robot-1 off (the API server evicts untolerated pods after {args.toleration} s)")
            seen = cut_off_robot(real, namespace, placed, "robot-1", control, status, args.hold, args.toleration)
            restarts = sum(r for _uid, r, _d in seen["after"].values()) - sum(r for _uid, r, _d in seen["before"].values())
            results.update(
                partition_s=seen["partition_s"],
                tainted_after_s=seen["tainted_after_s"],
                control_evicted_after_s=seen["control_evicted_after_s"],
                onboard_pods=len(seen["before"]),
                onboard_restarts_after=restarts,
                onboard_pods_replaced=sum(
                    1 for name, row in seen["before"].items() if seen["after"].get(name, ("",))[0] != row[0]
                ),
                ready_after_reconnect_s=seen["ready_after_reconnect_s"],
                rematch_after_reconnect_s=seen["rematch_after_reconnect_s"],
                moves_while_robot_offline=len(seen["moves_after"]),
            )
            log(f"robot-1 offline {seen['partition_s']} s: {results['onboard_pods']} onboard pods, restarts after "
                f"{restarts}, moves {len(seen['moves_after'])}; every module placed {seen['rematch_after_reconnect_s']} s "
                "after reconnecting")  # fmt: skip
            trials = []
            for trial in range(1, args.failovers + 1):
                row, placed = failover(real, namespace, placed, trial)
                trials.append(row)
            seconds = [t["seconds"] for t in trials]
            results.update(
                edge_failovers=trials,
                edge_failover_p50_s=round(percentile(seconds, 0.5), 1) if seconds else None,
                edge_failover_p95_s=round(percentile(seconds, 0.95), 1) if seconds else None,
                false_moves=results["moves_while_robot_offline"] + sum(len(t["false_moves"]) for t in trials),
            )
        finally:
            controller["controller_state"] = "stopped"
            real.play("controller.yml", "-e", json.dumps(controller))
            real.stop(state="absent")
    after = snapshot_host()
    results["host_as_before"] = all(before[k] == after[k] for k in before)
    print("\n| figure | value |\n|---|---|")
    for key in ("partition_s", "tainted_after_s", "control_evicted_after_s", "onboard_pods", "onboard_restarts_after",
                "onboard_pods_replaced", "ready_after_reconnect_s", "rematch_after_reconnect_s", "false_moves",
                "edge_failover_p50_s", "edge_failover_p95_s", "host_as_before"):  # fmt: skip
        print(f"| {key} | {results.get(key)} |")
    if args.json:
        path = Path(args.json)
        earlier = json.loads(path.read_text()) if path.exists() else {}
        # keys another run measured (bench_discovery.py, the real-node tests) stay, with what measured them
        for key, how in (earlier.get("measured_by") or {}).items():
            if results.get(key) is None:
                results[key] = earlier.get(key)
                results.setdefault("measured_by", {})[key] = how
                results["not_measured"].pop(key, None)
        path.write_text(json.dumps(results, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
