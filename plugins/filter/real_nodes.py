# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The local cluster's real nodes: a thin adapter over module_utils/kuberos_cluster/cluster_nodes.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: real_nodes
short_description: The hosts the local cluster runs as real nodes, with their labels, taints and link delays
version_added: 0.3.0
description:
  - A host whose C(kuberos_local_node) is C(real) becomes a real node of the local cluster (a kubelet,
    containerd and kube-proxy in a network namespace of its own); every other host is a kwok node.
  - Returns C(nodes) (name, tier, the KubeROS labels and taints its kubelet registers with) and C(delay_ms),
    the one-way delay between every two real nodes from the inventory's latencies (docs/real-nodes.md).
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
  hostvars:
    description: The play's C(hostvars), where C(kuberos_local_node) is read.
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Work out the real nodes
  ansible.builtin.set_fact:
    real: "{{ groups | kuberos.platform.fleet_inventory(hostvars) | kuberos.platform.real_nodes(hostvars) }}"
"""

RETURN = r"""
_value:
  description:
    - C(nodes), a list of C(name), C(tier), C(labels) and C(taints).
    - C(delay_ms), source node to destination node to milliseconds.
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import real_node_names
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import real_nodes as plan
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def real_nodes(inventory, hostvars):
    hosts = {
        host: {"kuberos_local_node": plain(hostvars[host].get("kuberos_local_node", "simulated"))}
        for host in inventory.get("hosts", {})
    }
    return plan(load_inventory(inventory), real_node_names(inventory, hosts))


class FilterModule:
    def filters(self):
        return {"real_nodes": real_nodes}
