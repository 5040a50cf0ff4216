# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The robot taint of every robot node of the inventory."""

from __future__ import annotations

DOCUMENTATION = r"""
name: robot_taints
short_description: The taint each robot node carries, so that only modules KubeROS placed run there
version_added: 0.1.0
description:
  - Returns C({name, taints}) for every robot of the inventory, with the taint C(kuberos.io/robot=<robot>:NoSchedule),
    ready for P(kubernetes.core.k8s_taint#module).
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Taint robot nodes
  kubernetes.core.k8s_taint:
    name: "{{ item.name }}"
    taints: "{{ item.taints }}"
  loop: "{{ groups | kuberos.platform.fleet_inventory(hostvars) | kuberos.platform.robot_taints }}"
"""

RETURN = r"""
_value:
  description: One C({name, taints}) per robot node.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import robot_taints as build_taints
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def robot_taints(inventory):
    return build_taints(load_inventory(inventory))


class FilterModule:
    def filters(self):
        return {"robot_taints": robot_taints}
