#!/usr/bin/env python3
"""Deploy benchmark: ``playbooks/deploy.yml`` against plain ``kubectl apply --server-side``.

On a dedicated local control plane (its own ports and state directory, 130 kwok nodes by default)
it deploys a pick-and-place app to a fleet of N robots (4 dedicated modules per robot, so 4·N module
pods, plus the fleet's discovery servers) twice per repeat, from the same starting state:

(a) ``ansible-playbook playbooks/deploy.yml``: validate, place, render, new namespaces, then the
    objects dealt into ``kuberos_apply_workers`` batches (default 4, ``--apply-workers``) that are
    server-side dry-run side by side and, once every batch passed, server-side applied side by side
    (one ``kubernetes.core.k8s`` call per batch), then prune beside the wait (rosdeployment_info)
    until every pod is Ready on its placed node. Timed from the start of the process to its exit. A
    watcher thread also notes when every pod was first seen Ready from outside, and the
    profile_tasks callback gives the time of every task.
(b) ``kubectl apply --server-side --field-manager=bench -R -f <render dir>/manifests`` of the
    manifests (a) rendered, then polling the pods until every one is Running and Ready. Timed from
    the start of kubectl until the poll sees every pod Ready.

Between runs the deployment is removed with ``playbooks/undeploy.yml`` and the benchmark waits until
no Deployment, ReplicaSet or Pod is left in the fleet's namespace (the namespace itself stays, so (b)
and every (a) after the first find it). Every wait is bounded by ``--timeout``; the cluster is
stopped and its state removed at the end, also on failure, unless ``--keep-cluster``.

    .venv/bin/python bench/bench_deploy.py                 # 100 robots, 3 pairs of runs
    .venv/bin/python bench/bench_deploy.py --robots 20 --repeat 1
    .venv/bin/python bench/bench_deploy.py --json /tmp/bench.json --keep-cluster

Needs the control-plane programs and kubectl in the cache (``make binaries WITH_KUBECTL=1``).
The result is printed as Markdown, ready to paste into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from workload import pick_and_place  # bench/ is on sys.path when a benchmark runs

REPO = Path(__file__).resolve().parent.parent
VENV_BIN = REPO / ".venv" / "bin"
CACHE_DIR = Path(os.environ.get("KUBEROS_CACHE_DIR") or Path.home() / ".cache" / "kuberos")
KUBECTL = CACHE_DIR / "bin" / "kubectl-v1.34.4"

FLEET = "bench-fleet"
NAMESPACE = f"kuberos-{FLEET}"
SPEC_NAME = "bench-pnp"
EDGE_NODES = 20
CLOUD_NODES = 10
DISCOVERY_SERVERS = 2
MODULES_PER_ROBOT = 4
FIELD_MANAGER = "bench"
MAX_ROBOTS = 1000  # 20 edge nodes x 110 pods hold perception + coordinator of about 1,000 robots
PORTS = {
    "apiserver": 36443,
    "etcd_client": 32379,
    "etcd_peer": 32380,
    "controller_manager": 36257,
    "scheduler": 36259,
    "kwok": 36247,
}
POLL_SECONDS = 0.5
TARGET_SECONDS = 60.0
TARGET_RATIO = 1.5
PROFILE_LINE = re.compile(r"^(?P<name>\S.*?) -+ ?(?P<seconds>\d+\.\d+)s$")
RECAP = re.compile(r"^(\S+)\s+: ok=\d+\s+changed=\d+\s+unreachable=(\d+)\s+failed=(\d+)", re.M)


# -- inputs --------------------------------------------------------------------------------
def write_inventory(directory: Path, robots: int, edge: int = EDGE_NODES, cloud: int = CLOUD_NODES, gpus: bool = True) -> Path:
    """An Ansible YAML inventory: N robots in one fleet, edge (every 4th with 2 GPUs) and cloud nodes (the first 4
    with 8 GPUs; no GPUs with ``gpus=False``), all local."""
    group_vars = directory / "group_vars"
    group_vars.mkdir(parents=True)
    hosts = {
        "all": {
            "children": {
                "robots": {"hosts": {f"robot-{i:03d}": None for i in range(robots)}},
                "edge": {"hosts": {f"edge-{i:02d}": ({"kuberos_gpu": 2} if gpus and i % 4 == 0 else None) for i in range(edge)}},
                "cloud": {"hosts": {f"cloud-{i:02d}": ({"kuberos_gpu": 8} if gpus and i < 4 else None) for i in range(cloud)}},
            }
        }
    }
    files = {
        "hosts.yml": hosts,
        "group_vars/all.yml": {
            "kuberos_default_latency_ms": {"onboard": 0, "edge": 5, "cloud": 40},
            "ansible_connection": "local",
            "ansible_python_interpreter": "{{ ansible_playbook_python }}",
        },
        "group_vars/robots.yml": {
            "kuberos_fleet": FLEET,
            "kuberos_cpu": 4,
            "kuberos_memory": "8Gi",
            "kuberos_gpu": 0,
            "kuberos_arch": "amd64",
            "kuberos_devices": ["camera", "gripper"],
        },
        "group_vars/edge.yml": {
            "kuberos_cpu": 32,
            "kuberos_memory": "64Gi",
            "kuberos_pods": 110,
            "kuberos_resource_group": "bench-site",
        },
        "group_vars/cloud.yml": {
            "kuberos_cpu": 64,
            "kuberos_memory": "128Gi",
            "kuberos_pods": 110,
            "kuberos_resource_group": "bench-cloud",
        },
    }
    for name, data in files.items():
        (directory / name).write_text("---\n" + json.dumps(data, indent=2) + "\n")  # JSON is YAML
    return directory


def write_spec(path: Path) -> Path:
    """Pick-and-place with four dedicated modules per robot (the coordinator is dedicated here)."""
    path.write_text(json.dumps(pick_and_place(SPEC_NAME, FLEET, "dedicated"), indent=2) + "\n")
    return path


# -- running things ------------------------------------------------------------------------
def ansible_env(profile: bool = False) -> dict:
    env = {**os.environ, "ANSIBLE_CONFIG": str(REPO / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    if profile:
        env.update(
            ANSIBLE_CALLBACKS_ENABLED="ansible.posix.profile_tasks",
            PROFILE_TASKS_SORT_ORDER="none",
            PROFILE_TASKS_TASK_OUTPUT_LIMIT="all",
        )
    return env


def playbook(name: str, inventory: Path, *extra: str, timeout: float, profile: bool = False) -> subprocess.CompletedProcess:
    command = [str(VENV_BIN / "ansible-playbook"), f"playbooks/{name}", "-i", str(inventory), *extra]
    return subprocess.run(command, cwd=REPO, env=ansible_env(profile), capture_output=True, text=True, timeout=timeout)


def check(result: subprocess.CompletedProcess, what: str) -> None:
    if result.returncode != 0:
        tail = "\n".join((result.stdout + result.stderr).splitlines()[-60:])
        raise SystemExit(f"bench: {what} failed (exit {result.returncode}):\n{tail}")


def parse_profile(stdout: str) -> list[tuple[str, float]]:
    """The profile_tasks summary (after the TASKS RECAP banner), in execution order."""
    _head, _sep, recap = stdout.rpartition("TASKS RECAP")
    rows = []
    for line in recap.splitlines():
        match = PROFILE_LINE.match(line.strip())
        if match:
            rows.append((match["name"], float(match["seconds"])))
    return rows


class Cluster:
    def __init__(self, inventory: Path, state_dir: Path, timeout: float):
        self.inventory = inventory
        self.state_dir = state_dir
        self.kubeconfig = state_dir / "kubeconfig"
        self.timeout = timeout
        self.vars = json.dumps(
            {"local_cluster_state_dir": str(state_dir), "local_cluster_ports": PORTS, "local_cluster_timeout": int(timeout)}
        )

    def start(self) -> float:
        start = time.monotonic()
        check(playbook("local_cluster.yml", self.inventory, "-e", self.vars, timeout=self.timeout + 600), "starting the cluster")
        return time.monotonic() - start

    def stop(self) -> subprocess.CompletedProcess:
        return playbook("local_cluster.yml", self.inventory, "-e", self.vars, "-e", "local_cluster_state=absent", timeout=300)

    def core(self):
        from kubernetes import client, config

        return client.CoreV1Api(config.new_client_from_config(config_file=str(self.kubeconfig)))

    def apps(self):
        from kubernetes import client, config

        return client.AppsV1Api(config.new_client_from_config(config_file=str(self.kubeconfig)))


def pod_state(core) -> tuple[int, int, list]:
    """(live pods, live pods Running and Ready, live pods) in the fleet's namespace."""
    pods = [p for p in core.list_namespaced_pod(NAMESPACE).items if not p.metadata.deletion_timestamp]
    ready = sum(
        1
        for p in pods
        if p.status.phase == "Running" and any(c.type == "Ready" and c.status == "True" for c in (p.status.conditions or []))
    )
    return len(pods), ready, pods


def wait_all_ready(core, expected: int, start: float, deadline: float, stop: threading.Event | None = None) -> float | None:
    """Seconds from ``start`` until exactly ``expected`` live pods are all Running and Ready; None on timeout."""
    while time.monotonic() < deadline and not (stop and stop.is_set()):
        live, ready, _pods = pod_state(core)
        if live == expected and ready == expected:
            return time.monotonic() - start
        time.sleep(POLL_SECONDS)
    return None


def not_ready_report(core, limit: int = 15) -> str:
    _live, _ready, pods = pod_state(core)
    lines = []
    for p in pods:
        conditions = {c.type: c for c in (p.status.conditions or [])}
        if p.status.phase == "Running" and conditions.get("Ready") and conditions["Ready"].status == "True":
            continue
        scheduled = conditions.get("PodScheduled")
        why = f"{scheduled.reason}: {scheduled.message}" if scheduled and scheduled.status != "True" else ""
        lines.append(f"  {p.metadata.name}: {p.status.phase} on {p.spec.node_name or '-'} {why}".rstrip())
    return f"{len(lines)} pods not Ready (of {len(pods)} live):\n" + "\n".join(lines[:limit])


def wait_empty(cluster: Cluster, deadline: float) -> None:
    core, apps = cluster.core(), cluster.apps()
    while time.monotonic() < deadline:
        left = (
            len(apps.list_namespaced_deployment(NAMESPACE).items),
            len(apps.list_namespaced_replica_set(NAMESPACE).items),
            len(core.list_namespaced_pod(NAMESPACE).items),
        )
        if left == (0, 0, 0):
            return
        time.sleep(POLL_SECONDS)
    raise SystemExit(f"bench: {NAMESPACE} not empty after undeploy (deployments, replicasets, pods = {left})")


def teardown(cluster: Cluster, spec: Path, timeout: float) -> float:
    start = time.monotonic()
    result = playbook(
        "undeploy.yml", cluster.inventory, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}",
        timeout=timeout,
    )  # fmt: skip
    check(result, "undeploy")
    wait_empty(cluster, start + timeout)
    return time.monotonic() - start


def run_ansible(cluster: Cluster, spec: Path, render_dir: Path, expected: int, timeout: float, workers: int | None) -> dict:
    """(a): the deploy playbook; wall time of the process, and when all pods were first seen Ready."""
    watcher_core = cluster.core()
    seen: dict[str, float | None] = {"ready": None}
    stop = threading.Event()
    start = time.monotonic()
    watcher = threading.Thread(
        target=lambda: seen.update(ready=wait_all_ready(watcher_core, expected, start, start + timeout + 60, stop)), daemon=True
    )
    watcher.start()
    result = playbook(
        "deploy.yml", cluster.inventory,
        "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={render_dir}",
        "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", "-e", f"rosdeployment_wait_timeout={int(timeout)}",
        *(["-e", f"kuberos_apply_workers={workers}"] if workers else []),
        timeout=timeout + 120, profile=True,
    )  # fmt: skip
    wall = time.monotonic() - start
    watcher.join(timeout=10)
    stop.set()
    if result.returncode != 0:
        print(not_ready_report(cluster.core()), file=sys.stderr)
    check(result, "deploy.yml")
    recap = {host: (unreachable, failed) for host, unreachable, failed in RECAP.findall(result.stdout)}
    if "localhost" not in recap or set(recap.values()) != {("0", "0")}:
        raise SystemExit("bench: deploy.yml recap missing or failed:\n" + result.stdout[-3000:])
    live, ready, _pods = pod_state(cluster.core())
    if (live, ready) != (expected, expected):
        raise SystemExit(
            f"bench: after deploy.yml {ready} of {live} pods Ready, expected {expected}\n{not_ready_report(cluster.core())}"
        )
    profile = parse_profile(result.stdout)
    return {
        "wall_s": wall,
        "ready_seen_s": seen["ready"],
        "profile": profile,
        "tasks_s": sum(s for _n, s in profile),
        "batch_hosts": sorted(h for h in recap if h != "localhost"),
    }


def run_kubectl(cluster: Cluster, manifests: Path, expected: int, timeout: float, cache_dir: Path) -> dict:
    """(b): kubectl server-side apply of the rendered manifests, then poll until every pod is Ready."""
    core = cluster.core()
    command = [
        str(KUBECTL), f"--kubeconfig={cluster.kubeconfig}", f"--cache-dir={cache_dir}",
        "apply", "--server-side", f"--field-manager={FIELD_MANAGER}", "-R", "-f", str(manifests),
    ]  # fmt: skip
    start = time.monotonic()
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    applied = time.monotonic() - start
    check(result, "kubectl apply")
    ready = wait_all_ready(core, expected, start, start + timeout)
    if ready is None:
        raise SystemExit(f"bench: kubectl path not Ready after {timeout} s\n{not_ready_report(core)}")
    return {"wall_s": ready, "apply_s": applied, "objects": len(result.stdout.splitlines())}


# -- report --------------------------------------------------------------------------------
def machine() -> dict:
    def sh(command: str) -> str:
        return subprocess.run(command, shell=True, capture_output=True, text=True).stdout.strip()

    return {
        "date": sh("date -u"),
        "nproc": sh("nproc"),
        "cpu": sh("lscpu | sed -n 's/^Model name: *//p'"),
        "memory": sh('free -h | awk \'/^Mem:/ {print $2 " total, " $7 " available"}\''),
        "python": sys.version.split()[0],
        "kernel": sh("uname -r"),
        "load": sh("cat /proc/loadavg | cut -d' ' -f1-3"),
        "commit": sh(f"git -C {REPO} rev-parse --short HEAD")
        + (" (+ uncommitted changes)" if sh(f"git -C {REPO} status --porcelain") else ""),
    }


def markdown(data: dict) -> str:
    runs, args, info = data["runs"], data["args"], data["machine"]
    out = [
        f"## Deploy benchmark: {args['robots']} robots ({data['expected_pods']} pods), deploy.yml vs kubectl apply --server-side",
        "",
        f"Date: {info['date']}. Machine: nproc {info['nproc']}, {info['cpu']}, memory {info['memory']}; "
        f"Python {info['python']}, Linux {info['kernel']}; code at {info['commit']}.",
        "",
        f"Load average (1, 5, 15 min) at the start: {info['load']}; at the end: {data.get('load_end', '-')}.",
        "",
        f"Command: `{data['command']}`",
        "",
        f"Cluster: {data['nodes']} kwok nodes ({args['robots']} robots, {EDGE_NODES} edge, {CLOUD_NODES} cloud), "
        f"started in {data['cluster_start_s']:.1f} s; {data['objects']} objects rendered "
        f"({data['expected_pods']} Deployments of 1 replica, so {data['expected_pods']} pods). "
        f"Batch hosts of (a): {len(runs[0]['a']['batch_hosts']) if runs else '-'}.",
        "",
        "| run | (a) deploy.yml s | (a) all Ready seen s | (b) kubectl apply s | (b) until all Ready s "
        "| ratio (a)/(b) | undeploy+empty s |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, run in enumerate(runs, 1):
        a, b = run["a"], run["b"]
        seen = f"{a['ready_seen_s']:.1f}" if a["ready_seen_s"] is not None else "-"
        out.append(
            f"| {i} | {a['wall_s']:.1f} | {seen} | {b['apply_s']:.1f} | {b['wall_s']:.1f} | {a['wall_s'] / b['wall_s']:.2f} "
            f"| {run['teardown_a_s']:.1f} / {run['teardown_b_s']:.1f} |"
        )
    med_a = statistics.median(r["a"]["wall_s"] for r in runs)
    med_b = statistics.median(r["b"]["wall_s"] for r in runs)
    med_ratio = statistics.median(r["a"]["wall_s"] / r["b"]["wall_s"] for r in runs)
    out.append(f"| **median** | **{med_a:.1f}** | | | **{med_b:.1f}** | **{med_ratio:.2f}** | |")
    out += [
        "",
        f"Target: (a) under {TARGET_SECONDS:.0f} s: **{'met' if med_a < TARGET_SECONDS else 'missed'}** ({med_a:.1f} s); "
        f"ratio under {TARGET_RATIO}: **{'met' if med_ratio < TARGET_RATIO else 'missed'}** ({med_ratio:.2f}).",
        "",
        "Per-task profile of (a) (`ansible.posix.profile_tasks`, execution order, seconds). A task's time runs until "
        "the next task starts, so for a task of the batch hosts it is that of the slowest batch; in the last play "
        "(strategy free) the prune and the wait overlap, so their times do not add up:",
        "",
        "| task | " + " | ".join(f"run {i}" for i in range(1, len(runs) + 1)) + " |",
        "|---|" + "---:|" * len(runs),
    ]
    names = [name for name, _s in runs[0]["a"]["profile"]]
    for index, name in enumerate(names):
        cells = []
        for run in runs:
            profile = run["a"]["profile"]
            cells.append(f"{profile[index][1]:.2f}" if index < len(profile) and profile[index][0] == name else "-")
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    out.append("| sum of tasks | " + " | ".join(f"{r['a']['tasks_s']:.2f}" for r in runs) + " |")
    out.append(
        "| process wall - sum of tasks (start-up, parsing, exit) | "
        + " | ".join(f"{r['a']['wall_s'] - r['a']['tasks_s']:.2f}" for r in runs)
        + " |"
    )
    return "\n".join(out) + "\n"


# -- main ----------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Ports used: "
        + ", ".join(f"{k} {v}" for k, v in PORTS.items())
        + ". Output: Markdown on stdout, progress on stderr.",
    )
    parser.add_argument("--robots", type=int, default=100, help="robots in the fleet (4 module pods each); default 100")
    parser.add_argument("--repeat", type=int, default=3, help="pairs of runs (a), (b), 1 to 5; default 3")
    parser.add_argument("--timeout", type=int, default=300, help="bound of every deploy and wait, seconds; default 300")
    parser.add_argument(
        "--apply-workers", type=int, help="kuberos_apply_workers for (a), 1 to 10 (ansible.cfg forks); default: the role's, 4"
    )
    parser.add_argument("--keep-cluster", action="store_true", help="leave the cluster (and its work dir) running at the end")
    parser.add_argument(
        "--workdir", type=Path, help="where inventory, spec, renders and cluster state go (default: a new temp dir)"
    )
    parser.add_argument("--json", type=Path, help="also write the raw results (every run, every task) to this file")
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be 1 to {MAX_ROBOTS}")
    if not 1 <= args.repeat <= 5:
        parser.error("--repeat must be 1 to 5")
    if args.apply_workers is not None and not 1 <= args.apply_workers <= 10:
        parser.error("--apply-workers must be 1 to 10")
    if args.timeout < 10:
        parser.error("--timeout must be at least 10 s")
    return args


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not KUBECTL.exists():
        raise SystemExit(f"bench: {KUBECTL} missing; run `make binaries WITH_KUBECTL=1`")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="kuberos-bench-deploy-"))
    work.mkdir(parents=True, exist_ok=True)
    inventory = write_inventory(work / "inventory", args.robots)
    spec = write_spec(work / f"{SPEC_NAME}.yml")
    render_dir = work / "render"
    cluster = Cluster(inventory, work / "cluster", args.timeout)
    expected = args.robots * MODULES_PER_ROBOT + DISCOVERY_SERVERS
    data = {
        "args": {"robots": args.robots, "repeat": args.repeat, "timeout": args.timeout, "apply_workers": args.apply_workers},
        "command": " ".join(
            ["cd", str(REPO), "&&", ".venv/bin/python", "bench/bench_deploy.py", *(argv if argv is not None else sys.argv[1:])]
        ),
        "machine": machine(),
        "expected_pods": expected,
        "runs": [],
    }
    log(f"work dir {work}; starting the cluster")
    finished = False
    try:
        data["cluster_start_s"] = cluster.start()
        data["nodes"] = len(cluster.core().list_node(label_selector="kuberos.io/role").items)
        log(f"cluster up with {data['nodes']} nodes in {data['cluster_start_s']:.1f} s")
        for index in range(args.repeat):
            log(f"run {index + 1}: (a) deploy.yml")
            a = run_ansible(cluster, spec, render_dir, expected, args.timeout, args.apply_workers)
            log(f"run {index + 1}: (a) {a['wall_s']:.1f} s (all Ready seen at {a['ready_seen_s']}); undeploying")
            teardown_a = teardown(cluster, spec, args.timeout)
            manifests = render_dir / "manifests"
            data["objects"] = sum(1 for _ in manifests.rglob("*.yaml"))
            deployments = sum(1 for _ in manifests.rglob("deployment-*.yaml"))
            if deployments != expected:
                raise SystemExit(f"bench: {deployments} Deployments rendered, expected {expected}")
            log(f"run {index + 1}: (b) kubectl apply --server-side of {data['objects']} objects")
            b = run_kubectl(cluster, manifests, expected, args.timeout, work / "kubectl-cache")
            log(
                f"run {index + 1}: (b) {b['wall_s']:.1f} s (apply {b['apply_s']:.1f} s); "
                f"ratio {a['wall_s'] / b['wall_s']:.2f}; undeploying"
            )
            teardown_b = teardown(cluster, spec, args.timeout)
            data["runs"].append({"a": a, "b": b, "teardown_a_s": teardown_a, "teardown_b_s": teardown_b})
        finished = True
    finally:
        if args.keep_cluster:
            log(f"cluster kept: KUBECONFIG={cluster.kubeconfig}; stop it with local_cluster_state=absent and -e '{cluster.vars}'")
        else:
            log("stopping the cluster")
            stopped = cluster.stop()
            if stopped.returncode != 0:
                log("stopping the cluster failed:\n" + (stopped.stdout + stopped.stderr)[-2000:])
            elif args.workdir is None and finished:
                shutil.rmtree(work, ignore_errors=True)
            else:
                log(f"work dir kept: {work}")
        data["load_end"] = machine()["load"]
        if args.json:
            args.json.write_text(json.dumps(data, indent=2, default=str) + "\n")
    print(markdown(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
