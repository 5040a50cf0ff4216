# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""One control plane's part of restoring the site's etcd: a thin adapter over kuberos_cluster/etcd_snapshots.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_restore_plan
short_description: One control plane's part of restoring every etcd member of the site from one snapshot
version_added: 0.3.0
description:
  - Reads the control plane's etcd static pod manifest (kubeadm's C(etcd.yaml)) for the etcd image, the member's
    name and peer URL and the data directory, and checks them against the inventory (C(kuberos_node_name),
    C(kuberos_address)), since a restore must make the members the manifests describe.
  - Returns where the snapshot is copied (beside the data directory), the new data directory etcdutl writes, where
    the old one is kept (C(<data dir>.before-restore-<stamp>)), and the C(ctr run) that runs C(etcdutl snapshot
    restore) from the etcd image already in containerd, with C(--initial-cluster) of every member, a new cluster
    token, and the revision bumped by O(bump_revision) and marked compacted.
options:
  _input:
    description: The control planes' inventory names (C(groups['control_plane'])).
    type: list
    elements: str
    required: true
  hostvars:
    description: The C(hostvars) magic variable.
    type: raw
    required: true
  host:
    description: The control plane whose plan is returned (C(inventory_hostname)).
    type: str
    required: true
  manifest:
    description: Its C(etcd.yaml), parsed (C(from_yaml)).
    type: dict
    required: true
  stamp:
    description: The restore's UTC time, C(20261207T031500Z); names the kept directory, the token and the container.
    type: str
    required: true
  bump_revision:
    description: How far etcd's revision moves on past the snapshot's.
    type: int
    default: 1000000000
"""

EXAMPLES = r"""
- name: Plan this control plane's part of the restore
  ansible.builtin.set_fact:
    plan: >-
      {{ groups['control_plane'] | kuberos.platform.etcd_restore_plan(hostvars, inventory_hostname,
         manifest.content | b64decode | from_yaml, stamp='20261207T031500Z') }}
"""

RETURN = r"""
_value:
  description: The plan.
  type: dict
  contains:
    name:
      description: The member's name (the node name).
      type: str
    peer_url:
      description: The member's peer URL.
      type: str
    initial_cluster:
      description: Every member as C(name=peer URL).
      type: str
    token:
      description: The new cluster's token.
      type: str
    image:
      description: The etcd image of the manifest.
      type: str
    data_dir:
      description: etcd's data directory.
      type: str
    snapshot:
      description: Where the snapshot is copied on the host.
      type: str
    restored_dir:
      description: The data directory etcdutl writes.
      type: str
    kept_dir:
      description: Where the old data directory is kept.
      type: str
    restore_argv:
      description: The C(ctr run ... etcdutl snapshot restore ...) command.
      type: list
      elements: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import host_address, node_name, plain


@reports_kuberos_errors
def etcd_restore_plan(control_planes, hostvars, host, manifest, stamp, bump_revision=etcd_snapshots.DEFAULT_BUMP_REVISION):
    hosts = [str(h) for h in control_planes or []]
    found = etcd_snapshots.members(
        hosts, {h: node_name(hostvars[h], h) for h in hosts}, {h: host_address(hostvars[h], h) for h in hosts}
    )
    bump = int(bump_revision) if isinstance(bump_revision, str) and bump_revision.isdigit() else bump_revision
    return etcd_snapshots.restore_plan(found, str(host), plain(manifest), str(stamp), bump)


class FilterModule:
    def filters(self):
        return {"etcd_restore_plan": etcd_restore_plan}
