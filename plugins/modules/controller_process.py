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
    modules off failed nodes, failing pods and links that break C(max_latency)) as a detached process with a
    pid file and a log under O(state_dir), or stops it.
  - Starting is idempotent. A running controller started with other settings is restarted.
  - For a controller inside the cluster use the C(kuberos.platform.controller) role with C(controller_mode=in_cluster).
extends_documentation_fragment:
  - kuberos.platform.cluster
options:
  state:
    description: C(started) or C(stopped).
    type: str
    choices: [started, stopped]
    default: started
  state_dir:
    description: Directory of the pid file (C(controller.pid)) and the log (C(controller.log)).
    type: path
    required: true
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
  resync:
    description: Seconds between passes when nothing changes.
    type: float
    default: 30.0
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
  - KubeROS contributors
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
  description: Pid of the running controller (when started).
  returned: state=started
  type: int
log:
  description: Path of the controller's log.
  returned: always
  type: str
command:
  description: The controller's command line.
  returned: always
  type: list
  elements: str
"""

import os
import sys
import time

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils import background_process
from ansible_collections.kuberos.platform.plugins.module_utils.cluster_state import KUBECONFIG_ARG

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
    resync=dict(type="float", default=30.0),
    log_level=dict(type="str", choices=["DEBUG", "INFO", "WARNING", "ERROR"], default="INFO"),
)


def is_controller(argv: list[str]) -> bool:
    return ENTRY in argv


def command(params: dict) -> list[str]:
    return [
        sys.executable, "-m", ENTRY, "--kubeconfig", params["kubeconfig"],
        "--grace", f"{params['grace']:g}", "--cooldown", f"{params['cooldown']:g}",
        "--restart-threshold", str(params["restart_threshold"]), "--resync", f"{params['resync']:g}",
        "--log-level", params["log_level"],
    ]  # fmt: skip


def run(module: AnsibleModule) -> dict:
    params = module.params
    pidfile = os.path.join(params["state_dir"], "controller.pid")
    logfile = os.path.join(params["state_dir"], "controller.log")
    wanted = command(params)
    pid = background_process.running_pid(pidfile, is_controller)
    result = {"changed": False, "log": logfile, "command": wanted}
    if params["state"] == "stopped":
        if pid is not None:
            result["changed"] = True
            if not module.check_mode:
                background_process.stop(pidfile, is_controller)
        return result
    if pid is not None and background_process.cmdline(pid) == wanted:
        return {**result, "pid": pid}
    result["changed"] = True
    if module.check_mode:
        return result
    if pid is not None:
        background_process.stop(pidfile, is_controller)
    if not os.path.exists(params["kubeconfig"]):
        module.fail_json(msg=f"no kubeconfig at {params['kubeconfig']}; start the local cluster with `make cluster` first")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(params["pythonpath"]), "PYTHONUNBUFFERED": "1"}
    start_offset = os.path.getsize(logfile) if os.path.exists(logfile) else 0
    process = background_process.start(wanted, pidfile, logfile, env)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if process.poll() is not None:
            module.fail_json(
                msg=f"the controller exited at start ({process.returncode}):\n{_since(logfile, start_offset)}", **result
            )
        if STARTED_LINE in _since(logfile, start_offset):
            return {**result, "pid": process.pid}
        time.sleep(0.1)
    module.fail_json(
        msg=f"the controller did not report '{STARTED_LINE}' within 20 s:\n{_since(logfile, start_offset)}", **result
    )


def _since(path: str, offset: int) -> str:
    with open(path, encoding="utf-8", errors="replace") as handle:
        handle.seek(offset)
        return handle.read()[-4000:]


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    module.exit_json(**run(module))


if __name__ == "__main__":
    main()
