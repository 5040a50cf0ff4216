# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The nodes still waiting for a CNI agent: a thin adapter over module_utils/kuberos_cluster/cluster_nodes.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: agents_waiting
short_description: The nodes whose kubelet reports but whose node agent (a DaemonSet pod) is not Ready yet
version_added: 0.5.0
description:
  - What the CNI roles wait for. A node whose kubelet stopped reporting (its Ready condition Unknown, as for a robot
    that is powered off) is not waited for; every other node needs a Ready agent pod that is not being deleted.
options:
  _input:
    description: The agent's pods (P(kubernetes.core.k8s_info#module) resources).
    type: list
    elements: dict
    required: true
  nodes:
    description: The cluster's Nodes (P(kubernetes.core.k8s_info#module) resources).
    type: list
    elements: dict
    required: true
"""

EXAMPLES = r"""
- name: Nodes without a Ready agent
  ansible.builtin.debug:
    msg: "{{ agents.resources | kuberos.platform.agents_waiting(nodes.resources) }}"
"""

RETURN = r"""
_value:
  description: The node names, sorted.
  type: list
  elements: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import agents_waiting as waiting


def agents_waiting(pods, nodes):
    return waiting(pods, nodes)


class FilterModule:
    def filters(self):
        return {"agents_waiting": agents_waiting}
