# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""A Kubernetes upgrade's plan (module_utils/kuberos_cluster/upgrade.py)."""

from __future__ import annotations

DOCUMENTATION = r"""
name: kubernetes_upgrade_plan
short_description: What a Kubernetes upgrade run does to each node, or why it refuses
version_added: 0.4.0
description:
  - From the cluster's version (kubeadm-config's C(kubernetesVersion)), the Node objects and the inventory's
    machines, the plan of C(playbooks/upgrade.yml) - one minor version at a time; each host C(upgrade), C(done),
    C(pending) (a robot that does not answer), C(behind) (more than one minor below the target) or C(not_joined).
  - Refused, naming both versions - a version that is not one, a downgrade, a skipped minor, a node newer than the
    target, a control plane or worker that does not answer, a kubelet left more than three minors behind.
options:
  _input:
    description: The version to reach (C(kuberos_kubernetes_version)), such as C(v1.34.4).
    type: str
    required: true
  cluster_version:
    description: The cluster's version as kubeadm keeps it.
    type: str
    required: true
  nodes:
    description: The cluster's Node objects.
    type: list
    elements: dict
    required: true
  hosts:
    description: The inventory's machines in the order they are upgraded, each C(host), C(node), C(kind)
      (control_plane, worker or robot) and C(reached).
    type: list
    elements: dict
    required: true
"""

EXAMPLES = r"""
- name: The plan
  ansible.builtin.set_fact:
    plan: "{{ 'v1.34.4' | kuberos.platform.kubernetes_upgrade_plan('v1.33.7', nodes.resources, machines) }}"
"""

RETURN = r"""
_value:
  description: C(refusal) (empty when the run may go on), C(from), C(to), C(apply) and C(apply_host) (where
    kubeadm upgrade apply runs), C(hosts) (host -> node, kind, kubelet, action, why), a list per action, and C(lines).
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.upgrade import upgrade_plan
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


def kubernetes_upgrade_plan(target, cluster_version, nodes, hosts):
    return upgrade_plan(str(target), str(cluster_version), plain(nodes), plain(hosts))


class FilterModule:
    def filters(self):
        return {"kubernetes_upgrade_plan": kubernetes_upgrade_plan}
