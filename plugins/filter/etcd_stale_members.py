# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The etcd members a rebuilt control plane's join removes first (module_utils/kuberos_cluster/control_planes.py)."""

from __future__ import annotations

DOCUMENTATION = r"""
name: etcd_stale_members
short_description: The etcd members of control planes that join again
version_added: 0.4.0
description:
  - A control plane rebuilt from a bare disk joins again under its old node name and peer address, while etcd
    still lists its old member. The C(kubeadm_init) role removes those members first, through a control plane that
    serves. A member is stale when its name is a joining control plane's node name, or (a member added but never
    started has no name) when one of its peer URLs is a joining control plane's.
options:
  _input:
    description: etcd's member list (C(members) of its v3 JSON gateway's C(/v3/cluster/member/list)).
    type: list
    elements: dict
    required: true
  names:
    description: The node names of the control planes joining now.
    type: list
    elements: str
    required: true
  peer_urls:
    description: Their peer URLs (C(https://<address>:2380)).
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
- name: The members to remove
  ansible.builtin.debug:
    msg: "{{ members.json.members | kuberos.platform.etcd_stale_members(['edge-a'], ['https://10.0.0.11:2380']) }}"
"""

RETURN = r"""
_value:
  description: Each stale member once, with C(ID) (a string), C(name) and C(peerURLs).
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.control_planes import stale_members
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


def etcd_stale_members(members, names, peer_urls):
    return stale_members(plain(members), plain(names), plain(peer_urls))


class FilterModule:
    def filters(self):
        return {"etcd_stale_members": etcd_stale_members}
