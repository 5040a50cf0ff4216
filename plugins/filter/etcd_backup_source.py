# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Which etcd pod a backup snapshots: a thin adapter over module_utils/kuberos_cluster/etcd_snapshots.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_backup_source
short_description: The healthy etcd member a snapshot is taken from, and the snapshot's name
version_added: 0.3.0
description:
  - Of the site's etcd static pods, the first that is Running and Ready on a control plane of the inventory (its
    node's name mapped back to the inventory host, C(kuberos_node_name) else the inventory name), or the one on
    O(preferred), which must be so.
  - When no pod will do, fails naming every pod and why.
options:
  _input:
    description: The etcd pods (C(kubernetes.core.k8s_info) resources, label C(component=etcd) in C(kube-system)).
    type: list
    elements: dict
    required: true
  control_planes:
    description: The control planes' inventory names.
    type: list
    elements: str
    required: true
  hostvars:
    description: The C(hostvars) magic variable.
    type: raw
    required: true
  stamp:
    description: The snapshot's UTC time, C(20261207T031500Z).
    type: str
    required: true
  preferred:
    description: An inventory host to take the snapshot on; empty for the first healthy one.
    type: str
    default: ""
"""

EXAMPLES = r"""
- name: Choose the etcd member to snapshot
  ansible.builtin.set_fact:
    source: >-
      {{ pods.resources | kuberos.platform.etcd_backup_source(groups['control_plane'], hostvars,
         stamp=now(utc=true, fmt='%Y%m%dT%H%M%SZ')) }}
"""

RETURN = r"""
_value:
  description: The source of the snapshot.
  type: dict
  contains:
    pod:
      description: The etcd pod's name.
      type: str
    node:
      description: Its node.
      type: str
    host:
      description: Its inventory host.
      type: str
    name:
      description: The snapshot's file name, C(etcd-snapshot-<stamp>-<node>.db).
      type: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import node_name, plain


@reports_kuberos_errors
def etcd_backup_source(pods, control_planes, hostvars, stamp, preferred=""):
    node_hosts = {node_name(hostvars[str(h)], str(h)): str(h) for h in control_planes or []}
    return etcd_snapshots.backup_source(plain(pods or []), node_hosts, str(stamp), str(preferred or ""))


class FilterModule:
    def filters(self):
        return {"etcd_backup_source": etcd_backup_source}
