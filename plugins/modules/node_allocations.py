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
  spec:
    description:
      - Path of the RosDeployment file about to be deployed. When given, the module fails, with one line per module,
        if a module of the file would name a Deployment or ConfigMap like an object already in its fleet's namespace
        that is not its own (another deployment's, or not KubeROS's). Names join deployment, module and robot with
        a dash, so deployment C(a-b) with module C(c) and deployment C(a) with module C(b-c) name their instances
        alike. The robots come from O(inventory).
    type: path
  catalog:
    description: The software catalog that the O(spec)'s C(module) references resolve against (a directory or one file).
    type: path
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

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import DEPLOYMENT, MODULE
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file, name_clash_problems
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import (
    namespace_names,
    node_allocations,
    previous_placement,
    unavailable_nodes,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, Kube, api_clients

# The kinds of object a module's names are given to (naming.module_object_names).
NAMED_KINDS = ("Deployment", "ConfigMap")


def live_names(clients, namespaces) -> list[dict]:
    """Every Deployment and ConfigMap of ``namespaces`` with the deployment and module that own it ('' when none)."""
    kube = Kube(clients)
    found = []
    for namespace in sorted(set(namespaces)):
        for kind in NAMED_KINDS:
            for item in kube.list(kind, namespace):
                labels = item["metadata"].get("labels") or {}
                found.append(
                    {
                        "kind": kind,
                        "namespace": namespace,
                        "name": item["metadata"]["name"],
                        "deployment": labels.get(DEPLOYMENT, ""),
                        "module": labels.get(MODULE, ""),
                    }
                )
    return found


def check_names(clients, spec: str, catalog: str | None, inventory) -> None:
    """Raise ``SpecError`` when a module of ``spec`` would take the name of an object that is not its own."""
    deployments = load_rosdeployment_file(spec, catalog=load_catalog(catalog) if catalog else None)
    fleets = inventory.fleets if inventory is not None else {}

    def robots_of(dep):
        return dep.robots or fleets.get(dep.fleet)

    live = live_names(clients, [fleet_namespace(dep.fleet) for dep in deployments])
    problems = name_clash_problems(deployments, robots_of, live)
    if problems:
        raise SpecError(problems, title=f"{spec} would take the names of objects in the cluster")


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            exclude_deployments=dict(type="list", elements="str", default=[]),
            exclude_discovery_of_fleets=dict(type="list", elements="str", default=[]),
            inventory=dict(type="dict"),
            previous_of=dict(type="list", elements="dict", default=[]),
            spec=dict(type="path"),
            catalog=dict(type="path"),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    try:
        clients = api_clients(module.params["kubeconfig"])
        allocated = node_allocations(clients, module.params["exclude_deployments"], module.params["exclude_discovery_of_fleets"])
        namespaces = namespace_names(clients)
        inventory = load_inventory(module.params["inventory"]) if module.params["inventory"] else None
        if module.params["spec"]:
            check_names(clients, module.params["spec"], module.params["catalog"], inventory)
        wanted = list(inventory.nodes) if inventory is not None else []
        unavailable = unavailable_nodes(clients, wanted)
        previous = previous_placement(clients, module.params["previous_of"])
    except Exception as exc:  # a KubeROS error, or the cluster's: one clear line, no traceback
        fail(module, exc, module.params["kubeconfig"])
    module.exit_json(changed=False, allocated=allocated, namespaces=namespaces, unavailable=unavailable, previous=previous)


if __name__ == "__main__":
    main()
