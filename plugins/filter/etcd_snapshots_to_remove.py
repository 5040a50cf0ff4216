# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The retention of etcd snapshots: a thin adapter over module_utils/kuberos_cluster/etcd_snapshots.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_snapshots_to_remove
short_description: The etcd snapshots to remove so that the newest ones stay
version_added: 0.3.0
description:
  - Of the given files, those named C(etcd-snapshot-<UTC time>-<node>.db) beyond the newest O(keep), oldest first.
    The time in the name decides, not the file's modification time. Any other file is never selected.
options:
  _input:
    description: File paths (C(ansible.builtin.find)'s C(files) mapped to their C(path)), or names.
    type: list
    elements: str
    required: true
  keep:
    description: How many snapshots stay (1 or more).
    type: int
    required: true
"""

EXAMPLES = r"""
- name: Remove the snapshots beyond the newest seven
  ansible.builtin.file:
    path: "{{ item }}"
    state: absent
  loop: "{{ found.files | map(attribute='path') | kuberos.platform.etcd_snapshots_to_remove(7) }}"
"""

RETURN = r"""
_value:
  description: The paths to remove, oldest first.
  type: list
  elements: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def etcd_snapshots_to_remove(paths, keep):
    count = int(keep) if isinstance(keep, str) and keep.strip().isdigit() else keep
    return etcd_snapshots.snapshots_to_remove([str(p) for p in paths or []], count)


class FilterModule:
    def filters(self):
        return {"etcd_snapshots_to_remove": etcd_snapshots_to_remove}
