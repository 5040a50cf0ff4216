#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Where every module of every robot runs, read back from the cluster."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_info
short_description: Read back from the cluster where every module of every robot runs
version_added: 0.1.0
description:
  - Lists the pods of the RosDeployments in O(placement) and reports, for every robot and module, the node
    the Kubernetes scheduler bound the pod to and its phase, next to the node KubeROS placed it on.
  - Optionally waits until every module's pod is Running and Ready on its placed node.
options:
  placement:
    description: The placement returned by the P(kuberos.platform.place_modules#filter) filter.
    type: dict
    required: true
  wait_timeout:
    description: Seconds to wait for every pod to be Ready on its placed node; 0 reads once.
    type: int
    default: 0
attributes:
  check_mode:
    support: full
  diff_mode:
    support: N/A
    details: Changes nothing.
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Where does everything run?
  kuberos.platform.rosdeployment_info:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    placement: "{{ placement }}"
    wait_timeout: 60
"""

RETURN = r"""
rows:
  description: One entry per robot and module, with C(placed_node) (the plan) and C(node), C(phase), C(ready) (the cluster).
  returned: always
  type: list
  elements: dict
table:
  description: The rows as a fixed-width table.
  returned: always
  type: str
ready:
  description: Every module runs, Ready, on the node it was placed on.
  returned: always
  type: bool
"""

import time

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import compare, deploy_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import running_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, api_clients


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            placement=dict(type="dict", required=True),
            wait_timeout=dict(type="int", default=0),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    placement = module.params["placement"]
    fleets = [d["fleet"] for d in placement.get("deployments", [])]
    names = [d["name"] for d in placement.get("deployments", [])]
    deadline = time.monotonic() + module.params["wait_timeout"]
    try:
        clients = api_clients(module.params["kubeconfig"])
        while True:
            rows = compare(placement, running_modules(clients, fleets, names))
            ready = all(r["ready"] for r in rows)
            if ready or time.monotonic() >= deadline:
                break
            time.sleep(1)
    except Exception as exc:  # a KubeROS error, or the cluster's: one clear line, no traceback
        fail(module, exc, module.params["kubeconfig"])
    result = {"changed": False, "rows": rows, "table": deploy_table(rows), "ready": ready}
    if module.params["wait_timeout"] and not ready:
        waiting = [f"{r['robot']}/{r['module']}: {r['phase']} on {r['node'] or '-'}" for r in rows if not r["ready"]]
        module.fail_json(
            msg=f"not every module is Ready on its placed node after {module.params['wait_timeout']} s: "
            + "; ".join(waiting[:10]),
            **result,
        )
    module.exit_json(**result)


if __name__ == "__main__":
    main()
