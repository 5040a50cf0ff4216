#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What removing a node asks of the site: the node, the pods a drain evicts, the deployments' passes to run first."""

from __future__ import annotations

DOCUMENTATION = r"""
module: node_removal_info
short_description: What removing a node from the site asks of its deployments
version_added: 0.4.0
description:
  - Reads the node as the cluster has it, the pods a drain would evict from it (not its DaemonSets' nor static
    pods), and every deployment whose record places something on it (module instances, a fleet's discovery or
    bridge servers, a robot's own servers).
  - C(playbooks/remove_node.yml) runs a pass of each of those deployments (a rollout at its current revision, the
    node's host left out of the inventory) before it drains the node, as the robot pool does for a reserved robot.
  - A record that cannot be read is a warning naming its ConfigMap; its deployment is not in RV(passes).
options:
  node:
    description: The node's name (the inventory host's C(kuberos_node_name), or the host's name).
    type: str
    required: true
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
- name: What removing edge-d asks of the deployments
  kuberos.platform.node_removal_info:
    kubeconfig: ~/.kube/kuberos-admin.conf
    node: edge-d
  register: removal
"""

RETURN = r"""
node:
  description: The node's C(name), and whether it C(exists), is C(ready) and is C(unschedulable) (cordoned).
  returned: always
  type: dict
pods:
  description: The pods a drain of the node would evict (namespace/name).
  returned: always
  type: list
  elements: str
passes:
  description:
    - The deployments to pass before the drain, each with C(deployment), C(fleet), C(revision), C(namespace) and
      C(on_node) (what its record places on the node, by name).
  returned: always
  type: list
  elements: dict
unreadable:
  description: The records that cannot be read, one line each naming the ConfigMap and why.
  returned: always
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.node_removal import removal_plan
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, Kube, api_clients


def main():
    module = AnsibleModule(argument_spec=dict(node=dict(type="str", required=True), **KUBECONFIG_ARG), supports_check_mode=True)
    require_packages(module)
    try:
        plan = removal_plan(Kube(api_clients(module.params["kubeconfig"]), "kuberos-remove-node"), module.params["node"])
    except Exception as exc:  # the cluster's error: one clear line
        fail(module, exc, module.params["kubeconfig"])
    for line in plan["unreadable"]:
        module.warn(f"{line}; its deployment is not passed: drain evicts its pods on {module.params['node']}")
    module.exit_json(changed=False, **plan)


if __name__ == "__main__":
    main()
