#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Run the KubeROS controller as a background process on this machine."""

from __future__ import annotations

DOCUMENTATION = r"""
module: controller_process
short_description: Run the KubeROS controller as a background process on this machine
version_added: 0.2.0
description:
  - Starts the KubeROS controller (it watches nodes, the KubeROS pods and the deployment records and moves
    modules off failed nodes, failing pods and links that break C(max_latency)) as O(replicas) detached
    processes with a pid file and a log each under O(state_dir), or stops them.
  - The replicas elect a leader on the Lease C(kuberos-system/kuberos-controller); only the leader acts, and
    when it dies another takes over once the Lease expires (O(lease_duration)).
  - Starting is idempotent. A running replica started with other settings is restarted; replicas beyond
    O(replicas) are stopped.
  - For a controller inside the cluster use the C(kuberos.platform.controller) role with C(controller_mode=in_cluster).
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
options:
  state:
    description: C(started) or C(stopped).
    type: str
    choices: [started, stopped]
    default: started
  state_dir:
    description:
      - Directory of the pid files and logs, C(controller.pid) and C(controller.log) for the first replica,
        C(controller-2.pid) and C(controller-2.log) for the second, and so on.
    type: path
    required: true
  replicas:
    description: How many controller processes run; one of them, the leader, acts.
    type: int
    default: 2
  lease_duration:
    description: Whole seconds a replica waits, after the last renewal it saw, before it takes the Lease.
    type: int
    default: 6
  renew_deadline:
    description: Seconds the leader keeps acting after its last successful renewal; below O(lease_duration).
    type: float
    default: 4.0
  retry_period:
    description: Seconds between tries to take or renew the Lease.
    type: float
    default: 1.0
  node_names:
    description:
      - The node each replica counts as running on (by index); a replica whose node is NotReady does not lead.
      - Empty for processes that do not run on a cluster node (the default).
    type: list
    elements: str
    default: []
  dashboard_port:
    description:
      - Port of the first replica's read-only dashboard and Prometheus C(/metrics) on 127.0.0.1; replica N serves
        on O(dashboard_port) + N - 1. C(0) serves none.
    type: int
    default: 8611
  prometheus_url:
    description:
      - A Prometheus the controller reads scaled modules' own load metrics from (docs/scaling.md), instead of each
        pod's C(/metrics). Empty reads the pods.
    type: str
    default: ""
  burst_command:
    description:
      - The cloud provisioner the controller runs when a fleet lacks room, with C(-e cloud_vms_fleet=<fleet>) appended
        (docs/cloud.md, burst), e.g. C(ansible-playbook playbooks/cloud.yml -i inventories/local -e cloud_vms_burst=true).
        Empty runs none (the demand is still written).
    type: str
    default: ""
  burst_release_after:
    description: Seconds without demand before the provisioner runs to release idle VMs.
    type: float
    default: 300.0
  pythonpath:
    description: Directories that hold C(ansible_collections/kuberos/platform), for the controller's Python.
    type: list
    elements: path
    required: true
  grace:
    description: Seconds a fault must last before modules move.
    type: float
    default: 5.0
  cooldown:
    description: Seconds before a module moved for a pod or latency fault may move again for such a fault.
    type: float
    default: 30.0
  restart_threshold:
    description: Container restarts at which a pod counts as failing.
    type: int
    default: 3
  node_probe_interval:
    description:
      - Seconds between the controller's probes of each edge and cloud node's kubelet port (a TCP connection to its
        InternalIP, port 10250). Three failed in a row make the node down at once, without waiting for Kubernetes'
        node grace period; robots are never probed. C(0) leaves it to Kubernetes' node status alone.
    type: float
    default: 1.0
  resync:
    description: Seconds between passes when nothing changes.
    type: float
    default: 30.0
  graph_every:
    description:
      - Seconds between the leader's rounds of live graph checks of the deployments whose modules declare topics (a
        check pod beside their modules; the dashboard's ROS graph view shows the results); 0 turns them off.
    type: float
    default: 0
  graph_image:
    description: The graph check pod's image (rclpy and the collection; the bridge's).
    type: str
    default: ghcr.io/kuberos/bridge:0.2.0
  log_level:
    description: Log level.
    type: str
    choices: [DEBUG, INFO, WARNING, ERROR]
    default: INFO
attributes:
  check_mode:
    support: full
  diff_mode:
    support: none
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Start the controller against the local cluster
  kuberos.platform.controller_process:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    state_dir: ~/.cache/kuberos/controller
    pythonpath: ["{{ playbook_dir }}/../.collections"]
"""

RETURN = r"""
pid:
  description: Pid of the first replica (when started).
  returned: state=started
  type: int
pids:
  description: Pids of every replica, in order (when started).
  returned: state=started
  type: list
  elements: int
log:
  description: Path of the first replica's log.
  returned: always
  type: str
logs:
  description: Paths of every replica's log, in order.
  returned: always
  type: list
  elements: str
command:
  description: The first replica's command line.
  returned: always
  type: list
  elements: str
dashboards:
  description: The address of every replica's dashboard (each serves C(/metrics) too), in order; empty when off.
  returned: always
  type: list
  elements: str
  sample: ["http://127.0.0.1:8611/", "http://127.0.0.1:8612/"]
"""

import glob
import os
import re
import sys
import time

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import background_process

ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"
STARTED_LINE = "controller started"

ARGUMENT_SPEC = dict(
    **KUBECONFIG_ARG,
    state=dict(type="str", choices=["started", "stopped"], default="started"),
    state_dir=dict(type="path", required=True),
    pythonpath=dict(type="list", elements="path", required=True),
    grace=dict(type="float", default=5.0),
    cooldown=dict(type="float", default=30.0),
    restart_threshold=dict(type="int", default=3),
    node_probe_interval=dict(type="float", default=1.0),
    resync=dict(type="float", default=30.0),
    graph_every=dict(type="float", default=0.0),
    graph_image=dict(type="str", default="ghcr.io/kuberos/bridge:0.2.0"),
    log_level=dict(type="str", choices=["DEBUG", "INFO", "WARNING", "ERROR"], default="INFO"),
    replicas=dict(type="int", default=2),
    lease_duration=dict(type="int", default=6),
    renew_deadline=dict(type="float", default=4.0),
    retry_period=dict(type="float", default=1.0),
    node_names=dict(type="list", elements="str", default=[]),
    dashboard_port=dict(type="int", default=8611),
    prometheus_url=dict(type="str", default=""),
    burst_command=dict(type="str", default=""),
    burst_release_after=dict(type="float", default=300.0),
)


def is_controller(argv: list[str]) -> bool:
    return ENTRY in argv


def command(params: dict, index: int = 1) -> list[str]:
    """Replica ``index``'s command line (1-based)."""
    node = params["node_names"][index - 1] if index <= len(params["node_names"]) else ""
    return [
        sys.executable, "-m", ENTRY, "--kubeconfig", params["kubeconfig"],
        "--grace", f"{params['grace']:g}", "--cooldown", f"{params['cooldown']:g}",
        "--restart-threshold", str(params["restart_threshold"]), "--resync", f"{params['resync']:g}",
        "--node-probe-interval", f"{params['node_probe_interval']:g}",
        "--graph-every", f"{params.get('graph_every', 0.0):g}",
        "--graph-image", params.get("graph_image") or "ghcr.io/kuberos/bridge:0.2.0",
        "--log-level", params["log_level"], "--lease-duration", str(params["lease_duration"]),
        "--renew-deadline", f"{params['renew_deadline']:g}", "--retry-period", f"{params['retry_period']:g}",
        "--dashboard-port", str(params["dashboard_port"] + index - 1 if params["dashboard_port"] else 0),
        *(["--node-name", node] if node else []),
        *(["--prometheus-url", params["prometheus_url"]] if params["prometheus_url"] else []),
        *(["--burst-command", params["burst_command"], "--burst-release-after", f"{params['burst_release_after']:g}"]
          if params["burst_command"] else []),
    ]  # fmt: skip


def replica_files(state_dir: str, index: int) -> tuple[str, str]:
    """Pid file and log of replica ``index``: controller.pid/.log for the first, controller-N.pid/.log after."""
    stem = "controller" if index == 1 else f"controller-{index}"
    return os.path.join(state_dir, stem + ".pid"), os.path.join(state_dir, stem + ".log")


def replica_indexes(state_dir: str) -> list[int]:
    """Indexes of every replica that has a pid file in ``state_dir``."""
    found = {1} if os.path.exists(os.path.join(state_dir, "controller.pid")) else set()
    for path in glob.glob(os.path.join(state_dir, "controller-*.pid")):
        match = re.fullmatch(r"controller-(\d+)\.pid", os.path.basename(path))
        if match:
            found.add(int(match[1]))
    return sorted(found)


def run(module: AnsibleModule) -> dict:
    params = module.params
    state_dir = params["state_dir"]
    if params["replicas"] < 1:
        module.fail_json(msg=f"replicas must be 1 or more, not {params['replicas']}")
    if params["dashboard_port"] and not 1024 <= params["dashboard_port"] <= 65536 - params["replicas"]:
        module.fail_json(msg=f"dashboard_port must be 0 (none) or a port from 1024 to {65536 - params['replicas']}, "
                         f"not {params['dashboard_port']}")  # fmt: skip
    if not params["renew_deadline"] < params["lease_duration"]:
        module.fail_json(
            msg=f"renew_deadline ({params['renew_deadline']:g} s) must be below lease_duration ({params['lease_duration']} s)"
        )
    wanted = {i: command(params, i) for i in range(1, params["replicas"] + 1)}
    logs = [replica_files(state_dir, i)[1] for i in wanted]
    dashboards = [f"http://127.0.0.1:{params['dashboard_port'] + i - 1}/" for i in wanted] if params["dashboard_port"] else []
    result = {"changed": False, "log": logs[0], "logs": logs, "command": wanted[1], "dashboards": dashboards}
    pids_found = {
        i: background_process.running_pid(replica_files(state_dir, i)[0], is_controller) for i in replica_indexes(state_dir)
    }
    running = {i: pid for i, pid in pids_found.items() if pid is not None}
    keep = {i: pid for i, pid in running.items() if i in wanted and background_process.cmdline(pid) == wanted[i]}
    stale = [i for i in running if i not in keep]  # other settings, or beyond the wanted replicas
    missing = [i for i in wanted if i not in keep]
    if params["state"] == "stopped":
        result["changed"] = bool(running)
        if not module.check_mode:
            for i in running:
                background_process.stop(replica_files(state_dir, i)[0], is_controller)
        return result
    if not stale and not missing:
        return {**result, "pid": keep[1], "pids": [keep[i] for i in wanted]}
    result["changed"] = True
    if module.check_mode:
        return result
    for i in stale:
        background_process.stop(replica_files(state_dir, i)[0], is_controller)
    if not os.path.exists(params["kubeconfig"]):
        module.fail_json(msg=f"no kubeconfig at {params['kubeconfig']}; start the local cluster with `make cluster` first")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(params["pythonpath"]), "PYTHONUNBUFFERED": "1"}
    started = {}
    for i in missing:
        pidfile, logfile = replica_files(state_dir, i)
        offset = os.path.getsize(logfile) if os.path.exists(logfile) else 0
        started[i] = (background_process.start(wanted[i], pidfile, logfile, env), logfile, offset)
    deadline = time.monotonic() + 20
    waiting = dict(started)
    while waiting and time.monotonic() < deadline:
        for i, (process, logfile, offset) in list(waiting.items()):
            if process.poll() is not None:
                module.fail_json(
                    msg=f"controller replica {i} exited at start ({process.returncode}):\n{_since(logfile, offset)}", **result
                )
            if STARTED_LINE in _since(logfile, offset):
                del waiting[i]
        time.sleep(0.1)
    for i, (_process, logfile, offset) in waiting.items():
        module.fail_json(
            msg=f"controller replica {i} did not report '{STARTED_LINE}' within 20 s:\n{_since(logfile, offset)}", **result
        )
    pids = {**keep, **{i: entry[0].pid for i, entry in started.items()}}
    return {**result, "pid": pids[1], "pids": [pids[i] for i in wanted]}


def _since(path: str, offset: int) -> str:
    with open(path, encoding="utf-8", errors="replace") as handle:
        handle.seek(offset)
        return handle.read()[-4000:]


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    require_packages(module)
    module.exit_json(**run(module))


if __name__ == "__main__":
    main()
