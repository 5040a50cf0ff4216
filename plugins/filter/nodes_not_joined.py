# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The inventory's nodes the cluster has no Node for: a thin adapter over module_utils/kuberos_cluster/cluster_nodes.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: nodes_not_joined
short_description: The inventory's robots, edge servers and cloud VMs that have no Node in the cluster
version_added: 0.5.0
description:
  - Compares the inventory's node names with the names of the cluster's Nodes.
  - C(robots) are robots with no Node (powered off, or never joined); the C(node_labels) role leaves them for a
    later run. C(others) are edge servers and cloud VMs with no Node, which a site needs.
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
  existing:
    description: The names of the cluster's Nodes.
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
- name: Which hosts have not joined
  ansible.builtin.debug:
    msg: "{{ groups | kuberos.platform.fleet_inventory(hostvars) | kuberos.platform.nodes_not_joined(node_names) }}"
"""

RETURN = r"""
_value:
  description: C(robots) and C(others), each a sorted list of node names.
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import not_joined
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def nodes_not_joined(inventory, existing):
    return not_joined(load_inventory(inventory), [str(name) for name in existing or ()])


class FilterModule:
    def filters(self):
        return {"nodes_not_joined": nodes_not_joined}
