# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What etcdutl says of a snapshot: a thin adapter over module_utils/kuberos_cluster/etcd_snapshots.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_snapshot_status
short_description: The revision, key count, size and hash of an etcd snapshot, from etcdutl's JSON status
version_added: 0.3.0
description:
  - Reads what C(etcdutl snapshot status <file> -w json) (or C(etcdctl)'s) printed. Fails on anything else, and on
    a snapshot with no revision or no keys, which holds no cluster.
options:
  _input:
    description: etcdutl's standard output.
    type: str
    required: true
"""

EXAMPLES = r"""
- name: Report the snapshot
  ansible.builtin.debug:
    msg: "{{ (status.stdout | kuberos.platform.etcd_snapshot_status).revision }}"
"""

RETURN = r"""
_value:
  description: The snapshot's status.
  type: dict
  contains:
    revision:
      description: etcd's revision in the snapshot.
      type: int
    keys:
      description: How many keys it holds.
      type: int
    size_bytes:
      description: The database's size in bytes.
      type: int
    size:
      description: The size for a person (C(12.3 MiB)).
      type: str
    hash:
      description: etcd's hash of the database.
      type: int
    version:
      description: The storage version etcdutl reports (empty from etcd 3.5).
      type: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def etcd_snapshot_status(text):
    return etcd_snapshots.snapshot_status(str(text or ""))


class FilterModule:
    def filters(self):
        return {"etcd_snapshot_status": etcd_snapshot_status}
