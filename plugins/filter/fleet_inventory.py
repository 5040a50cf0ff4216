# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Collects the KubeROS resource model (robots, edge, cloud) out of Ansible's inventory."""

from __future__ import annotations

DOCUMENTATION = r"""
name: fleet_inventory
short_description: The KubeROS resource model of an Ansible inventory
version_added: 0.1.0
description:
  - Takes C(groups) and C(hostvars) and returns the plain-data resource model that the scheduler uses,
    made of every host of the groups C(robots), C(edge) and C(cloud) with its resource-model variables
    (C(kuberos_cpu), C(kuberos_fleet)... as listed in docs/inventory.md; site settings such as
    C(kuberos_kubeconfig) are left out).
  - Validates it, failing with the host, the variable and the reason for each problem, unless O(validate=false),
    which a task whose module validates it anyway sets (the P(kuberos.platform.rosdeployment#module) family), so
    that an inventory is validated once per task.
options:
  _input:
    description: The C(groups) magic variable.
    type: dict
    required: true
  hostvars:
    description: The C(hostvars) magic variable.
    type: raw
    required: true
  validate:
    description: Validate the resource model here (V(false) leaves it to the module the model is given to).
    type: bool
    default: true
  without:
    description:
      - Hosts to leave out of the model, as if they were not in the inventory (C(playbooks/remove_node.yml)
        passes the deployments without the host it removes).
    type: list
    elements: str
    default: []
"""

EXAMPLES = r"""
- name: Build the resource model
  ansible.builtin.set_fact:
    fleet: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
"""

RETURN = r"""
_value:
  description: >-
    C(hosts) (each host's resource-model variables), C(groups) (robots, edge, cloud, and clusters when there are
    third-party clusters) and C(default_latency_ms).
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory, raw_inventory
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def fleet_inventory(groups, hostvars, validate=True, without=()):
    if without:
        gone = set(without)
        groups = {name: [h for h in hosts if h not in gone] for name, hosts in groups.items()}
    raw = plain(raw_inventory(groups, hostvars))
    if validate:
        load_inventory(raw)  # validates: every problem named by host and variable
    return raw


class FilterModule:
    def filters(self):
        return {"fleet_inventory": fleet_inventory}
