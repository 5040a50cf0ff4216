#!/usr/bin/env python3
"""The platform as pods, measured on the real-node tier: the controller's takeover and the bridge's added latency.

On a cluster of real nodes of its own (inventories/real-pods: robot-1, edge-1, edge-2, cloud-1; its own ports,
addresses and state directory), in one run:

(1) the pick-and-place example deployed (``playbooks/deploy.yml``) and every instance Running and Ready;
(2) ``controller.yml`` in-cluster: two replicas from the collection's image on the edge servers. Then ``--trials``
    times: the leader is read from the Lease and killed (the clock starts right before: epoch time), in turn by
    deleting its pod (with its grace period: the kubelet sends SIGTERM, and the controller gives the Lease up) and
    by SIGKILL to its process through the node's containerd (a crash: nothing gives the Lease up; the kubelet
    restarts the container in its pod, which holds the Lease under the same name and may lead again before the
    other replica's wait for the Lease to run out, 6 s, ends); the takeover is the epoch at which a replica (the
    other, the restarted one, or the Deployment's replacement of a deleted pod) logs ``first pass as leader
    completed at`` minus the kill's, as
    ``bench_controller_ha.py`` measures the processes. After each trial, once the Deployment's
    replacement replica is Ready, the fleet's pods are compared with those before: an instance without its pod is
    lost, one with two is duplicated, a pod with another UID was restarted (none may be);
(3) a second cluster of real nodes (partner-1), registered as the third-party cluster ``partner-real``: a ping pod
    on robot-1 measures ROS 2 round trips to an echo on edge-1 (direct, through the fleet's discovery servers), then
    to an echo module deployed in the partner cluster, with the bridge's server and client as pods; the added
    latency is the difference of the two medians, side by side in one run.

Results print as Markdown; ``--json`` merges the keys of issue 28 (``in_cluster_takeover_p95_s``,
``bridge_pods_p50_ms``, and what they are made of) into that file (``bench/results/images.json``). As root.

    .venv/bin/python bench/bench_platform_pods.py --trials 20 --json bench/results/images.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_controller_ha import percentile  # the process benchmark's p95, so that the two compare
from bench_deploy import REPO, log, machine

sys.path[:0] = [str(REPO / ".collections"), str(REPO / "tests")]
from real_tier import (  # noqa: E402  (the tests' driver of the real-node tier)
    CONTROLLER_NAMESPACE,
    RealCluster,
    bridge_round_trips,
    controller_pods,
    first_pass_as_leader,
    lease_holder,
    wait_for,
)

PORTS = {"apiserver": 39443, "etcd_client": 39379, "etcd_peer": 39380, "controller_manager": 39257, "scheduler": 39259}
PORTS["kwok"] = 39247
PARTNER_PORTS = {k: v + 1000 for k, v in PORTS.items()}
BASE, TAG = 211, "kc"  # 10.211-213.x
PARTNER_BASE, PARTNER_TAG = 215, "kd"  # 10.215-217.x
SPEC = REPO / "examples" / "pick-and-place.yml"


def fleet_pods(core, namespace: str) -> dict[str, list[str]]:
    """Instance -> UIDs of its live pods."""
    found: dict[str, list[str]] = {}
    for pod in core.list_namespaced_pod(namespace, label_selector="kuberos.io/instance").items:
        if pod.metadata.deletion_timestamp is None:
            found.setdefault(pod.metadata.labels["kuberos.io/instance"], []).append(pod.metadata.uid)
    return found


def kill_process(real: RealCluster, pod_name: str) -> int:
    """SIGKILL to the controller's process through its node's containerd (a crash: no Lease released). Returns the
    container's restart count before."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import RealNodes

    pod = real.core.read_namespaced_pod(pod_name, CONTROLLER_NAMESPACE)
    (status,) = pod.status.container_statuses
    socket = RealNodes.from_state(real.plane(), {}).socket(pod.spec.node_name)
    container = status.container_id.split("://", 1)[1]
    subprocess.run(["ctr", "--address", socket, "-n", "k8s.io", "tasks", "kill", "-s", "SIGKILL", container],
                   check=True, capture_output=True, timeout=30)  # fmt: skip
    return status.restart_count


def restarted(real: RealCluster, pod_name: str, before: int) -> bool:
    (status,) = real.core.read_namespaced_pod(pod_name, CONTROLLER_NAMESPACE).status.container_statuses
    return status.restart_count > before and status.ready


def replica_names(real: RealCluster) -> list[str]:
    selector = "app.kubernetes.io/name=kuberos-controller"
    return [p.metadata.name for p in real.core.list_namespaced_pod(CONTROLLER_NAMESPACE, label_selector=selector).items]


def takeover_trial(real: RealCluster, namespace: str, index: int, kind: str) -> dict:
    """One kill of the leader: ``pod deleted`` (with its grace period, as a drain or an eviction deletes it: the
    kubelet sends SIGTERM and the controller gives the Lease up) or ``process killed`` (SIGKILL in the container:
    nothing gives the Lease up)."""
    pods = wait_for(lambda: (lambda f: f if len(f) == 2 else None)(controller_pods(real.core)), 240, "two replicas Ready")
    leader = wait_for(lambda: (lambda h: h if h in pods else None)(lease_holder(real.core)), 60, "a leader")
    before = fleet_pods(real.core, namespace)
    killed = time.time()
    if kind == "pod deleted":
        real.core.delete_namespaced_pod(leader, CONTROLLER_NAMESPACE)  # its grace period, as a drain or an eviction
    else:
        restarts = kill_process(real, leader)
    # Whichever replica takes the Lease: the other, the killed one restarted in its pod (it holds the Lease under its
    # own name already), or the Deployment's replacement for a deleted pod, when it starts before the other's retry.
    led = lambda: next(  # noqa: E731
        ((pod, at) for pod in replica_names(real) if (at := first_pass_as_leader(real.core, pod, killed))), None
    )
    new_leader, passed = wait_for(led, 60, "a replica's first pass as leader", 0.2)
    wait_for(lambda: lease_holder(real.core) == new_leader, 10, f"{new_leader} holding the Lease", 0.2)
    if kind == "pod deleted":
        wait_for(lambda: len(controller_pods(real.core)) == 2, 240, "the replacement replica Ready")
    else:
        wait_for(lambda: restarted(real, leader, restarts), 240, f"{leader}'s container restarted and Ready")
    after = fleet_pods(real.core, namespace)
    row = {
        "trial": index,
        "kind": kind,
        "killed": leader,
        "leader": new_leader,
        "takeover_s": round(passed - killed, 3),
        "lost": sorted(set(before) - set(after)),
        "duplicated": sorted(i for i, uids in after.items() if len(uids) > 1),
        "restarted": sorted(i for i in set(before) & set(after) if before[i] != after[i]),
    }
    log(f"trial {index} ({kind}): {leader} killed, {new_leader} led after {row['takeover_s']:.2f} s; "
        f"lost {row['lost']}, duplicated {row['duplicated']}, restarted {row['restarted']}")  # fmt: skip
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20, help="leader pods killed [%(default)s]")
    parser.add_argument("--samples", type=int, default=40, help="round trips per path [%(default)s]")
    parser.add_argument("--json", help="merge the results into this file (bench/results/images.json)")
    args = parser.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("bench: real nodes need root")
    results: dict = {"machine": machine(), "command": " ".join(sys.argv)}
    with tempfile.TemporaryDirectory(prefix="kuberos-bench-pods-") as work:
        work = Path(work)
        real = RealCluster(work / "cluster", PORTS, BASE, TAG, controller_state_dir=str(work / "controller"))
        try:
            started = time.monotonic()
            done = real.start()
            if done.returncode:
                raise SystemExit("bench: the real-node tier did not start:\n" + done.stdout[-6000:])
            real.connect()
            log(f"real nodes up in {time.monotonic() - started:.0f} s")
            done = real.deploy(str(SPEC), work / "render")
            if done.returncode:
                raise SystemExit("bench: deploy failed:\n" + done.stdout[-6000:])
            placement = json.loads((work / "render" / "placement.json").read_text())
            namespace = placement["deployments"][0]["namespace"]
            wanted = {i["name"] for i in placement["instances"]} | {
                s["name"] for f in placement["discovery"] for s in f["servers"]
            }
            wait_for(lambda: set(fleet_pods(real.core, namespace)) >= wanted, 300, "every instance's pod")

            extra = {
                "controller_mode": "in_cluster",
                "controller_kubeconfig": real.kubeconfig,
                "controller_fleets": ["test-fleet"],
            }
            done = real.play("controller.yml", "-e", json.dumps(extra))
            if done.returncode:
                raise SystemExit("bench: controller.yml failed:\n" + done.stdout[-6000:])
            kinds = ("pod deleted", "process killed")
            trials = [takeover_trial(real, namespace, i, kinds[(i - 1) % 2]) for i in range(1, args.trials + 1)]
            takeovers = [t["takeover_s"] for t in trials]
            for kind in kinds:
                own = [t["takeover_s"] for t in trials if t["kind"] == kind]
                key = kind.split()[0]
                results[f"in_cluster_takeover_{key}_p50_s"] = round(statistics.median(own), 2)
                results[f"in_cluster_takeover_{key}_p95_s"] = round(percentile(own, 0.95), 2)
            results.update(
                in_cluster_takeover_trials=trials,
                in_cluster_takeover_p50_s=round(statistics.median(takeovers), 2),
                in_cluster_takeover_p95_s=round(percentile(takeovers, 0.95), 2),
                in_cluster_takeover_max_s=max(takeovers),
                in_cluster_modules_lost=sum(len(t["lost"]) for t in trials),
                in_cluster_modules_duplicated=sum(len(t["duplicated"]) for t in trials),
                in_cluster_modules_restarted=sum(len(t["restarted"]) for t in trials),
            )
            real.play("controller.yml", "-e", json.dumps({**extra, "controller_state": "stopped"}))

            bridge = bridge_round_trips(real, placement, work / "partner", PARTNER_PORTS, PARTNER_BASE, PARTNER_TAG, args.samples)
            results.update(
                bridge_pods_direct_p50_ms=round(statistics.median(bridge["direct_ms"]), 1),
                bridge_pods_through_p50_ms=round(statistics.median(bridge["through_ms"]), 1),
                bridge_pods_p50_ms=round(statistics.median(bridge["through_ms"]) - statistics.median(bridge["direct_ms"]), 1),
                bridge_pods_samples=bridge,
            )
        finally:
            real.stop(state="absent")

    print("\n| what | figure |\n|---|---|")
    takeover = ("pod_p50_s", "pod_p95_s", "process_p50_s", "process_p95_s", "p95_s", "max_s")
    for key in (*(f"in_cluster_takeover_{k}" for k in takeover), "in_cluster_modules_lost", "in_cluster_modules_duplicated",
                "in_cluster_modules_restarted", "bridge_pods_direct_p50_ms", "bridge_pods_through_p50_ms",
                "bridge_pods_p50_ms"):  # fmt: skip
        print(f"| {key} | {results.get(key)} |")
    if args.json:
        path = Path(args.json)
        merged = json.loads(path.read_text()) if path.exists() else {}
        merged["platform_pods_machine"] = results.pop("machine")
        merged["platform_pods_command"] = results.pop("command")
        merged.update(results)
        path.write_text(json.dumps(merged, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
