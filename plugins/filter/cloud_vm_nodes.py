# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""kwok nodes for cloud VMs in the local cluster: a thin adapter over module_utils/kuberos_cluster/cloud.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cloud_vm_nodes
short_description: Simulated (kwok) Node objects of the local cluster for cloud VMs, labelled as cloud nodes
version_added: 0.3.0
description:
  - The embedded default site has no machines to join; each provisioned VM becomes a kwok node instead, with the
    KubeROS labels of a cloud node (C(kuberos.io/role=cloud), C(kuberos.io/shared), C(fleet-access.kuberos.io/<fleet>),
    the resource group) and the capacity of its instance type, as P(kuberos.platform.cluster_nodes#filter) builds them.
options:
  _input:
    description: The inventory source of P(kuberos.platform.cloud_vm_inventory#filter).
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: A kwok node for every VM
  kubernetes.core.k8s:
    definition: "{{ found.instances | kuberos.platform.cloud_vm_inventory(settings) | kuberos.platform.cloud_vm_nodes }}"
"""

RETURN = r"""
_value:
  description: A list of Node objects, one per VM, sorted by name.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cloud import simulated_nodes
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def cloud_vm_nodes(document):
    hosts = ((plain(document).get("all") or {}).get("children") or {}).get("cloud", {}).get("hosts") or {}
    return simulated_nodes(hosts)


class FilterModule:
    def filters(self):
        return {"cloud_vm_nodes": cloud_vm_nodes}
