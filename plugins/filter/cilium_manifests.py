# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Cilium's objects: a thin adapter over module_utils/kuberos_cluster/cilium.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cilium_manifests
short_description: The Kubernetes objects of a manifest-based Cilium install beside kube-proxy
version_added: 0.3.0
description:
  - Returns, in apply order, the ServiceAccounts, ClusterRoles, Roles and bindings of the Cilium agent and operator,
    the C(cilium-config) ConfigMap, the C(cilium) DaemonSet (on every node, tainted robots included) and the
    C(cilium-operator) Deployment. The operator registers Cilium's CRDs when it starts.
  - A VXLAN or Geneve overlay, IPAM from the nodes' podCIDR, Kubernetes NetworkPolicy enforced by the agents; no
    kube-proxy replacement, no L7 proxy, no Hubble.
  - The network MTU given to the agent is O(base_mtu), or O(vpn_mtu) when O(vpn=true) and it is smaller; the agent
    subtracts 50 bytes of tunnel headers for the pods.
  - Invalid settings fail with every problem at once, each naming the role variable (C(cilium_) and the option's
    name), the value and the reason.
options:
  _input:
    description: The pod network, in CIDR notation (IPv4); kubeadm's podSubnet.
    type: str
    required: true
  version:
    description: Cilium release tag of the images.
    type: str
    default: v1.15.19
  image_registry:
    description: Registry path the C(cilium) and C(operator-generic) images are pulled from.
    type: str
    default: quay.io/cilium
  tunnel_protocol:
    description: The overlay between nodes.
    type: str
    choices: [vxlan, geneve]
    default: vxlan
  base_mtu:
    description: MTU of the nodes' network.
    type: int
    default: 1500
  vpn:
    description: Pod traffic crosses the site's WireGuard VPN (cloud VMs).
    type: bool
    default: false
  vpn_mtu:
    description: MTU of the WireGuard interface.
    type: int
    default: 1420
  masquerade:
    description: Masquerade traffic from pods to addresses outside the pod network.
    type: bool
    default: true
  agent_cpu_request:
    description: The agent's CPU request (C(0) for none).
    type: str
    default: 100m
  operator_replicas:
    description: Replicas of the operator.
    type: int
    default: 1
  namespace:
    description: Namespace of Cilium's workloads.
    type: str
    default: kube-system
"""

EXAMPLES = r"""
- name: Apply Cilium with a VXLAN overlay over the VPN
  kubernetes.core.k8s:
    definition: "{{ '10.244.0.0/16' | kuberos.platform.cilium_manifests(vpn=true) }}"
    apply: true
    server_side_apply:
      field_manager: kuberos
"""

RETURN = r"""
_value:
  description: Kubernetes objects, in apply order.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cilium import cilium_objects, settings_from
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def cilium_manifests(pod_cidr, **options):
    return cilium_objects(settings_from(pod_cidr, options))


class FilterModule:
    def filters(self):
        return {"cilium_manifests": cilium_manifests}
