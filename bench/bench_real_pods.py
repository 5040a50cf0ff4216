#!/usr/bin/env python3
"""Real-pod benchmark: the local cluster's real-node tier (docs/real-nodes.md), measured end to end.

On a cluster of its own (inventories/real-pods: robot-1, edge-1, edge-2 and cloud-1 as real nodes; its own ports,
addresses and state directory), each step timed from the start of its command to its end:

(1) images: the collection's images built (or found in the cache: ``--cold-images`` builds them into an empty
    cache first), their archive sizes;
(2) the tier's cold start (no state: certificates, namespaces, containerd, the images imported into every node,
    kubelets Ready) and, after a stop, its warm start (the images are kept);
(3) deploy of the pick-and-place app in the simulator's ``cloud`` strategy (perception and the motion planner on
    cloud-1, the coordinator on the edge, the controller onboard; the two CPU requests lowered to 750m so that both
    fit the 2 cores a real node reports): ``playbooks/deploy.yml`` until it exits, then until every instance's pod
    is Running and Ready on the node its placement names;
(4) the robot's simulated hardware (a pod on robot-1) doing ``--cycles`` pick cycles with the real pods, and the
    same strategy, fleet size and cycles in the simulator's network-namespace runtime (``kuberos_sim.evaluate``),
    side by side in one run;
(5) teardown (``local_cluster_state=absent``) and whether the host is as it was before (1).

Results print as Markdown and go to ``bench/results/real-pods.json`` with ``--json``. As root.

    .venv/bin/python bench/bench_real_pods.py --json bench/results/real-pods.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_deploy import REPO, check, log, machine, playbook

sys.path[:0] = [str(REPO / ".collections"), str(REPO / "sim")]
from kuberos_sim import scenario  # noqa: E402

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_host  # noqa: E402

INVENTORY = REPO / "inventories" / "real-pods"
PORTS = {"apiserver": 38443, "etcd_client": 38379, "etcd_peer": 38380}
PORTS.update(controller_manager=38257, scheduler=38259, kwok=38247)
FLEET = "test-fleet"


def timed(what: str, function):
    started = time.monotonic()
    value = function()
    seconds = time.monotonic() - started
    log(f"{what}: {seconds:.1f} s")
    return value, round(seconds, 1)


def instances_running(core, placement: dict) -> bool:
    wanted = {i["name"]: i["node"] for i in placement["instances"]}
    wanted.update({s["name"]: s["node"] for fleet in placement["discovery"] for s in fleet["servers"]})
    wanted.update({s["name"]: s["node"] for s in placement.get("robot_discovery", [])})
    running = {
        p.metadata.labels.get("kuberos.io/instance"): p.spec.node_name
        for p in core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items
        if p.status.phase == "Running" and all(s.ready for s in p.status.container_statuses or [])
    }
    return running == wanted


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=3, help="pick cycles of the robot [%(default)s]")
    parser.add_argument("--rate", type=float, default=12.0, help="pick tasks per minute [%(default)s]")
    parser.add_argument("--time-limit", type=float, default=900.0, help="seconds for the cycles [%(default)s]")
    parser.add_argument("--cold-images", action="store_true", help="build the images into an empty cache first")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("bench: real nodes need root")
    results: dict = {"machine": machine(), "command": " ".join(sys.argv), "cycles_asked": args.cycles}
    before = snapshot_host()

    cache = os.environ.get("KUBEROS_CACHE_DIR") or os.path.expanduser("~/.cache/kuberos")
    if args.cold_images:
        with tempfile.TemporaryDirectory(prefix="kuberos-images-") as empty:
            _built, results["images_cold_s"] = timed("images, cold", lambda: local_images.build_images(str(REPO), empty, log=log))
    images, results["images_cached_s"] = timed("images, cached", lambda: local_images.build_images(str(REPO), cache, log=log))
    results["image_mib"] = {ref: round(os.path.getsize(path) / 2**20, 1) for ref, path in images.items()}

    with tempfile.TemporaryDirectory(prefix="kuberos-bench-real-") as work:
        work = Path(work)
        state = work / "cluster"
        kubeconfig = state / "kubeconfig"
        variables = [
            "-e",
            json.dumps(
                {
                    "local_cluster_state_dir": str(state),
                    "local_cluster_ports": PORTS,
                    "local_cluster_real_nodes_base": 221,
                    "local_cluster_real_nodes_tag": "kb",
                    "kuberos_kubeconfig": str(kubeconfig),
                    "controller_state_dir": str(work / "controller"),
                }
            ),
        ]

        def cluster(state_name: str = "started"):
            done = playbook("local_cluster.yml", INVENTORY, *variables, "-e", f"local_cluster_state={state_name}", timeout=3600)
            check(done, f"local_cluster.yml {state_name}")

        try:
            _none, results["tier_cold_start_s"] = timed("tier, cold start", cluster)
            _none, results["tier_stop_s"] = timed("tier, stop", lambda: cluster("stopped"))
            _none, results["tier_warm_start_s"] = timed("tier, warm start", cluster)

            spec = scenario.strategy_spec("cloud", args.rate, args.cycles)
            spec["metadata"]["targetFleet"] = FLEET
            # The real nodes have the machine's 2 cores each: perception and the planner must fit on cloud-1 together.
            for module in spec["rosModules"]:
                if module["name"] in ("perception", "motion-planner"):
                    module["resources"]["cpu"] = "750m"
            spec_file = scenario.write_yaml(str(work / "pick-and-place-cloud.yml"), spec)
            render = work / "rendered"
            deploy = [*variables, "-e", f"rosdeployment_file={spec_file}", "-e", f"kuberos_render_dir={render}"]
            done, results["deploy_playbook_s"] = timed("deploy", lambda: playbook("deploy.yml", INVENTORY, *deploy, timeout=1800))
            check(done, "deploy.yml")
            placement = json.loads((render / "placement.json").read_text())
            from kubernetes import client, config

            core = client.CoreV1Api(config.new_client_from_config(config_file=str(kubeconfig)))
            started = time.monotonic()
            while not instances_running(core, placement):
                if time.monotonic() - started > 600:
                    raise SystemExit("bench: the deployed pods were not all Running and Ready within 600 s")
                time.sleep(0.5)
            results["deploy_to_all_running_s"] = round(time.monotonic() - started, 1)
            results["pods"] = len(placement["instances"]) + sum(len(f["servers"]) for f in placement["discovery"])
            log(f"all {results['pods']} pods Running and Ready {results['deploy_to_all_running_s']} s after deploy")

            env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "sim"), str(REPO / ".collections")])}
            command = [sys.executable, "-m", "kuberos_sim.real_pods", "--kubeconfig", str(kubeconfig), "--fleet", FLEET,
                       "--robots", "robot-1", "--cycles", str(args.cycles), "--time-limit", str(args.time_limit)]  # fmt: skip
            done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=args.time_limit + 120)
            summary = json.loads(done.stdout[done.stdout.rindex("\n{") :]) if "\n{" in done.stdout else {}
            results["real_pods"] = summary
            log(f"real pods: {json.dumps(summary)}")
        finally:
            _none, results["teardown_s"] = timed("tier, teardown (absent)", lambda: cluster("absent"))
    after = snapshot_host()
    results["host_as_before"] = {k: before[k] == after[k] for k in before}

    out = Path(tempfile.mkdtemp(prefix="kuberos-bench-netns-"))
    command = [sys.executable, "-m", "kuberos_sim.evaluate", "--strategies", "cloud", "--robots", "1",
               "--rates", f"{args.rate:g}", "--cycles", str(args.cycles), "--out", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "sim"), str(REPO / ".collections")])}
    done, results["netns_runtime_s"] = timed(
        "netns runtime", lambda: subprocess.run(command, env=env, capture_output=True, text=True, timeout=args.time_limit + 600)
    )
    rows = json.loads((out / "results.json").read_text()) if (out / "results.json").exists() else []
    rows = rows.get("rows", rows) if isinstance(rows, dict) else rows
    results["netns_runtime"] = rows[0] if rows else {"error": done.stdout[-2000:] + done.stderr[-2000:]}

    real = results.get("real_pods", {}).get("cycles", {}).get("robot-1", {})
    print("\n| what | real pods | netns runtime |\n|---|---|---|")
    print(f"| pick cycles succeeded / asked | {real.get('succeeded')} / {args.cycles} | "
          f"{results['netns_runtime'].get('cycles_ok')} / {args.cycles} |")  # fmt: skip
    print(f"| planning latency p50 | {results.get('real_pods', {}).get('planning_latency_p50_ms')} ms | "
          f"{results['netns_runtime'].get('plan_p50_ms')} ms |")  # fmt: skip
    for key in ("images_cold_s", "images_cached_s", "tier_cold_start_s", "tier_warm_start_s", "deploy_playbook_s",
                "deploy_to_all_running_s", "teardown_s"):  # fmt: skip
        if key in results:
            print(f"| {key} | {results[key]} | |")
    print(f"\nimages: {results['image_mib']} MiB; host as before: {results['host_as_before']}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
