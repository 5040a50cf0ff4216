#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What is already placed on each node of the cluster."""

from __future__ import annotations

DOCUMENTATION = r"""
module: node_allocations
short_description: Resources already requested on each node of the cluster
version_added: 0.1.0
description:
  - Sums the cpu, memory and C(nvidia.com/gpu) requests and the pod count of every pod bound to each node,
    leaving out the pods of O(exclude_deployments) and the discovery servers of O(exclude_discovery_of_fleets)
    (what is about to be placed again).
  - The result is the C(allocated) input of the P(kuberos.platform.place_modules#filter) filter, so that a new
    placement accounts for what already runs.
  - Also returns the names of the namespaces that exist, so that a deployment knows which of its fleets'
    namespaces it has to create without another module call, and the inventory's nodes that cannot take modules.
options:
  exclude_deployments:
    description: RosDeployments whose pods are not counted.
    type: list
    elements: str
    default: []
  exclude_discovery_of_fleets:
    description: Fleets whose discovery server pods are not counted.
    type: list
    elements: str
    default: []
  inventory:
    description:
      - The fleet resource model (P(kuberos.platform.fleet_inventory#filter)). When given, the result's C(unavailable)
        names each of its nodes that is NotReady or not in the cluster, with why, for the
        P(kuberos.platform.place_modules#filter) filter to leave out.
    type: dict
  previous_of:
    description:
      - RosDeployments about to be placed again, as C([{name, fleet}]). The result's C(previous) holds what runs now
        for them (the instances of their deployment records and their fleets' live discovery servers), for the
        P(kuberos.platform.place_modules#filter) filter's sticky placement.
    type: list
    elements: dict
    default: []
attributes:
  check_mode:
    support: full
extends_documentation_fragment:
  - kuberos.platform.cluster
author:
  - KubeROS contributors
"""

EXAMPLES = r"""
- name: What is already placed
  kuberos.platform.node_allocations:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    exclude_deployments: [pick-and-place]
  register: allocations
"""

RETURN = r"""
allocated:
  description: Per node, C(cpu) (millicores, as C(1500m)), C(memory) (bytes), C(gpu) and C(pods).
  returned: always
  type: dict
namespaces:
  description: Names of the namespaces that exist in the cluster, sorted.
  returned: always
  type: list
  elements: str
previous:
  description:
    - What runs now for O(previous_of), as a placement (empty instances and discovery when nothing runs), and under
      C(revisions) each one's current revision, as C(name) to C(revision) and C(hash).
  returned: always
  type: dict
unavailable:
  description: "Nodes of O(inventory) that are NotReady or not in the cluster, as C({node: why})."
  returned: always
  type: dict
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.cluster_state import (
    KUBECONFIG_ARG,
    api_clients,
    explain,
    namespace_names,
    node_allocations,
    previous_placement,
    unavailable_nodes,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            exclude_deployments=dict(type="list", elements="str", default=[]),
            exclude_discovery_of_fleets=dict(type="list", elements="str", default=[]),
            inventory=dict(type="dict"),
            previous_of=dict(type="list", elements="dict", default=[]),
        ),
        supports_check_mode=True,
    )
    try:
        clients = api_clients(module.params["kubeconfig"])
        allocated = node_allocations(clients, module.params["exclude_deployments"], module.params["exclude_discovery_of_fleets"])
        namespaces = namespace_names(clients)
        wanted = list(load_inventory(module.params["inventory"]).nodes) if module.params["inventory"] else []
        unavailable = unavailable_nodes(clients, wanted)
        previous = previous_placement(clients, module.params["previous_of"])
    except KuberosError as exc:
        module.fail_json(msg=str(exc))
    except Exception as exc:  # connection and configuration problems: one clear line, no traceback
        module.fail_json(msg=explain(exc, module.params["kubeconfig"]))
    module.exit_json(changed=False, allocated=allocated, namespaces=namespaces, unavailable=unavailable, previous=previous)


if __name__ == "__main__":
    main()
