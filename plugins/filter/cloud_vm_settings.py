# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The cloud VM settings, checked: a thin adapter over module_utils/kuberos_cluster/cloud.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cloud_vm_settings
short_description: Check the settings of the cloud_vms role (site, fleet, count, instance type, budget, region...)
version_added: 0.3.0
description:
  - Checks the request and the budget before any cloud API is called, and fails once with every problem, each naming
    the variable (C(cloud_vms_budget.instance_types['t3.large'].cpu)), the value and what is expected.
  - Returns the settings as they were given, so that the other cloud filters can take them.
options:
  _input:
    description:
      - The settings, keyed by the role's variable names without C(cloud_vms_) (C(site), C(fleet), C(count),
        C(instance_type), C(release), C(region), C(latency_ms), C(resource_group), C(ssh_user), C(vpn_network),
        C(budget)). No credentials.
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Check the settings
  ansible.builtin.set_fact:
    settings: "{{ {'site': 'local', 'fleet': 'test-fleet', 'count': 2, 'instance_type': 't3.large',
                   'region': 'eu-central-1', 'budget': {'max_vms': 4, 'instance_types': {'t3.large': {'cpu': 2,
                   'memory': '8Gi'}}}} | kuberos.platform.cloud_vm_settings }}"
"""

RETURN = r"""
_value:
  description: The settings, unchanged.
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cloud import load_settings
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def cloud_vm_settings(settings):
    settings = plain(settings)
    load_settings(settings)
    return settings


class FilterModule:
    def filters(self):
        return {"cloud_vm_settings": cloud_vm_settings}
