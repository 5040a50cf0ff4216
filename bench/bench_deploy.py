#!/usr/bin/env python3
"""Deploy benchmark: ``playbooks/deploy.yml`` against ``kubectl apply --server-side`` doing the same work.

On a dedicated local control plane (its own ports and state directory; one kwok node per robot plus 20 edge and 10
cloud nodes: 130 at 100 robots, 1,030 at 1,000) it deploys a pick-and-place app to a fleet of N robots: 4 dedicated
modules per robot, so 4·N module pods, plus each robot's own discovery server (N) and the fleet's 2. Every repeat
runs the three ways below, each from the same starting state: the fleet's namespace exists and holds none of the
deployment's objects.

(a) ``ansible-playbook playbooks/deploy.yml``, timed from the start of the process to its exit (the playbook itself
    waits until every pod is Ready). A watcher notes when every pod was first seen Ready from outside. Then, with
    nothing changed:
    - the re-run: ``deploy.yml`` again, timed to its exit. It must touch nothing: the pods (names, uids, restart
      counts) and ReplicaSets are compared before and after, and the objects whose resourceVersion changed (the
      Namespace, Deployments, Services, ConfigMaps) are counted;
    - the undeploy: ``playbooks/undeploy.yml``, timed to its exit and until the namespace is empty (no Deployment,
      ReplicaSet, Pod, Service, or ConfigMap other than kube-root-ca.crt; a namespace that is gone is empty too).
(b) kubectl doing the work of the deploy: ``kubectl apply --server-side --dry-run=server -R -f <manifests>`` of every
    object, then ``kubectl apply --server-side -R -f <manifests>``, then a poll until every pod is Running and Ready.
    Timed from the start of the dry run until the poll sees every pod Ready.
(c) plain ``kubectl apply --server-side -R -f <manifests>``, then the same poll; timed from the start of kubectl.

(b) and (c) are removed with undeploy.yml too (timed, recorded, not a key). The order of (a), (b) and (c) turns by one
every repeat (run 1: a b c, run 2: b c a, run 3: c a b), so that none always runs first.

The namespace: deploy.yml creates a fleet's namespace only when it is new; when it exists, deploy.yml applies it with
the other objects. Before the first run the benchmark renders the deployment once (``kuberos_apply=false``, not timed)
and creates the namespace from that render as deploy.yml would (server-side apply, field manager ``kuberos``), and
undeploy.yml keeps it. So every (a) finds the namespace, and (b) and (c) apply it with the other objects (their dry run
needs it to exist) without creating it: the three do the same work. If an undeploy removes the namespace, it is created
again, not timed, before the next run. (b) and (c) apply that render's manifests with field manager ``bench``.

Output: Markdown on stdout (progress on stderr), and a JSON file (``--results``; default bench/results/deploy.json at
100 robots, bench/results/deploy-<N>.json otherwise) with the issue's keys (``robots``, ``deploy_s_median``,
``kubectl_same_work_s_median``, ``kubectl_plain_s_median``, ``ratio_median``: the median of the per-repeat ratios
(a)/(b), ``ratio_plain_median``: (a)/(c), ``rerun_s_median``, ``undeploy_s_median``), every run's raw values, the
machine, the load at the start and end of the benchmark and of every repeat, the date and the commit. Targets, checked
at 100 robots only, are printed as PASS or FAIL; the exit status does not depend on them: ratio_median ≤ 1.2,
ratio_plain_median ≤ 1.5, rerun_s_median < 5 s.

    .venv/bin/python bench/bench_deploy.py                         # 100 robots, 3 repeats
    .venv/bin/python bench/bench_deploy.py --robots 5 --repeat 1   # smoke run
    .venv/bin/python bench/bench_deploy.py --robots 1000 --repeat 1 --timeout 900

Every deploy and wait is bounded by ``--timeout``. The cluster is stopped and its state removed at the end, also on
failure or SIGTERM, unless ``--keep-cluster``. The per-task profile of (a) (``--profile``, on by default) comes from
the profile_tasks callback and takes whatever tasks the playbook has. Needs the control-plane programs and kubectl in
the cache (``make binaries WITH_KUBECTL=1``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from workload import pick_and_place  # bench/ is on sys.path when a benchmark runs

REPO = Path(__file__).resolve().parent.parent
VENV_BIN = REPO / ".venv" / "bin"
CACHE_DIR = Path(os.environ.get("KUBEROS_CACHE_DIR") or Path.home() / ".cache" / "kuberos")
KUBECTL = CACHE_DIR / "bin" / "kubectl-v1.34.4"
RESULTS_DIR = REPO / "bench" / "results"

FLEET = "bench-fleet"
NAMESPACE = f"kuberos-{FLEET}"
SPEC_NAME = "bench-pnp"
EDGE_NODES = 20
CLOUD_NODES = 10
DISCOVERY_SERVERS = 2
MODULES_PER_ROBOT = 4
ROBOT_SERVERS = 1  # each robot's own discovery server, on its computer (robotServers, the default)
FIELD_MANAGER = "bench"
DEPLOY_FIELD_MANAGER = "kuberos"  # deploy.yml's (rosdeployment_field_manager): the namespace is created as it would
MAX_ROBOTS = 1000  # 20 edge nodes x 110 pods hold perception + coordinator of about 1,000 robots
PORTS = {
    "apiserver": 36443,
    "etcd_client": 32379,
    "etcd_peer": 32380,
    "controller_manager": 36257,
    "scheduler": 36259,
    "kwok": 36247,
}
POLL_SECONDS = 0.5  # at least; a poll waits twice as long as the last list took (4,002 pods at 1,000 robots)
TARGET_ROBOTS = 100
# key, comparison, bound: the targets at TARGET_ROBOTS robots
TARGETS = (("ratio_median", "<=", 1.2), ("ratio_plain_median", "<=", 1.5), ("rerun_s_median", "<", 5.0))
PROFILE_LINE = re.compile(r"^(?P<name>\S.*?) -+ ?(?P<seconds>\d+\.\d+)s$")
RECAP = re.compile(r"^(\S+)\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=(\d+)\s+failed=(\d+)", re.M)
VARIANTS = "abc"


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
            "kuberos_pin_images": False,  # synthetic images on kwok nodes: no registry serves them
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
    """Run a playbook in a process group of its own: on a timeout, SIGTERM or Ctrl-C the whole group is killed, the
    worker forks and their modules too (killing ansible-playbook alone leaves its workers running)."""
    command = [str(VENV_BIN / "ansible-playbook"), f"playbooks/{name}", "-i", str(inventory), *extra]
    pipe = subprocess.PIPE
    with subprocess.Popen(
        command, cwd=REPO, env=ansible_env(profile), stdout=pipe, stderr=pipe, text=True, start_new_session=True
    ) as process:
        try:
            stdout, stderr = process.communicate(timeout=timeout)
        except BaseException:
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            process.communicate()
            raise
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def check(result: subprocess.CompletedProcess, what: str) -> None:
    if result.returncode != 0:
        tail = "\n".join((result.stdout + result.stderr).splitlines()[-60:])
        raise SystemExit(f"bench: {what} failed (exit {result.returncode}):\n{tail}")


def parse_profile(stdout: str) -> list[tuple[str, float]]:
    """The profile_tasks summary (after the TASKS RECAP banner), in execution order; empty without it. Any task
    names: the tasks are whatever the playbook runs."""
    _head, sep, recap = stdout.rpartition("TASKS RECAP")
    rows = []
    for line in recap.splitlines() if sep else []:
        match = PROFILE_LINE.match(line.strip())
        if match:
            rows.append((match["name"], float(match["seconds"])))
    return rows


def parse_recap(result: subprocess.CompletedProcess, what: str) -> dict[str, dict[str, int]]:
    """The PLAY RECAP counts per host; stops the benchmark when a host failed or was unreachable, or there is none."""
    keys = ("ok", "changed", "unreachable", "failed")
    recap = {host: dict(zip(keys, map(int, counts), strict=True)) for host, *counts in RECAP.findall(result.stdout)}
    if not recap or any(counts["unreachable"] or counts["failed"] for counts in recap.values()):
        raise SystemExit(f"bench: {what}: recap missing or failed:\n" + result.stdout[-3000:])
    return recap


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


# -- what the cluster holds ----------------------------------------------------------------
def items(list_call, *args, **kwargs) -> list[dict]:
    """A list call of the Python client, as plain JSON (no model objects: 4,002 pods deserialize in a fraction of the
    time)."""
    return json.loads(list_call(*args, _preload_content=False, **kwargs).data)["items"]


def is_ready(pod: dict) -> bool:
    status = pod.get("status") or {}
    conditions = status.get("conditions") or []
    return status.get("phase") == "Running" and any(c.get("type") == "Ready" and c.get("status") == "True" for c in conditions)


def live_pods(core) -> list[dict]:
    """The fleet namespace's pods that are not being deleted."""
    return [p for p in items(core.list_namespaced_pod, NAMESPACE) if not p["metadata"].get("deletionTimestamp")]


def wait_all_ready(core, expected: int, start: float, deadline: float, stop: threading.Event | None = None) -> float | None:
    """Seconds from ``start`` until exactly ``expected`` live pods are all Running and Ready; None on timeout."""
    while time.monotonic() < deadline and not (stop and stop.is_set()):
        listed = time.monotonic()
        pods = live_pods(core)
        if len(pods) == expected and all(map(is_ready, pods)):
            return time.monotonic() - start
        time.sleep(max(POLL_SECONDS, 2 * (time.monotonic() - listed)))
    return None


def not_ready_report(core, limit: int = 15) -> str:
    pods = live_pods(core)
    lines = []
    for pod in (p for p in pods if not is_ready(p)):
        scheduled = next((c for c in pod["status"].get("conditions") or [] if c.get("type") == "PodScheduled"), {})
        why = f"{scheduled.get('reason')}: {scheduled.get('message')}" if scheduled.get("status") == "False" else ""
        node = pod["spec"].get("nodeName") or "-"
        lines.append(f"  {pod['metadata']['name']}: {pod['status'].get('phase')} on {node} {why}".rstrip())
    return f"{len(lines)} pods not Ready (of {len(pods)} live):\n" + "\n".join(lines[:limit])


def left_in_namespace(cluster: Cluster) -> dict[str, int]:
    """Kinds of the deployment that still have an object in the fleet's namespace (1 means at least one)."""
    core, apps = cluster.core(), cluster.apps()
    calls = {
        "Deployment": (apps.list_namespaced_deployment, {}),
        "ReplicaSet": (apps.list_namespaced_replica_set, {}),
        "Pod": (core.list_namespaced_pod, {}),
        "Service": (core.list_namespaced_service, {}),
        "ConfigMap": (core.list_namespaced_config_map, {"field_selector": "metadata.name!=kube-root-ca.crt"}),
    }
    left = {kind: len(items(call, NAMESPACE, limit=1, **kwargs)) for kind, (call, kwargs) in calls.items()}
    return {kind: n for kind, n in left.items() if n}


def wait_empty(cluster: Cluster, start: float, deadline: float) -> float:
    """Seconds from ``start`` until the fleet's namespace holds none of the deployment's objects (or is gone)."""
    while time.monotonic() < deadline:
        left = left_in_namespace(cluster)
        if not left:
            return time.monotonic() - start
        time.sleep(POLL_SECONDS)
    raise SystemExit(f"bench: {NAMESPACE} not empty {deadline - start:.0f} s after undeploy: still {sorted(left)}")


def snapshot(cluster: Cluster) -> dict:
    """What a deploy that changes nothing must leave as it is: the pods (uid, restarts), the ReplicaSets, and the
    resourceVersion of every object the deployment applies."""
    core, apps = cluster.core(), cluster.apps()
    pods = {
        p["metadata"]["name"]: (
            p["metadata"]["uid"],
            sum(c.get("restartCount", 0) for c in p["status"].get("containerStatuses") or []),
        )
        for p in items(core.list_namespaced_pod, NAMESPACE)
    }
    versions = {}
    for kind, call in (
        ("Deployment", apps.list_namespaced_deployment),
        ("Service", core.list_namespaced_service),
        ("ConfigMap", core.list_namespaced_config_map),
    ):
        versions.update({f"{kind}/{o['metadata']['name']}": o["metadata"]["resourceVersion"] for o in items(call, NAMESPACE)})
    namespace = json.loads(core.read_namespace(NAMESPACE, _preload_content=False).data)
    versions[f"Namespace/{NAMESPACE}"] = namespace["metadata"]["resourceVersion"]
    replica_sets = sorted(o["metadata"]["uid"] for o in items(apps.list_namespaced_replica_set, NAMESPACE))
    return {"pods": pods, "replica_sets": replica_sets, "versions": versions}


# -- the three ways to deploy, and the starting state ----------------------------------------
@dataclass(frozen=True)
class Setup:
    """The fixed inputs of every run."""

    cluster: Cluster
    spec: Path
    render_dir: Path  # where (a) renders
    manifests: Path  # the untimed render's manifests, which (b) and (c) apply
    namespace_files: tuple[Path, ...]  # its Namespace manifests
    expected: int  # pods
    timeout: float
    workers: int | None
    profile: bool
    kubectl_cache: Path


def kubectl(setup: Setup, *arguments: str, what: str) -> subprocess.CompletedProcess:
    command = [str(KUBECTL), f"--kubeconfig={setup.cluster.kubeconfig}", f"--cache-dir={setup.kubectl_cache}", *arguments]
    result = subprocess.run(command, capture_output=True, text=True, timeout=setup.timeout)
    check(result, what)
    return result


def deploy_playbook(setup: Setup, render_dir: Path, *extra: str, profile: bool = False) -> subprocess.CompletedProcess:
    return playbook(
        "deploy.yml", setup.cluster.inventory,
        "-e", f"rosdeployment_file={setup.spec}", "-e", f"kuberos_render_dir={render_dir}",
        "-e", f"kuberos_kubeconfig={setup.cluster.kubeconfig}", "-e", f"rosdeployment_wait_timeout={int(setup.timeout)}",
        *(["-e", f"kuberos_apply_workers={setup.workers}"] if setup.workers else []), *extra,
        timeout=setup.timeout + 120, profile=profile,
    )  # fmt: skip


def render_once(cluster: Cluster, spec: Path, directory: Path, timeout: float) -> Path:
    """Render without applying (not timed): the manifests (b) and (c) apply, and the Namespace to create."""
    result = playbook(
        "deploy.yml", cluster.inventory, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={directory}",
        "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", "-e", "kuberos_apply=false", timeout=timeout + 120,
    )  # fmt: skip
    check(result, "deploy.yml (render only)")
    manifests = directory / "manifests"
    if not any(manifests.rglob("*.yaml")):
        raise SystemExit(f"bench: deploy.yml with kuberos_apply=false rendered no manifests into {manifests}")
    return manifests


def manifest_kinds(manifests: Path) -> dict[str, list[Path]]:
    """The files of the render by kind of the object(s) they hold."""
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    kinds: dict[str, list[Path]] = {}
    for path in sorted(manifests.rglob("*.yaml")):
        for document in yaml.load_all(path.read_text(), Loader=loader):
            if document:
                kinds.setdefault(document["kind"], []).append(path)
    return kinds


def ensure_start_state(setup: Setup) -> None:
    """Not timed: wait until the namespace holds nothing of the deployment, and create it if an undeploy removed it."""
    from kubernetes.client.exceptions import ApiException

    deadline = time.monotonic() + setup.timeout
    wait_empty(setup.cluster, time.monotonic(), deadline)
    core = setup.cluster.core()
    while True:
        try:
            namespace = core.read_namespace(NAMESPACE)
        except ApiException as error:
            if error.status != 404:
                raise
            log(f"creating the namespace {NAMESPACE} (not timed)")
            files = [arg for path in setup.namespace_files for arg in ("-f", str(path))]
            manager = f"--field-manager={DEPLOY_FIELD_MANAGER}"
            kubectl(setup, "apply", "--server-side", manager, *files, what="creating the namespace")
            return
        if namespace.status.phase != "Terminating":
            return
        if time.monotonic() > deadline:
            raise SystemExit(f"bench: namespace {NAMESPACE} still Terminating after {setup.timeout} s")
        time.sleep(POLL_SECONDS)


def check_all_ready(setup: Setup, what: str) -> None:
    core = setup.cluster.core()
    pods = live_pods(core)
    ready = sum(map(is_ready, pods))
    if (len(pods), ready) != (setup.expected, setup.expected):
        report = not_ready_report(core)
        raise SystemExit(f"bench: after {what} {ready} of {len(pods)} pods Ready, expected {setup.expected}\n{report}")


def run_deploy(setup: Setup) -> dict:
    """(a): deploy.yml; wall time of the process, and when all pods were first seen Ready from outside."""
    watcher_core = setup.cluster.core()
    seen: dict[str, float | str | None] = {"ready": None}
    stop = threading.Event()
    start = time.monotonic()
    deadline = start + setup.timeout + 60

    def watch() -> None:
        try:
            seen["ready"] = wait_all_ready(watcher_core, setup.expected, start, deadline, stop)
        except Exception as error:  # the watcher only informs; the deploy's own checks follow
            seen["error"] = repr(error)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        result = deploy_playbook(setup, setup.render_dir, profile=setup.profile)
        wall = time.monotonic() - start
        watcher.join(timeout=10)
    finally:
        stop.set()
    if result.returncode != 0:
        print(not_ready_report(setup.cluster.core()), file=sys.stderr)
    check(result, "deploy.yml")
    recap = parse_recap(result, "deploy.yml")
    check_all_ready(setup, "deploy.yml")
    profile = parse_profile(result.stdout)
    return {
        "wall_s": wall,
        "ready_seen_s": seen["ready"],
        **({"watcher_error": seen["error"]} if "error" in seen else {}),
        "recap": recap,
        "profile": profile,
        "tasks_s": sum(s for _n, s in profile) if profile else None,
    }


def run_rerun(setup: Setup) -> dict:
    """deploy.yml again with nothing changed: time to exit, and whether it left every pod and object as it was."""
    before = snapshot(setup.cluster)
    start = time.monotonic()
    result = deploy_playbook(setup, setup.render_dir, profile=setup.profile)
    wall = time.monotonic() - start
    check(result, "deploy.yml (re-run)")
    recap = parse_recap(result, "deploy.yml (re-run)")
    check_all_ready(setup, "the re-run of deploy.yml")
    after = snapshot(setup.cluster)
    rewritten = sorted(k for k, v in after["versions"].items() if before["versions"].get(k) != v)
    pods_unchanged = before["pods"] == after["pods"]
    return {
        "wall_s": wall,
        "pods_unchanged": pods_unchanged,
        "replica_sets_unchanged": before["replica_sets"] == after["replica_sets"],
        "pods_replaced": len(set(before["pods"].items()) ^ set(after["pods"].items())) if not pods_unchanged else 0,
        "objects_rewritten": len(rewritten),
        "objects_rewritten_first": rewritten[:10],
        "changed_tasks": sum(counts["changed"] for counts in recap.values()),
        "recap": recap,
        "profile": parse_profile(result.stdout),
    }


def run_undeploy(setup: Setup, what: str) -> dict:
    """undeploy.yml: time to its exit, and until the namespace holds nothing of the deployment."""
    start = time.monotonic()
    result = playbook(
        "undeploy.yml", setup.cluster.inventory, "-e", f"rosdeployment_file={setup.spec}",
        "-e", f"kuberos_render_dir={setup.render_dir}", "-e", f"kuberos_kubeconfig={setup.cluster.kubeconfig}",
        timeout=setup.timeout,
    )  # fmt: skip
    exit_s = time.monotonic() - start
    check(result, f"undeploy.yml after {what}")
    return {"exit_s": exit_s, "empty_s": wait_empty(setup.cluster, start, start + setup.timeout)}


def run_kubectl(setup: Setup, dry_run: bool) -> dict:
    """(b) with ``dry_run``, else (c): kubectl server-side apply of the manifests, then a poll until every pod is
    Ready. With ``dry_run`` a server-side dry run of every object comes first, as the deploy does."""
    core = setup.cluster.core()
    apply = ["apply", "--server-side", f"--field-manager={FIELD_MANAGER}", "-R", "-f", str(setup.manifests)]
    start = time.monotonic()
    if dry_run:
        kubectl(setup, *apply, "--dry-run=server", what="kubectl apply --dry-run=server")
    dry_run_s = time.monotonic() - start
    result = kubectl(setup, *apply, what="kubectl apply")
    applied = time.monotonic() - start
    ready = wait_all_ready(core, setup.expected, start, start + setup.timeout)
    if ready is None:
        raise SystemExit(f"bench: kubectl path not Ready after {setup.timeout} s\n{not_ready_report(core)}")
    return {
        "wall_s": ready,
        "dry_run_s": dry_run_s if dry_run else None,
        "apply_exit_s": applied,
        "objects": len(result.stdout.splitlines()),
    }


@contextmanager
def step(run: dict, name: str):
    """Marks ``name`` as running in ``run`` until it ends, so that a benchmark stopped on the way can tell where."""
    run["running"] = {"step": name, "started": time.monotonic()}
    yield
    del run["running"]


def run_variant(setup: Setup, variant: str, label: str, run: dict) -> None:
    """One way to deploy, from the starting state, and its removal; each step recorded into ``run`` when it ends."""
    ensure_start_state(setup)
    if variant == "a":
        log(f"{label}: (a) deploy.yml")
        with step(run, "a"):
            a = run["a"] = run_deploy(setup)
        log(f"{label}: (a) {a['wall_s']:.1f} s (all Ready seen at {fmt(a['ready_seen_s'])} s); re-run with nothing changed")
        with step(run, "rerun"):
            rerun = run["rerun"] = run_rerun(setup)
        log(
            f"{label}: re-run {rerun['wall_s']:.1f} s, pods unchanged: {rerun['pods_unchanged']}, "
            f"objects rewritten: {rerun['objects_rewritten']}; undeploying"
        )
        with step(run, "undeploy_a"):
            undeploy = run["undeploy_a"] = run_undeploy(setup, "(a)")
        log(f"{label}: undeploy exits at {undeploy['exit_s']:.1f} s, namespace empty at {undeploy['empty_s']:.1f} s")
        return
    what = "(b) kubectl dry run + apply" if variant == "b" else "(c) kubectl apply"
    log(f"{label}: {what}")
    with step(run, variant):
        result = run[variant] = run_kubectl(setup, dry_run=variant == "b")
    log(f"{label}: {what}: all Ready at {result['wall_s']:.1f} s (apply exits at {result['apply_exit_s']:.1f} s); undeploying")
    with step(run, f"undeploy_{variant}"):
        run[f"undeploy_{variant}"] = run_undeploy(setup, f"({variant})")


def note_stop(cluster: Cluster, runs: list[dict]) -> None:
    """When the benchmark stops inside a step: which step, after how long, and how far the cluster got."""
    running = runs[-1].pop("running", None) if runs else None
    if running is None:
        return
    stopped = {"step": running["step"], "after_s": time.monotonic() - running["started"]}
    try:
        pods = live_pods(cluster.core())
        stopped.update(
            deployments=len(items(cluster.apps().list_namespaced_deployment, NAMESPACE)),
            pods=len(pods),
            pods_ready=sum(map(is_ready, pods)),
        )
    except Exception as error:  # the cluster may be what failed
        stopped["cluster_error"] = repr(error)
    runs[-1]["stopped_in"] = stopped
    log(f"stopped in {stopped}")


def run_repeat(setup: Setup, index: int, run: dict) -> None:
    """One repeat, recorded into ``run`` as it goes (what finished stays recorded when a later step fails)."""
    order = VARIANTS[index % 3 :] + VARIANTS[: index % 3]
    run.update(order=" ".join(order), load_start=load())
    for variant in order:
        run_variant(setup, variant, f"run {index + 1}", run)
    run["load_end"] = load()
    run["ratio"] = run["a"]["wall_s"] / run["b"]["wall_s"]
    run["ratio_plain"] = run["a"]["wall_s"] / run["c"]["wall_s"]
    log(f"run {index + 1}: ratio (a)/(b) {run['ratio']:.2f}, (a)/(c) {run['ratio_plain']:.2f}")


# -- report --------------------------------------------------------------------------------
def sh(command: str) -> str:
    return subprocess.run(command, shell=True, capture_output=True, text=True).stdout.strip()


def load() -> str:
    """`uptime`: the time, the uptime and the load averages over 1, 5 and 15 minutes."""
    return sh("uptime")


def machine() -> dict:
    dirty = sh(f"git -C {REPO} status --porcelain")
    return {
        "date": sh("date -u"),
        "nproc": sh("nproc"),
        "cpu": sh("lscpu | sed -n 's/^Model name: *//p'"),
        "memory": sh('free -h | awk \'/^Mem:/ {print $2 " total, " $7 " available"}\''),
        "python": sys.version.split()[0],
        "kernel": sh("uname -r"),
        "load": sh("cat /proc/loadavg | cut -d' ' -f1-3"),
        "uptime": load(),
        "commit": sh(f"git -C {REPO} rev-parse --short HEAD") + (" (+ uncommitted changes)" if dirty else ""),
        "commit_short": sh(f"git -C {REPO} rev-parse --short HEAD"),
        "dirty": bool(dirty),
        "dirty_paths": [line[3:] for line in dirty.splitlines()],
    }


# (key, where in a run) of the per-run series; the medians of the first seven are the keys.
SERIES = {
    "deploy_s": ("a", "wall_s"),
    "kubectl_same_work_s": ("b", "wall_s"),
    "kubectl_plain_s": ("c", "wall_s"),
    "ratio": ("ratio", None),
    "ratio_plain": ("ratio_plain", None),
    "rerun_s": ("rerun", "wall_s"),
    "undeploy_s": ("undeploy_a", "exit_s"),
    "undeploy_empty_s": ("undeploy_a", "empty_s"),
    "deploy_ready_seen_s": ("a", "ready_seen_s"),
    "kubectl_same_work_dry_run_s": ("b", "dry_run_s"),
    "kubectl_same_work_apply_exit_s": ("b", "apply_exit_s"),
    "kubectl_plain_apply_exit_s": ("c", "apply_exit_s"),
    "rerun_objects_rewritten": ("rerun", "objects_rewritten"),
}


def value(run: dict, part: str, field: str | None = None):
    """A value of a run; None when that part did not run (a benchmark stopped on the way)."""
    found = run.get(part)
    return found if field is None or found is None else found.get(field)


def summarize(runs: list[dict], robots: int) -> dict:
    """The issue's keys (medians over the repeats), the per-run values behind them, and the targets."""
    raw = {key: [value(run, part, field) for run in runs] for key, (part, field) in SERIES.items()}
    summary: dict = {"robots": robots}
    for key, values in raw.items():
        present = [v for v in values if v is not None]
        summary[f"{key}_median"] = statistics.median(present) if present else None
    reruns = [run["rerun"]["pods_unchanged"] for run in runs if "rerun" in run]
    summary["rerun_pods_unchanged"] = all(reruns) if reruns else None
    summary["raw"] = raw
    summary["targets"] = None  # the targets are set at 100 robots
    if robots == TARGET_ROBOTS:
        met = {
            key: summary[key] is not None and (summary[key] <= bound if op == "<=" else summary[key] < bound)
            for key, op, bound in TARGETS
        }
        summary["targets"] = {
            key: {"target": f"{op} {bound}", "value": summary[key], "pass": met[key]} for key, op, bound in TARGETS
        }
        unchanged = summary["rerun_pods_unchanged"]
        summary["targets"]["rerun_pods_unchanged"] = {"target": "true", "value": unchanged, "pass": bool(unchanged)}
    return summary


def fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(data: dict) -> str:
    runs, args, info = data["runs"], data["args"], data["machine"]
    out = [
        f"## Deploy benchmark: {args['robots']} robots ({data['expected_pods']} pods), deploy.yml vs kubectl apply --server-side",
        "",
        f"Date: {info['date']}. Machine: nproc {info['nproc']}, {info['cpu']}, memory {info['memory']}; "
        f"Python {info['python']}, Linux {info['kernel']}; code at {info['commit']}.",
        "",
        f"Load (`uptime`) at the start: {data['load_start']}; at the end: {data.get('load_end', '-')}.",
        "",
        f"Command: `{data['command']}`",
        "",
        *([] if data["complete"] else ["**Incomplete**: the benchmark stopped before the end; `-` marks what did not run.", ""]),
        f"Cluster: {data.get('nodes', '-')} kwok nodes ({args['robots']} robots, {EDGE_NODES} edge, {CLOUD_NODES} cloud), "
        f"started in {fmt(data.get('cluster_start_s'))} s; {data.get('objects', '-')} objects rendered "
        f"({data['expected_pods']} Deployments of 1 replica, so {data['expected_pods']} pods).",
        "",
        "| run | order | (a) deploy.yml s | (a) all Ready seen s | re-run s | re-run: pods unchanged, objects rewritten "
        "| undeploy exits / empty s | (b) dry run / apply exit / all Ready s | (c) apply exit / all Ready s "
        "| (a)/(b) | (a)/(c) |",
        "|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for i, run in enumerate(runs, 1):
        unchanged = {True: "yes", False: "**no**", None: "-"}[value(run, "rerun", "pods_unchanged")]
        rewritten = value(run, "rerun", "objects_rewritten")
        out.append(
            f"| {i} | {run.get('order', '-')} | {fmt(value(run, 'a', 'wall_s'))} | {fmt(value(run, 'a', 'ready_seen_s'))} "
            f"| {fmt(value(run, 'rerun', 'wall_s'))} | {unchanged}, {'-' if rewritten is None else rewritten} "
            f"| {fmt(value(run, 'undeploy_a', 'exit_s'))} / {fmt(value(run, 'undeploy_a', 'empty_s'))} "
            f"| {fmt(value(run, 'b', 'dry_run_s'))} / {fmt(value(run, 'b', 'apply_exit_s'))} / {fmt(value(run, 'b', 'wall_s'))} "
            f"| {fmt(value(run, 'c', 'apply_exit_s'))} / {fmt(value(run, 'c', 'wall_s'))} "
            f"| {fmt(value(run, 'ratio'), 2)} | {fmt(value(run, 'ratio_plain'), 2)} |"
        )
    if runs:
        s = data
        out.append(
            f"| **median** | | **{fmt(s['deploy_s_median'])}** | {fmt(s['deploy_ready_seen_s_median'])} "
            f"| **{fmt(s['rerun_s_median'])}** | | **{fmt(s['undeploy_s_median'])}** / {fmt(s['undeploy_empty_s_median'])} "
            f"| **{fmt(s['kubectl_same_work_s_median'])}** | **{fmt(s['kubectl_plain_s_median'])}** "
            f"| **{fmt(s['ratio_median'], 2)}** | **{fmt(s['ratio_plain_median'], 2)}** |"
        )
        for i, run in enumerate(runs, 1):
            if "stopped_in" in run:
                stop = run["stopped_in"]
                seen = ", ".join(f"{k.replace('_', ' ')} {stop[k]}" for k in ("deployments", "pods", "pods_ready") if k in stop)
                out += [
                    "",
                    f"Run {i} stopped in step {stop['step']} after {stop['after_s']:.0f} s; the namespace held: {seen or '-'}.",
                ]
        out += ["", *target_lines(data)]
        out += ["", "Loads (`uptime`) per run, start / end:", ""]
        out += [f"- run {i}: {run.get('load_start', '-')} / {run.get('load_end', '-')}" for i, run in enumerate(runs, 1)]
        out += profile_table(runs)
    return "\n".join(out) + "\n"


def target_lines(summary: dict) -> list[str]:
    if not summary["targets"]:
        return [f"No targets at {summary['robots']} robots (they are set at {TARGET_ROBOTS})."]
    lines = [f"Targets at {TARGET_ROBOTS} robots:", ""]
    for key, target in summary["targets"].items():
        got = target["value"]
        shown = f"{got:.2f}" if isinstance(got, float) else "-" if got is None else str(got).lower()
        lines.append(f"- {key} {target['target']}: {shown}: **{'PASS' if target['pass'] else 'FAIL'}**")
    return lines


def profile_table(runs: list[dict]) -> list[str]:
    """The per-task profile of (a), if taken. Tasks are matched by name and by occurrence (the same name may run
    twice), in the order of their first appearance; a task that a run did not have shows '-'."""
    keyed = []
    for run in runs:
        seen: dict[str, int] = {}
        row = {}
        for name, seconds in value(run, "a", "profile") or []:
            seen[name] = seen.get(name, 0) + 1
            row[(name, seen[name])] = seconds
        keyed.append(row)
    order = list(dict.fromkeys(key for row in keyed for key in row))
    if not order:
        return []
    out = [
        "",
        "Per-task profile of (a) (`ansible.posix.profile_tasks`, execution order, seconds). A task's time runs until the "
        "next task starts; tasks of hosts that run side by side, or in a play with strategy free, overlap:",
        "",
        "| task | " + " | ".join(f"run {i}" for i in range(1, len(runs) + 1)) + " |",
        "|---|" + "---:|" * len(runs),
    ]
    for key in order:
        name = key[0] + (f" ({key[1]})" if key[1] > 1 else "")
        out.append(f"| {name} | " + " | ".join(fmt(row.get(key), 2) for row in keyed) + " |")
    tasks = [value(r, "a", "tasks_s") for r in runs]
    walls = [value(r, "a", "wall_s") for r in runs]
    out.append("| sum of tasks | " + " | ".join(fmt(t, 2) for t in tasks) + " |")
    out.append(
        "| process wall - sum of tasks (start-up, parsing, exit) | "
        + " | ".join(fmt(w - t if t is not None else None, 2) for w, t in zip(walls, tasks, strict=True))
        + " |"
    )
    return out


# -- main ----------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Ports used: "
        + ", ".join(f"{k} {v}" for k, v in PORTS.items())
        + ". Output: Markdown on stdout, progress on stderr.",
    )
    parser.add_argument("--robots", type=int, default=100, help="robots in the fleet (4 module pods each); default 100")
    parser.add_argument("--repeat", type=int, default=3, help="repeats of (a), (b), (c), 1 to 5; default 3")
    parser.add_argument("--timeout", type=int, default=300, help="bound of every deploy and wait, seconds; default 300")
    parser.add_argument(
        "--apply-workers", type=int, help="kuberos_apply_workers for (a), 1 to 10 (ansible.cfg forks); default: not set"
    )
    parser.add_argument(
        "--profile", action=argparse.BooleanOptionalAction, default=True, help="profile_tasks breakdown of (a); default on"
    )
    parser.add_argument("--keep-cluster", action="store_true", help="leave the cluster (and its work dir) running at the end")
    parser.add_argument(
        "--workdir", type=Path, help="where inventory, spec, renders and cluster state go (default: a new temp dir)"
    )
    parser.add_argument(
        "--results",
        type=Path,
        help="the results file (issue keys, every run's values, machine, load, commit); "
        "default bench/results/deploy.json at 100 robots, bench/results/deploy-<robots>.json otherwise",
    )
    parser.add_argument("--json", type=Path, help="also write the results to this file")
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be 1 to {MAX_ROBOTS}")
    if not 1 <= args.repeat <= 5:
        parser.error("--repeat must be 1 to 5")
    if args.apply_workers is not None and not 1 <= args.apply_workers <= 10:
        parser.error("--apply-workers must be 1 to 10")
    if args.timeout < 10:
        parser.error("--timeout must be at least 10 s")
    if args.results is None:
        args.results = RESULTS_DIR / ("deploy.json" if args.robots == TARGET_ROBOTS else f"deploy-{args.robots}.json")
    return args


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def command_line(argv: list[str] | None, script: str = "bench/bench_deploy.py") -> str:
    """The command that ran a benchmark ``script`` (from the repository's root) with ``argv``."""
    niceness = os.nice(0)
    return " ".join(
        ["cd", str(REPO), "&&", *(["nice", "-n", str(niceness)] if niceness else []), ".venv/bin/python", script]
        + (argv if argv is not None else sys.argv[1:])
    )


def prepare(cluster: Cluster, spec: Path, work: Path, args: argparse.Namespace, expected: int) -> Setup:
    """Render once without applying, check the render, and create the namespace (none of it timed)."""
    manifests = render_once(cluster, spec, work / "render-once", args.timeout)
    kinds = manifest_kinds(manifests)
    if len(kinds.get("Deployment", [])) != expected:
        raise SystemExit(f"bench: {len(kinds.get('Deployment', []))} Deployments rendered, expected {expected}")
    unwatched = sorted(set(kinds) - {"Namespace", "Deployment", "Service", "ConfigMap"})
    if unwatched:
        log(f"the render also holds {unwatched}: the wait for an empty namespace does not look at them")
    setup = Setup(
        cluster=cluster,
        spec=spec,
        render_dir=work / "render",
        manifests=manifests,
        namespace_files=tuple(kinds.get("Namespace", [])),
        expected=expected,
        timeout=args.timeout,
        workers=args.apply_workers,
        profile=args.profile,
        kubectl_cache=work / "kubectl-cache",
    )
    if not setup.namespace_files:
        raise SystemExit(f"bench: the render holds no Namespace; cannot create {NAMESPACE}")
    ensure_start_state(setup)
    return setup


def write_results(data: dict, args: argparse.Namespace) -> None:
    text = json.dumps(data, indent=2, default=str) + "\n"
    for path in filter(None, (args.results, args.json)):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        log(f"results written to {path}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not KUBECTL.exists():
        raise SystemExit(f"bench: {KUBECTL} missing; run `make binaries WITH_KUBECTL=1`")
    signal.signal(signal.SIGTERM, lambda _signum, _frame: sys.exit(143))  # so that the cluster is stopped
    work = args.workdir or Path(tempfile.mkdtemp(prefix="kuberos-bench-deploy-"))
    work.mkdir(parents=True, exist_ok=True)
    inventory = write_inventory(work / "inventory", args.robots)
    spec = write_spec(work / f"{SPEC_NAME}.yml")
    cluster = Cluster(inventory, work / "cluster", args.timeout)
    expected = args.robots * (MODULES_PER_ROBOT + ROBOT_SERVERS) + DISCOVERY_SERVERS
    info = machine()
    data: dict = {
        "robots": args.robots,
        "complete": False,
        "date": info["date"],
        "commit": info["commit_short"],
        "dirty": info["dirty"],
        "command": command_line(argv),
        "load_start": info["uptime"],
        "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "machine": info,
        "expected_pods": expected,
        "runs": [],
    }
    log(f"work dir {work}; load {data['load_start']}; starting the cluster")
    finished = False
    try:
        data["cluster_start_s"] = cluster.start()
        data["nodes"] = len(cluster.core().list_node(label_selector="kuberos.io/role").items)
        log(f"cluster up with {data['nodes']} nodes in {data['cluster_start_s']:.1f} s")
        if data["nodes"] != args.robots + EDGE_NODES + CLOUD_NODES:
            raise SystemExit(f"bench: {data['nodes']} nodes, expected {args.robots + EDGE_NODES + CLOUD_NODES}")
        started = time.monotonic()
        setup = prepare(cluster, spec, work, args, expected)
        data["prepare_s"] = time.monotonic() - started
        log(f"rendered once and namespace ready in {data['prepare_s']:.1f} s (not timed)")
        data["objects"] = sum(1 for _ in setup.manifests.rglob("*.yaml"))
        for index in range(args.repeat):
            data["runs"].append({})
            run_repeat(setup, index, data["runs"][-1])
        finished = True
    finally:
        note_stop(cluster, data["runs"])
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
        data["load_end"] = load()
        data["complete"] = finished
        if data["runs"]:
            data.update(summarize(data["runs"], args.robots))
        write_results(data, args)
        print(markdown(data))  # also what finished before a failure
    return 0


if __name__ == "__main__":
    sys.exit(main())
