# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Node objects from the inventory: a thin adapter over module_utils/kuberos_cluster/cluster_nodes.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cluster_nodes
short_description: Kubernetes Node objects for every robot, edge server and cloud VM of the inventory
version_added: 0.1.0
description:
  - With O(simulated=false), the part of each Node the resource manager owns, ready for server-side apply
    on a real cluster, the KubeROS labels (role, hostname, robot, fleet, devices, resource group). Robot taints
    are merged separately (P(kubernetes.core.k8s_taint#module)), see the C(node_labels) role.
  - With O(simulated=true), whole nodes for kwok, with the same labels and taints plus the
    capacity (cpu, memory, pods, nvidia.com/gpu) of the inventory.
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
  simulated:
    description: Build whole kwok nodes instead of label patches.
    type: bool
    default: false
  exclude:
    description: Node names to leave out (the local cluster's real nodes, which register themselves).
    type: list
    elements: str
    default: []
"""

EXAMPLES = r"""
- name: Label the cluster's nodes from the inventory
  kubernetes.core.k8s:
    definition: "{{ groups | kuberos.platform.fleet_inventory(hostvars) | kuberos.platform.cluster_nodes }}"
    apply: true
    server_side_apply:
      field_manager: kuberos-resource-manager
"""

RETURN = r"""
_value:
  description: A list of Node objects, one per robot, edge server and cloud VM.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import cluster_nodes as build_nodes
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def cluster_nodes(inventory, simulated=False, exclude=()):
    return build_nodes(load_inventory(inventory), bool(simulated), exclude or ())


class FilterModule:
    def filters(self):
        return {"cluster_nodes": cluster_nodes}
