#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Run a batch job (a grid of parameter values, each combination a Kubernetes indexed Job) and collect its results."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosbatchjob
short_description: Run a batch job of ROS 2 modules over a grid of parameters as Kubernetes Jobs, and collect the results
version_added: 0.3.0
description:
  - Reads one batch job (C(kind RosBatchJob), or the reference format's C(kind BatchJob); docs/batch.md) - a
    RosDeployment's modules and parameter maps with a C(job) section naming the lifecycle module, the grid of
    parameter values, the repeats, the parallelism and the start-up and running timeouts.
  - Places the runs with the same scheduler as a deployment (beside what runs already), renders every object into
    O(dest)C(/manifests) with the plan (C(plan.txt), C(batch.json)), and with O(apply) runs it - one indexed Job per
    combination, O(dest) gets each run's container logs and termination message (C(runs/<run>-<repeat>/)) and
    C(results.json) and C(results.csv).
  - Progress (runs done, running, starting) is returned and written to O(dest)C(/progress.log) at least every 30 s;
    run the task with C(async) to see the playbook poll it.
  - Runs of an earlier run of the same job are deleted first. O(state=absent) deletes the job's Jobs and parameter maps.
options:
  src:
    description: The batch job file (one job).
    type: path
    required: true
  inventory:
    description: The fleet resource model (P(kuberos.platform.fleet_inventory#filter)).
    type: dict
    required: true
  dest:
    description: Directory the manifests, the plan and the results are written to.
    type: path
    required: true
  apply:
    description: Run the job on the cluster; false renders only.
    type: bool
    default: true
  state:
    description: C(present) runs the job; C(absent) deletes its Jobs and parameter maps from the cluster.
    type: str
    choices: [present, absent]
    default: present
  kubeconfig:
    description: Kubeconfig of the cluster; required unless O(apply=false).
    type: path
  field_manager:
    description: Field manager of the server-side applies.
    type: str
    default: kuberos
  allocated:
    description: "Resources used per node by workloads the cluster does not show, as C({node: {cpu, memory, gpu, pods}})."
    type: dict
    default: {}
  poll:
    description: Seconds between two looks at the runs' pods.
    type: float
    default: 2.0
extends_documentation_fragment:
  - kuberos.platform.attributes
attributes:
  check_mode:
    support: full
    details: Places and renders in memory; writes nothing and starts nothing.
  diff_mode:
    support: none
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Run the navigation grid and collect its results
  kuberos.platform.rosbatchjob:
    src: examples/batch/nav-grid.yml
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    dest: rendered/nav-grid
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
  async: 7200
  poll: 15
"""

RETURN = r"""
plan:
  description: Each combination's run number, wave, node, repeats and parameter values.
  returned: when state is present
  type: str
runs:
  description: Runs in all (combinations times repeats).
  returned: when state is present
  type: int
runs_succeeded:
  description: Runs whose lifecycle module exited 0.
  returned: when applied
  type: int
runs_failed:
  description: Runs that failed (a module's exit code, the start-up or running timeout); a failed run does not fail the task.
  returned: when applied
  type: int
failures:
  description: One line per failed run, with its parameters and why.
  returned: when applied
  type: list
  elements: str
progress:
  description: The progress lines of the run.
  returned: when applied
  type: list
  elements: str
notes:
  description: What the reference format's translation ignored or chose.
  returned: when state is present
  type: list
  elements: str
removed:
  description: The objects deleted (state absent).
  returned: when state is absent
  type: list
  elements: str
"""

import os
import time

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.batch_runner import remove_batch, run_batch
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import api_clients

ARGUMENT_SPEC = dict(
    src=dict(type="path", required=True),
    inventory=dict(type="dict", required=True),
    dest=dict(type="path", required=True),
    apply=dict(type="bool", default=True),
    state=dict(type="str", choices=["present", "absent"], default="present"),
    kubeconfig=dict(type="path"),
    field_manager=dict(type="str", default="kuberos"),
    allocated=dict(type="dict", default={}),
    poll=dict(type="float", default=2.0),
)


def main():
    module = AnsibleModule(
        argument_spec=ARGUMENT_SPEC,
        required_if=[("apply", True, ("kubeconfig",)), ("state", "absent", ("kubeconfig",))],
        supports_check_mode=True,
    )
    require_packages(module)
    params = module.params
    progress = []

    def report(line: str) -> None:
        stamped = f"[{time.strftime('%H:%M:%S')}] {line}"
        progress.append(stamped)
        if params["apply"] and not module.check_mode:
            os.makedirs(params["dest"], exist_ok=True)
            with open(os.path.join(params["dest"], "progress.log"), "a", encoding="utf-8") as handle:
                handle.write(stamped + "\n")

    try:
        if params["state"] == "absent":
            result = {"changed": False} if module.check_mode else remove_batch(api_clients(params["kubeconfig"]), params)
        else:
            result = run_batch(lambda: api_clients(params["kubeconfig"]), params, module.check_mode, report)
    except KuberosError as exc:  # the job's, the inventory's, the results directory's
        fail(module, exc, progress=progress)
    except OSError as exc:
        module.fail_json(msg=f"cannot write {params['dest']}: {exc}", progress=progress)
    except Exception as exc:  # the cluster's: one clear line, no traceback
        fail(module, exc, params["kubeconfig"], progress=progress)
    result["progress"] = progress
    module.exit_json(**result)


if __name__ == "__main__":
    main()
