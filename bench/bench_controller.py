#!/usr/bin/env python3
"""Controller failover benchmark: from a node turning NotReady to every affected module Running elsewhere.

On a dedicated local control plane (its own ports and state directory; 20 robots in one fleet, 6 edge and
3 cloud kwok nodes by default) it deploys a pick-and-place app with ``playbooks/deploy.yml``, starts the
KubeROS controller with ``playbooks/controller.yml`` (a local process, grace ``--grace`` seconds), and then,
trial after trial, kills an edge node that hosts module pods (rotating over the edge nodes):

1. the node's annotation ``kwok.x-k8s.io/node`` is removed, so kwok stops heartbeating it, as it would
   stop for a dead kubelet;
2. its Ready condition is patched to ``Unknown`` (reason NodeStatusUnknown, lastTransitionTime now, sent
   just after a whole second so the second-resolution timestamp is within a few ms of the patch). The
   clock starts right before this patch;
3. the pods of the benchmark's namespace are polled (every ``--poll`` s, Python client) until every
   module instance (and discovery server) that had a pod on the node has exactly one pod Running and
   Ready on another node and no pod left on the dead node. The clock stops at the first poll that sees it.

Then the annotation is put back (kwok marks the node Ready again), and the benchmark waits until the node
is Ready without the unreachable/not-ready taints and every pod of the namespace is Running and Ready, plus
``--calm`` seconds, before the next trial. Every wait is bounded by ``--timeout``; a trial that exceeds
it is recorded as failed, with the controller's log lines of the trial. The controller's log
(``<state_dir>/controller.log``) gives when the first and last "moved from" lines of the trial were
written (right after the record write), which splits each trial into grace, grace end to first move,
and first move to all Running.

    .venv/bin/python bench/bench_controller.py                      # 12 trials, grace 5 s
    .venv/bin/python bench/bench_controller.py --trials 10 --grace 2 --json /tmp/failover.json

The controller and the cluster are stopped (``local_cluster_state=absent``) at the end, also on failure,
unless ``--keep-cluster``. The result is printed as Markdown, ready to paste into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_deploy import REPO, Cluster, check, log, machine, playbook  # bench/ is on sys.path when a benchmark runs
from bench_deploy import write_inventory as write_deploy_inventory
from workload import pick_and_place

FLEET = "bench-fleet"
NAMESPACE = f"kuberos-{FLEET}"
SPEC_NAME = "bench-failover"
PORTS = {
    "apiserver": 46443,
    "etcd_client": 42379,
    "etcd_peer": 42380,
    "controller_manager": 46257,
    "scheduler": 46259,
    "kwok": 46247,
}
KWOK_ANNOTATION = "kwok.x-k8s.io/node"
MANAGED = "app.kubernetes.io/managed-by=kuberos"
INSTANCE = "kuberos.io/instance"
DOWN_TAINTS = ("node.kubernetes.io/unreachable", "node.kubernetes.io/not-ready")
TARGET_P95_S = 15.0
LOG_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) (\w+) (.*)$")
SMP = "application/strategic-merge-patch+json"


# -- inputs --------------------------------------------------------------------------------
def write_inventory(directory: Path, robots: int, edge: int, cloud: int) -> Path:
    """bench_deploy's inventory with this benchmark's node counts and no GPUs."""
    return write_deploy_inventory(directory, robots, edge, cloud, gpus=False)


# -- the cluster and the controller ---------------------------------------------------------
class FailoverCluster(Cluster):
    """bench_deploy's Cluster on this benchmark's own ports."""

    def __init__(self, inventory: Path, state_dir: Path, timeout: float):
        super().__init__(inventory, state_dir, timeout)
        self.vars = json.dumps(
            {"local_cluster_state_dir": str(state_dir), "local_cluster_ports": PORTS, "local_cluster_timeout": int(timeout)}
        )


class ControllerProcess:
    """The controller through playbooks/controller.yml; one replica here (its log has every move of a trial)."""

    def __init__(self, cluster: Cluster, state_dir: Path, grace: float, replicas: int = 1):
        self.cluster = cluster
        self.state_dir = state_dir
        self.log_file = state_dir / "controller.log"
        self.vars = json.dumps(
            {
                "controller_kubeconfig": str(cluster.kubeconfig),
                "controller_state_dir": str(state_dir),
                "controller_grace": grace,
                "controller_replicas": replicas,
            }
        )

    def start(self) -> int:
        check(playbook("controller.yml", self.cluster.inventory, "-e", self.vars, timeout=120), "starting the controller")
        pid = self.pid()
        if pid is None:
            raise SystemExit(f"bench: the controller is not running after controller.yml (pid file in {self.state_dir})")
        if "controller started" not in self.log_file.read_text(errors="replace"):
            raise SystemExit(f"bench: no 'controller started' line in {self.log_file}")
        return pid

    def pid(self) -> int | None:
        try:
            pid = int((self.state_dir / "controller.pid").read_text().strip())
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except (OSError, ValueError):
            return None
        return pid if b"kuberos_controller" in cmdline else None

    def stop(self) -> subprocess.CompletedProcess:
        return playbook("controller.yml", self.cluster.inventory, "-e", self.vars, "-e", "controller_state=stopped", timeout=120)

    def lines(self) -> list[tuple[float, str, str]]:
        """(epoch, level, message) of every timestamped line of the log."""
        out = []
        for line in self.log_file.read_text(errors="replace").splitlines():
            match = LOG_LINE.match(line)
            if match:
                stamp = datetime.datetime.strptime(match[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()  # local time, as asctime
                out.append((stamp, match[2], match[3]))
        return out


# -- observing -----------------------------------------------------------------------------
def list_pods(core) -> list[dict]:
    response = core.list_namespaced_pod(NAMESPACE, label_selector=MANAGED, _preload_content=False)
    return json.loads(response.data)["items"]


def pod_ready(pod: dict) -> bool:
    status = pod.get("status", {})
    return status.get("phase") == "Running" and any(
        c.get("type") == "Ready" and c.get("status") == "True" for c in status.get("conditions") or []
    )


def pod_node(pod: dict) -> str:
    return pod.get("spec", {}).get("nodeName") or ""


def by_instance(pods: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for pod in pods:
        instance = (pod["metadata"].get("labels") or {}).get(INSTANCE)
        if instance:
            out.setdefault(instance, []).append(pod)
    return out


def node_ready(node) -> str:
    ready = next((c for c in node.status.conditions or [] if c.type == "Ready"), None)
    return ready.status if ready else "missing"


def moved(instances: dict[str, list[dict]], affected: list[str], dead: str) -> dict[str, str] | None:
    """Instance -> new node when every affected instance runs, Ready, in exactly one pod elsewhere and
    none of its pods is left on the dead node; else None."""
    where = {}
    for name in affected:
        pods = instances.get(name, [])
        if any(pod_node(p) == dead for p in pods):
            return None
        running = [p for p in pods if pod_ready(p) and not p["metadata"].get("deletionTimestamp")]
        if len(running) != 1:
            return None
        where[name] = pod_node(running[0])
    return where


def describe(instances: dict[str, list[dict]], names: list[str]) -> str:
    lines = []
    for name in names:
        pods = instances.get(name, [])
        states = [
            f"{p['metadata']['name']} on {pod_node(p) or '-'} {p.get('status', {}).get('phase', '?')}"
            f"{' Ready' if pod_ready(p) else ''}{' deleting' if p['metadata'].get('deletionTimestamp') else ''}"
            for p in pods
        ]
        lines.append(f"  {name}: " + ("; ".join(states) if states else "no pod"))
    return "\n".join(lines)


def wait_steady(core, expected: int, deadline: float, poll: float) -> None:
    """Every pod of the namespace Running and Ready, one per instance, none deleting."""
    while True:
        pods = list_pods(core)
        live = [p for p in pods if not p["metadata"].get("deletionTimestamp")]
        if len(pods) == expected and len(live) == expected and all(pod_ready(p) for p in live):
            return
        if time.monotonic() > deadline:
            bad = [p for p in pods if not pod_ready(p) or p["metadata"].get("deletionTimestamp")]
            raise TimeoutError(
                f"{len(pods)} pods ({expected} expected), {len(bad)} not Running+Ready or deleting:\n"
                + describe(by_instance(bad), sorted(by_instance(bad)))
            )
        time.sleep(poll)


def wait_node_back(core, node: str, deadline: float, poll: float) -> None:
    while True:
        obj = core.read_node(node)
        taints = [t.key for t in obj.spec.taints or [] if t.key in DOWN_TAINTS]
        if node_ready(obj) == "True" and not taints:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"node {node} not back: Ready={node_ready(obj)}, taints {taints}")
        time.sleep(poll)


# -- a trial -------------------------------------------------------------------------------
def kill_node(core, node: str) -> tuple[float, float, str]:
    """Remove kwok's annotation, then patch Ready=Unknown just after a whole second. Returns (monotonic
    and epoch time right before the status patch, the lastTransitionTime written)."""
    core.patch_node(node, {"metadata": {"annotations": {KWOK_ANNOTATION: None}}}, _content_type=SMP)
    time.sleep(0.2)  # kwok's watch sees the annotation go before the status changes
    now = time.time()
    time.sleep(math.ceil(now) - now + 0.005)  # just after a whole second: lastTransitionTime has 1 s resolution
    wall = time.time()
    transition = datetime.datetime.fromtimestamp(int(wall), datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    body = {
        "status": {
            "conditions": [
                {
                    "type": "Ready",
                    "status": "Unknown",
                    "reason": "NodeStatusUnknown",
                    "message": "Kubelet stopped posting node status.",
                    "lastTransitionTime": transition,
                }
            ]
        }
    }
    start = time.monotonic()
    core.patch_node_status(node, body, _content_type=SMP)
    return start, wall, transition


def restore_node(core, node: str) -> None:
    core.patch_node(node, {"metadata": {"annotations": {KWOK_ANNOTATION: "fake"}}}, _content_type=SMP)


def pick_node(pods: list[dict], edge_nodes: list[str], last_killed: dict[str, int]) -> str:
    hosting = {pod_node(p) for p in pods}
    candidates = [n for n in edge_nodes if n in hosting]
    if not candidates:
        raise SystemExit("bench: no edge node hosts a module pod")
    return min(candidates, key=lambda n: (last_killed.get(n, -1), n))  # the one killed longest ago


def trial(index: int, core, controller: ControllerProcess, node: str, args) -> dict:
    pods = list_pods(core)
    instances = by_instance(pods)
    affected = sorted(name for name, ps in instances.items() if any(pod_node(p) == node for p in ps))
    log(f"trial {index}: killing {node}, which hosts {len(affected)} instances")
    start, wall, transition = kill_node(core, node)
    deadline = start + args.timeout
    result: dict = {"trial": index, "node": node, "affected": affected, "patched_at": wall, "transition": transition}
    polls = 0
    while True:
        pods = list_pods(core)
        polls += 1
        instances = by_instance(pods)
        where = moved(instances, affected, node)
        if where is not None:
            result["seconds"] = time.monotonic() - start
            result["to"] = where
            break
        if time.monotonic() > deadline:
            result["seconds"] = None
            result["error"] = f"not moved within {args.timeout:.0f} s:\n" + describe(instances, affected)
            break
        time.sleep(args.poll)
    result["polls"] = polls
    result["node_ready_at_end"] = node_ready(core.read_node(node))
    end_wall = time.time()
    lines = [(t, level, msg) for t, level, msg in controller.lines() if wall - 1 <= t <= end_wall + 1]
    moves = [t for t, _level, msg in lines if f" moved from {node} to " in msg]
    deletes = [t for t, _level, msg in lines if "deleted pod" in msg and f"left on {node}" in msg]
    grace_end = datetime.datetime.fromisoformat(transition.replace("Z", "+00:00")).timestamp() + args.grace
    result.update(
        moves_logged=len(moves),
        deletes_logged=len(deletes),
        grace_end_offset_s=grace_end - wall,
        first_move_s=(min(moves) - wall) if moves else None,
        last_move_s=(max(moves) - wall) if moves else None,
        last_delete_s=(max(deletes) - wall) if deletes else None,
        log=[f"{datetime.datetime.fromtimestamp(t):%H:%M:%S.%f}"[:-3] + f" {level} {msg}" for t, level, msg in lines][-60:],
    )
    if result["seconds"] is not None:
        log(
            f"trial {index}: {len(affected)} instances off {node} in {result['seconds']:.2f} s "
            f"(first move logged at {result['first_move_s']}, node Ready={result['node_ready_at_end']})"
        )
    else:
        log(f"trial {index}: FAILED: {result['error']}\ncontroller log of the trial:\n" + "\n".join(result["log"]))
    return result


def settle(core, node: str, expected: int, args) -> float:
    start = time.monotonic()
    restore_node(core, node)
    wait_node_back(core, node, start + args.timeout, args.poll)
    wait_steady(core, expected, start + args.timeout, args.poll)
    time.sleep(args.calm)
    return time.monotonic() - start


# -- report --------------------------------------------------------------------------------
def nearest_rank(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q * len(ordered)) - 1)]


def summary(trials: list[dict]) -> dict:
    ok = [t for t in trials if t.get("seconds") is not None]
    if not ok:
        return {"ok": 0, "failed": len(trials)}
    seconds = [t["seconds"] for t in ok]
    out = {
        "ok": len(ok),
        "failed": len(trials) - len(ok),
        "p50": statistics.median(seconds),
        "p95": nearest_rank(seconds, 0.95),
        "p95_interpolated": statistics.quantiles(seconds, n=20, method="inclusive")[18] if len(seconds) > 1 else seconds[0],
        "min": min(seconds),
        "max": max(seconds),
        "mean": statistics.fmean(seconds),
    }
    split = [t for t in ok if t["first_move_s"] is not None]
    if split:
        out["grace_end_to_move_median"] = statistics.median(t["first_move_s"] - t["grace_end_offset_s"] for t in split)
        out["move_to_running_median"] = statistics.median(t["seconds"] - t["first_move_s"] for t in split)
    return out


def fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(data: dict) -> str:
    info, args, s = data["machine"], data["args"], data["summary"]
    out = [
        f"## Controller failover benchmark: node NotReady to every affected module Running elsewhere ({data['date']})",
        "",
        f"Date: {info['date']}. Machine: nproc {info['nproc']}, {info['cpu']}, memory {info['memory']}; "
        f"Python {info['python']}, Linux {info['kernel']}; code at {info['commit']}.",
        f"Load (`/proc/loadavg`) before: {data['load_before']}; after: {data['load_after']}. "
        f"Other kube-apiservers running on the machine at the start: {data['other_apiservers']}.",
        "",
        f"Command: `{data['command']}`",
        "",
        f"Cluster: {data['nodes']} kwok nodes ({args['robots']} robots in {FLEET}, {args['edge']} edge, {args['cloud']} cloud) "
        f"on ports {', '.join(str(p) for p in PORTS.values())}, started in {fmt(data.get('cluster_start_s'), 1)} s; "
        f"pick-and-place (perception and shared task-coordinator on the edge, planner in the cloud, controller onboard, "
        f"2 discovery servers): {data.get('expected_pods')} pods, deployed with deploy.yml in {fmt(data.get('deploy_s'), 1)} s. "
        f"Controller: local process started by playbooks/controller.yml, grace **{args['grace']:g} s** (configured), "
        f"other settings at their defaults; poll every {args['poll']:g} s; calm {args['calm']:g} s between trials.",
        "",
        'Times are from the Ready=Unknown status patch. "grace end" is lastTransitionTime + grace (the patch is sent '
        'just after a whole second, so lastTransitionTime is within a few ms of it); "first/last move" are the '
        "controller's first and last `moved from <node>` log lines of the trial (written right after the record write).",
        "",
        "| trial | node | affected instances | grace end s | first move s | last move s | all Running elsewhere s |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for t in data["trials"]:
        total = fmt(t.get("seconds")) if t.get("seconds") is not None else "**failed**"
        out.append(
            f"| {t['trial']} | {t['node']} | {len(t['affected'])} | {fmt(t['grace_end_offset_s'])} | {fmt(t['first_move_s'])} "
            f"| {fmt(t['last_move_s'])} | {total} |"
        )
    out.append("")
    if s.get("ok"):
        met = s["failed"] == 0 and s["p95"] < TARGET_P95_S
        out += [
            f"Over {s['ok']} successful trials ({s['failed']} failed): **p50 {s['p50']:.2f} s, p95 {s['p95']:.2f} s** "
            f"(nearest rank; interpolated {s['p95_interpolated']:.2f} s), min {s['min']:.2f} s, max {s['max']:.2f} s, "
            f"mean {s['mean']:.2f} s.",
            "",
            f"Split (medians): grace {args['grace']:g} s (configured); grace end to first move logged "
            f"{fmt(s.get('grace_end_to_move_median'))} s; first move to all Running {fmt(s.get('move_to_running_median'))} s.",
            "",
            f"Target p95 under {TARGET_P95_S:.0f} s: **{'met' if met else 'missed'}**.",
        ]
    else:
        out.append(f"No trial succeeded ({s['failed']} failed); target p95 under {TARGET_P95_S:.0f} s: **missed**.")
    for t in data["trials"]:
        if t.get("error"):
            out += ["", f"Trial {t['trial']} ({t['node']}) failed: {t['error']}", "", "```", *t["log"], "```"]
    return "\n".join(out) + "\n"


# -- main ----------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Ports used: "
        + ", ".join(f"{k} {v}" for k, v in PORTS.items())
        + ". Output: Markdown on stdout, progress on stderr.",
    )
    parser.add_argument("--trials", type=int, default=12, help="node failures, at least 10; default 12")
    parser.add_argument("--grace", type=float, default=5.0, help="the controller's grace, seconds; default 5 (its default)")
    parser.add_argument("--robots", type=int, default=20, help="robots in the fleet; default 20")
    parser.add_argument("--edge", type=int, default=6, help="edge nodes; default 6")
    parser.add_argument("--cloud", type=int, default=3, help="cloud nodes; default 3")
    parser.add_argument("--poll", type=float, default=0.15, help="poll interval, seconds; default 0.15")
    parser.add_argument("--calm", type=float, default=3.0, help="seconds to wait between trials once all is Ready; default 3")
    parser.add_argument("--timeout", type=float, default=120.0, help="bound of every wait, seconds; default 120")
    parser.add_argument("--keep-cluster", action="store_true", help="leave the controller, the cluster and the work dir")
    parser.add_argument("--workdir", type=Path, help="where inventory, spec, renders and states go (default: a new temp dir)")
    parser.add_argument("--json", type=Path, help="also write the raw results (every trial, its controller log lines)")
    args = parser.parse_args(argv)
    if args.trials < 10:
        parser.error("--trials must be at least 10")
    if not 0.1 <= args.poll <= 0.2:
        parser.error("--poll must be 0.1 to 0.2 s")
    if args.edge < 2 or args.robots < 1 or args.cloud < 1:
        parser.error("at least 2 edge nodes, 1 cloud node and 1 robot")
    return args


def loadavg() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def other_apiservers() -> int:
    count = 0
    for proc in Path("/proc").iterdir():
        try:
            cmdline = (proc / "cmdline").read_bytes()
        except OSError:
            continue
        if b"kube-apiserver" in cmdline.split(b"\0")[0] and f"--secure-port={PORTS['apiserver']}".encode() not in cmdline:
            count += 1
    return count


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="kuberos-bench-controller-"))
    work.mkdir(parents=True, exist_ok=True)
    inventory = write_inventory(work / "inventory", args.robots, args.edge, args.cloud)
    spec = work / f"{SPEC_NAME}.yml"
    spec.write_text(json.dumps(pick_and_place(SPEC_NAME, FLEET), indent=2) + "\n")
    cluster = FailoverCluster(inventory, work / "cluster", args.timeout)
    controller = ControllerProcess(cluster, work / "controller", args.grace)
    edge_nodes = [f"edge-{i:02d}" for i in range(args.edge)]
    data: dict = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "command": " ".join(
            ["cd", str(REPO), "&&", ".venv/bin/python", "bench/bench_controller.py", *(sys.argv[1:] if argv is None else argv)]
        ),
        "machine": machine(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "load_before": loadavg(),
        "other_apiservers": other_apiservers(),
        "trials": [],
    }
    log(f"work dir {work}; load {data['load_before']}; starting the cluster")
    finished = False
    try:
        data["cluster_start_s"] = cluster.start()
        core = cluster.core()
        data["nodes"] = len(core.list_node(label_selector="kuberos.io/role").items)
        log(f"cluster up with {data['nodes']} nodes in {data['cluster_start_s']:.1f} s; deploying")
        start = time.monotonic()
        result = playbook(
            "deploy.yml", inventory, "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={work / 'render'}",
            "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", timeout=args.timeout + 300,
        )  # fmt: skip
        check(result, "deploy.yml")
        data["deploy_s"] = time.monotonic() - start
        data["expected_pods"] = len(list_pods(core))
        wait_steady(core, data["expected_pods"], time.monotonic() + args.timeout, args.poll)
        log(f"deployed {data['expected_pods']} pods in {data['deploy_s']:.1f} s; starting the controller, grace {args.grace:g} s")
        data["controller_pid"] = controller.start()
        log(f"controller running, pid {data['controller_pid']}; log {controller.log_file}")
        time.sleep(args.calm)
        last_killed: dict[str, int] = {}
        for index in range(1, args.trials + 1):
            if controller.pid() is None:
                raise SystemExit("bench: the controller is no longer running:\n" + controller.log_file.read_text()[-3000:])
            node = pick_node(list_pods(core), edge_nodes, last_killed)
            last_killed[node] = index
            outcome = trial(index, core, controller, node, args)
            data["trials"].append(outcome)
            outcome["settle_s"] = settle(core, node, data["expected_pods"], args)
        finished = True
    finally:
        data["load_after"] = loadavg()
        data["summary"] = summary(data["trials"])
        if args.keep_cluster:
            log(f"kept: KUBECONFIG={cluster.kubeconfig}; controller log {controller.log_file}; work dir {work}")
        else:
            log("stopping the controller and the cluster")
            for what, stopped in (("controller", controller.stop()), ("cluster", cluster.stop())):
                if stopped.returncode != 0:
                    log(f"stopping the {what} failed:\n" + (stopped.stdout + stopped.stderr)[-2000:])
                    finished = False
            if args.workdir is None and finished and data["summary"].get("failed") == 0:
                shutil.rmtree(work, ignore_errors=True)
            else:
                log(f"work dir kept: {work}")
        if args.json:
            args.json.write_text(json.dumps(data, indent=2, default=str) + "\n")
    print(markdown(data))
    return 0 if data["summary"].get("failed", 1) == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
