"""The pick-and-place fleet as real pods: each robot's simulated hardware as a pod on its robot node, and the
pick cycles the deployed modules complete, read from the pods' logs through the API server (kubelet logs).

The modules themselves are deployed with playbooks/deploy.yml like on any cluster; this adds what a real site
has without deploying it, the robots' hardware (here the PyBullet physics of kuberos_pnp.robot), and measures.

    python -m kuberos_sim.real_pods --kubeconfig ~/.cache/kuberos/cluster-real/kubeconfig --robots robot-1 --cycles 2

Exit status 0 when every robot completed its cycles within the time limit; the summary is printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from kuberos_pnp import common

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security

HARDWARE_IMAGE = "ghcr.io/kuberos/pnp-robot-sim:0.1"
HARDWARE_LABEL = "kuberos-sim/robot-hardware"
FLEET_ENV = ("ROS_DISCOVERY_SERVER", "ROS_DOMAIN_ID", "RMW_IMPLEMENTATION", "KUBEROS_FLEET")
ROBOT_TAINT = "kuberos.io/robot"
ROBOT_LABEL = "robot.kuberos.io/name"


def hardware_pod(
    robot: str, namespace: str, env: dict[str, str], seed: int, objects: int, image: str = HARDWARE_IMAGE, node: str = ""
) -> dict:
    """The robot's simulated hardware: a pod on the robot's own node, found by its robot label (the node's name may
    be a host name), tolerating only that robot's taint. It runs as the fleet's modules do: not as root, nothing
    more than the restricted Pod Security level allows (its namespace enforces it)."""
    variables = {**env, "KUBEROS_ROBOT_NAME": robot, "KUBEROS_NODE_NAME": node or robot, "ROS_HOME": pod_security.ROS_HOME}
    parameters = ["-p", f"seed:={seed}", "-p", f"objects:={objects}"]
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {"name": f"hardware-{robot}", "namespace": namespace, "labels": {HARDWARE_LABEL: robot}},
        "spec": pod_security.harden(
            {
                "nodeSelector": {ROBOT_LABEL: robot},
                "tolerations": [{"key": ROBOT_TAINT, "operator": "Equal", "value": robot, "effect": "NoSchedule"}],
                "restartPolicy": "Never",
                "containers": [
                    {
                        "name": "physics",
                        "image": image,
                        "imagePullPolicy": "IfNotPresent",
                        "args": ["python3", "-m", "kuberos_pnp.robot", "--ros-args", *parameters],
                        "env": [{"name": k, "value": v} for k, v in sorted(variables.items())],
                    }
                ],
            }
        ),
    }


def fleet_env(apps, fleet: str) -> tuple[str, dict[str, str]]:
    """The fleet's namespace and the ROS environment its modules get (discovery servers, domain)."""
    deployments = apps.list_deployment_for_all_namespaces(label_selector=f"fleet.kuberos.io/name={fleet},kuberos.io/module").items
    if not deployments:
        raise SystemExit(f"no module of fleet {fleet} is deployed (playbooks/deploy.yml first)")
    first = deployments[0]
    env = {e.name: e.value for e in first.spec.template.spec.containers[0].env or [] if e.name in FLEET_ENV and e.value}
    return first.metadata.namespace, env


def records(core, namespace: str) -> list[dict]:
    """Every result line the namespace's pods logged (the coordinator's cycles and planning requests)."""
    found = []
    for pod in core.list_namespaced_pod(namespace).items:
        for container in pod.spec.containers:
            try:
                text = core.read_namespaced_pod_log(pod.metadata.name, namespace, container=container.name)
            except Exception:
                continue
            found.extend(common.read_results(text or ""))  # a container that has written nothing yet: no log at all
    return found


def cycles_by_robot(found: list[dict]) -> dict[str, dict[str, int]]:
    counts: dict[str, dict[str, int]] = {}
    for record in found:
        if record.get("kind") == "cycle":
            robot = counts.setdefault(record.get("robot", "?"), {"cycles": 0, "succeeded": 0})
            robot["cycles"] += 1
            robot["succeeded"] += 1 if record.get("outcome") == "success" else 0
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kubeconfig", required=True)
    parser.add_argument("--fleet", default="test-fleet")
    parser.add_argument("--robots", default="robot-1", help="comma-separated robot names (their nodes must exist)")
    parser.add_argument("--cycles", type=int, default=2, help="pick cycles per robot (one cube each)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--time-limit", type=float, default=600.0, help="seconds to wait for the cycles")
    parser.add_argument("--keep", action="store_true", help="leave the hardware pods running afterwards")
    args = parser.parse_args(argv)

    from kubernetes import client, config

    api = config.new_client_from_config(config_file=args.kubeconfig)
    core, apps = client.CoreV1Api(api), client.AppsV1Api(api)
    namespace, env = fleet_env(apps, args.fleet)
    robots = [r for r in args.robots.split(",") if r]
    started = time.monotonic()
    for robot in robots:
        nodes = core.list_node(label_selector=f"{ROBOT_LABEL}={robot}").items
        if not nodes:
            raise SystemExit(f"no node carries {ROBOT_LABEL}={robot}: is {robot} a robot of the cluster?")
        pod = hardware_pod(robot, namespace, env, args.seed, args.cycles, node=nodes[0].metadata.name)
        core.create_namespaced_pod(namespace, pod)
        print(f"started the hardware of {robot} in {namespace}", flush=True)
    counts: dict = {}
    try:
        while time.monotonic() - started < args.time_limit:
            counts = cycles_by_robot(records(core, namespace))
            done = sum(c["cycles"] for c in counts.values())
            print(f"[{time.monotonic() - started:5.0f} s] cycles: {json.dumps(counts)}", flush=True)
            if all(counts.get(r, {}).get("cycles", 0) >= args.cycles for r in robots):
                break
            time.sleep(5 if done else 10)
        found = records(core, namespace)
    finally:
        if not args.keep:
            for robot in robots:
                core.delete_namespaced_pod(f"hardware-{robot}", namespace, grace_period_seconds=0)
    latencies = sorted(r["latency_ms"] for r in found if r.get("kind") == "plan" and r.get("latency_ms") is not None)
    summary = {
        "robots": robots,
        "cycles": cycles_by_robot(found),
        "seconds": round(time.monotonic() - started, 1),
        "plans": len(latencies),
        "planning_latency_p50_ms": latencies[len(latencies) // 2] if latencies else None,
    }
    print(json.dumps(summary, indent=1))
    complete = all(summary["cycles"].get(r, {}).get("succeeded", 0) >= args.cycles for r in robots)
    return 0 if complete else 1


if __name__ == "__main__":
    sys.exit(main())
