# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The inventory a site's cloud VMs become: a thin adapter over module_utils/kuberos_cluster/cloud.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cloud_vm_inventory
short_description: A YAML inventory source with a host of the group cloud for every running VM of a site
version_added: 0.3.0
description:
  - Every running VM KubeROS manages at the site becomes a host of the group C(cloud), named like the VM, with the
    host variables of docs/inventory.md (C(kuberos_cpu), C(kuberos_memory), C(kuberos_gpu), C(kuberos_arch),
    C(kuberos_fleets), C(kuberos_shared), C(kuberos_latency_ms), C(kuberos_resource_group)), its address
    (C(ansible_host)), its VPN address when it has one, and the instance id, type and region.
options:
  _input:
    description: The C(instances) of P(amazon.aws.ec2_instance_info#module), with their tags.
    type: list
    elements: dict
    required: true
  settings:
    description: The settings, as P(kuberos.platform.cloud_vm_settings#filter) takes them.
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Write the inventory file
  ansible.builtin.copy:
    dest: inventories/site/cloud_vms.yml
    content: "{{ found.instances | kuberos.platform.cloud_vm_inventory(settings) | to_nice_yaml(indent=2) }}"
    mode: "0644"
"""

RETURN = r"""
_value:
  description: "A YAML inventory source: C(all.children.cloud.hosts), each VM's name to its host variables."
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cloud import (
    inventory_document,
    inventory_hosts,
    load_settings,
    vms_from_instances,
)
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def cloud_vm_inventory(instances, settings):
    checked = load_settings(plain(settings))
    hosts = inventory_hosts(vms_from_instances(plain(instances)), checked.request.site, checked.budget)
    return inventory_document(hosts)


class FilterModule:
    def filters(self):
        return {"cloud_vm_inventory": cloud_vm_inventory}
