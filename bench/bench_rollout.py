#!/usr/bin/env python3
"""Rollout benchmark: upgrade one module on every robot of a 100-robot fleet with ``playbooks/rollout.yml``.

On a dedicated local control plane (its own ports and state directory; 100 robots, 20 edge and 10 cloud kwok
nodes by default) it deploys a pick-and-place app whose controller (onboard, holds the gripper: upgrade
``recreate``, stop-then-start) and motion planner (``surge``: the old pod serves until the new one is Ready) come
from a generated software catalog, then, each timed from the start of ``ansible-playbook`` to its exit:

(1) the controller 1.0.0 -> 1.1.0 on every robot (canary 1, waves of ``--wave-size``, soak ``--soak`` s);
(2) the motion planner 1.0.0 -> 1.1.0 on every robot, likewise;
(3) the motion planner 1.1.0 -> 1.2.0, a broken version: a watcher marks its pods crash-looping as a kubelet would
    (kwok nodes run no containers), so the rollout must stop at the canary and roll it back; the benchmark checks
    that every other robot's planner Deployment kept its resourceVersion.

The rollout module measures per replaced instance the seconds it had no Ready pod (polled every 0.2 s); the
largest is ``max_module_downtime_s``. Results print as Markdown and go to ``bench/results/rollout.json`` with
``--json``. Every wait is bounded; the cluster is removed at the end unless ``--keep-cluster``.

    .venv/bin/python bench/bench_rollout.py --json bench/results/rollout.json
    .venv/bin/python bench/bench_rollout.py --robots 20
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench_deploy import REPO, Cluster, check, log, machine, playbook, write_inventory
from workload import pick_and_place

FLEET = "bench-fleet"
NAMESPACE = f"kuberos-{FLEET}"
SPEC_NAME = "bench-pnp"
BROKEN_TAG = "1.2.0-crashloop"
TARGET_TOTAL_S = 300.0
TARGET_DOWNTIME_S = 5.0


def write_catalog(directory: Path) -> Path:
    """The controller and the motion planner of workload.pick_and_place as catalog modules, three versions each."""
    app = pick_and_place(SPEC_NAME, FLEET, "dedicated")
    modules = {m["name"]: m for m in app["rosModules"]}
    catalog = {"apiVersion": "kuberos.io/v1alpha1", "kind": "RosModuleCatalog", "modules": []}
    for name, module in (("bench-control", modules["controller"]), ("bench-planner", modules["motion-planner"])):
        image = module["image"].rsplit(":", 1)[0]
        versions = []
        for version in ("1.0.0", "1.1.0", "1.2.0"):
            tag = BROKEN_TAG if (name, version) == ("bench-planner", "1.2.0") else version
            entry = {"version": version, "image": f"{image}:{tag}", "launch": module["launch"], "rosDistro": "jazzy",
                     "architectures": ["amd64"], "resources": module["resources"]}  # fmt: skip
            for key in ("requirements", "preference", "rosParameters"):
                if key in module:
                    entry[key] = module[key]
            versions.append(entry)
        catalog["modules"].append({"name": name, "description": f"the benchmark's {module['name']}", "versions": versions})
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "bench.yml").write_text(json.dumps(catalog, indent=2) + "\n")
    return directory


def write_spec(path: Path, control: str, planner: str) -> Path:
    app = pick_and_place(SPEC_NAME, FLEET, "dedicated")
    for module in app["rosModules"]:
        if module["name"] in ("controller", "motion-planner"):
            ref = f"bench-control@{control}" if module["name"] == "controller" else f"bench-planner@{planner}"
            for key in ("image", "launch", "resources", "requirements", "preference", "rosParameters"):
                module.pop(key, None)
            module["module"] = ref
    path.write_text(json.dumps(app, indent=2) + "\n")
    return path


class CrashLooper(threading.Thread):
    """Marks every pod of the broken image as a kubelet reports a crash-looping container."""

    def __init__(self, core, deadline_s: float):
        super().__init__(daemon=True)
        self.core, self.deadline = core, time.monotonic() + deadline_s
        self.stop = threading.Event()
        self.marked: set[str] = set()

    def run(self):
        while not self.stop.is_set() and time.monotonic() < self.deadline:
            for pod in self.core.list_namespaced_pod(NAMESPACE, label_selector="kuberos.io/module=motion-planner").items:
                if not pod.spec.containers[0].image.endswith(BROKEN_TAG) or pod.metadata.name in self.marked:
                    continue
                statuses = [{"name": c.name, "ready": False, "restartCount": 3, "image": c.image, "imageID": "",
                             "started": False, "state": {"waiting": {"reason": "CrashLoopBackOff"}}}
                            for c in pod.spec.containers]  # fmt: skip
                try:
                    self.core.patch_namespaced_pod_status(
                        pod.metadata.name, NAMESPACE, {"status": {"containerStatuses": statuses}}
                    )
                    self.marked.add(pod.metadata.name)
                except Exception as exc:  # the pod went away meanwhile
                    log(f"crash-looper: {pod.metadata.name}: {exc.__class__.__name__}")
            time.sleep(0.2)


def rollout(inventory: Path, cluster: Cluster, spec: Path, args, expect_failure=False) -> dict:
    """Run playbooks/rollout.yml; its module result (JSON callback) and the wall time."""
    extra = {
        "kuberos_kubeconfig": str(cluster.kubeconfig), "rosdeployment_file": str(spec),
        "rosdeployment_rollout_wave_size": args.wave_size, "rosdeployment_rollout_canary": 1,
        "rosdeployment_rollout_soak": args.soak, "rosdeployment_rollout_gate_timeout": 120,
    }  # fmt: skip
    import os
    import subprocess

    from bench_deploy import ansible_env

    env = {**ansible_env(), "ANSIBLE_STDOUT_CALLBACK": "ansible.posix.json"}
    command = [
        str(REPO / ".venv" / "bin" / "ansible-playbook"),
        "playbooks/rollout.yml",
        "-i",
        str(inventory),
        "-e",
        json.dumps(extra),
    ]
    start = time.monotonic()
    done = subprocess.run(command, cwd=REPO, env={**os.environ, **env}, capture_output=True, text=True, timeout=args.timeout)
    wall = time.monotonic() - start
    if (done.returncode != 0) != expect_failure:
        expected = "failure" if expect_failure else "success"
        raise SystemExit(f"bench: rollout exit {done.returncode}, expected {expected}:\n{done.stdout[-4000:]}")
    report = json.loads(done.stdout)
    result = next(
        host_result
        for play in report["plays"]
        for task in play["tasks"]
        if task["task"]["name"].endswith("Roll out, wave by wave")
        for host_result in task["hosts"].values()
    )
    return {"wall_s": round(wall, 2), "result": result}


def summary(run: dict) -> dict:
    r = run["result"]
    return {
        "wall_s": run["wall_s"],
        "module_total_s": r.get("total_s"),
        "waves": len(r.get("waves", [])),
        "wave_seconds": [w["seconds"] for w in r.get("waves", [])],
        "replaced": len(r.get("downtime_s", {})),
        "max_module_downtime_s": r.get("max_module_downtime_s"),
        "revision": r.get("revision"),
    }


def markdown(data: dict) -> str:
    m = data["machine"]
    lines = [
        f"### Rollout, {data['robots']} robots ({m['date']}, commit {m['commit']})",
        "",
        f"Machine: {m['nproc']} cores ({m['cpu']}), {m['memory']}, Python {m['python']}, load {m['load']}.",
        f"Command: `{data['command']}`. Waves: canary 1, then {data['wave_size']} robots; soak {data['soak']} s.",
        "",
        "| run | wall (s) | waves | instances replaced | longest downtime of a module (s) |",
        "|---|---|---|---|---|",
    ]
    for name in ("controller_recreate", "planner_surge"):
        s = data[name]
        lines.append(f"| {name} | {s['wall_s']} | {s['waves']} | {s['replaced']} | {s['max_module_downtime_s']} |")
    b = data["broken"]
    lines += [
        "",
        f"Broken version: stopped at the canary: {data['broken_version_stopped_at_canary']}; rolled back: "
        f"{data['rolled_back']} (robots {', '.join(b['rolled_back_robots'])}); other robots' planners untouched: "
        f"{b['others_untouched']}; {b['wall_s']} s.",
        f"Targets: total under {TARGET_TOTAL_S:g} s with waves of 10 ({data['total_s']} s), no module down longer than "
        f"{TARGET_DOWNTIME_S:g} s ({data['max_module_downtime_s']} s).",
    ]
    return "\n".join(lines)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--wave-size", type=int, default=10)
    parser.add_argument("--soak", type=float, default=5.0)
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds any one step may take")
    parser.add_argument("--json", type=Path, help="write the results here (bench/results/rollout.json)")
    parser.add_argument("--keep-cluster", action="store_true")
    args = parser.parse_args(argv)
    if not 2 <= args.robots <= 500:
        parser.error("--robots must be 2 to 500")
    if not 1 <= args.wave_size <= args.robots:
        parser.error("--wave-size must be 1 to --robots")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="kuberos-bench-rollout-"))
    inventory = write_inventory(work / "inventory", args.robots, gpus=False)
    catalog = write_catalog(inventory / "catalog")
    all_vars = json.loads((inventory / "group_vars" / "all.yml").read_text().split("---\n", 1)[1])
    all_vars["kuberos_catalog"] = str(catalog)
    (inventory / "group_vars" / "all.yml").write_text("---\n" + json.dumps(all_vars, indent=2) + "\n")
    cluster = Cluster(inventory, work / "cluster", args.timeout)
    arguments = " ".join(argv if argv is not None else sys.argv[1:])
    data = {
        "robots": args.robots, "wave_size": args.wave_size, "soak": args.soak, "machine": machine(),
        "command": f"cd {REPO} && .venv/bin/python bench/bench_rollout.py {arguments}",
    }  # fmt: skip
    try:
        log(f"work dir {work}; starting the cluster")
        cluster.start()
        spec = write_spec(work / "v1.yml", "1.0.0", "1.0.0")
        start = time.monotonic()
        settings = {"kuberos_kubeconfig": str(cluster.kubeconfig), "rosdeployment_file": str(spec),
                    "kuberos_render_dir": str(work / "render")}  # fmt: skip
        check(playbook("deploy.yml", inventory, "-e", json.dumps(settings), timeout=args.timeout), "deploying")
        data["deploy_s"] = round(time.monotonic() - start, 2)
        log(f"deployed {args.robots} robots in {data['deploy_s']} s; rolling the controller out (recreate)")
        one = rollout(inventory, cluster, write_spec(work / "v2.yml", "1.1.0", "1.0.0"), args)
        data["controller_recreate"] = summary(one)
        log(f"controller: {data['controller_recreate']}; rolling the planner out (surge)")
        two = rollout(inventory, cluster, write_spec(work / "v3.yml", "1.1.0", "1.1.0"), args)
        data["planner_surge"] = summary(two)
        log(f"planner: {data['planner_surge']}; the broken planner")
        apps = cluster.apps()
        before = {d.metadata.name: d.metadata.resource_version for d in apps.list_namespaced_deployment(NAMESPACE).items}
        looper = CrashLooper(cluster.core(), args.timeout)
        looper.start()
        try:
            broken = rollout(inventory, cluster, write_spec(work / "v4.yml", "1.1.0", "1.2.0"), args, expect_failure=True)
        finally:
            looper.stop.set()
        result = broken["result"]
        after = {d.metadata.name: d.metadata.resource_version for d in apps.list_namespaced_deployment(NAMESPACE).items}
        touched = {n for n in before if before[n] != after.get(n)}
        planners = {n for n in before if "motion-planner" in n}
        rolled = result.get("rolled_back_robots", [])
        images = {
            d.spec.template.spec.containers[0].image
            for d in apps.list_namespaced_deployment(NAMESPACE).items
            if d.metadata.name in planners
        }
        data["broken"] = {
            "wall_s": broken["wall_s"], "msg": result.get("msg", "")[:500], "rolled_back_robots": rolled,
            "marked_pods": len(looper.marked), "touched_planners": sorted(touched & planners),
            "others_untouched": len(touched & planners) <= len(rolled), "planner_images_after": sorted(images),
        }  # fmt: skip
        data["broken_version_stopped_at_canary"] = bool(result.get("failed_canary"))
        data["rolled_back"] = not result.get("not_back") and all(not i.endswith(BROKEN_TAG) for i in images)
        data["total_s"] = data["controller_recreate"]["wall_s"]
        data["max_module_downtime_s"] = max(
            data["controller_recreate"]["max_module_downtime_s"], data["planner_surge"]["max_module_downtime_s"]
        )
        print(markdown(data))
        if args.json:
            keys = {
                k: data[k]
                for k in ("robots", "total_s", "max_module_downtime_s", "broken_version_stopped_at_canary", "rolled_back")
            }
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({**keys, "details": data}, indent=2) + "\n")
    finally:
        if not args.keep_cluster:
            cluster.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
