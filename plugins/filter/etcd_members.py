# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The site's etcd members as kubeadm made them: a thin adapter over module_utils/kuberos_cluster/etcd_snapshots.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_members
short_description: The etcd members of a kubeadm site with stacked etcd, and its --initial-cluster
version_added: 0.3.0
description:
  - kubeadm names a control plane's etcd member after its node (C(kuberos_node_name), else the inventory name) and
    advertises it on C(https://<address>:2380), the address the API server advertises (C(kuberos_address), else
    C(ansible_host)).
  - Duplicate node names or peer URLs, and names or addresses etcd cannot use, are reported together, naming the host.
options:
  _input:
    description: The control planes' inventory names (C(groups['control_plane'])), in the inventory's order.
    type: list
    elements: str
    required: true
  hostvars:
    description: The C(hostvars) magic variable.
    type: raw
    required: true
"""

EXAMPLES = r"""
- name: Show the site's etcd members
  ansible.builtin.debug:
    msg: "{{ (groups['control_plane'] | kuberos.platform.etcd_members(hostvars)).initial_cluster }}"
"""

RETURN = r"""
_value:
  description: The members and their C(--initial-cluster).
  type: dict
  contains:
    members:
      description: One per control plane, with C(host), C(name) (the node name), C(address) and C(peer_url).
      type: list
      elements: dict
    initial_cluster:
      description: C(name=peer URL) of every member, comma-separated (C(edge-a=https://10.0.0.11:2380,...)).
      type: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import host_address, node_name


@reports_kuberos_errors
def etcd_members(control_planes, hostvars):
    hosts = [str(h) for h in control_planes or []]
    found = etcd_snapshots.members(
        hosts, {h: node_name(hostvars[h], h) for h in hosts}, {h: host_address(hostvars[h], h) for h in hosts}
    )
    return {
        "members": [{"host": m.host, "name": m.name, "address": m.address, "peer_url": m.peer_url} for m in found],
        "initial_cluster": etcd_snapshots.initial_cluster(found),
    }


class FilterModule:
    def filters(self):
        return {"etcd_members": etcd_members}
