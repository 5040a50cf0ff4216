# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Calico's objects: a thin adapter over module_utils/kuberos_cluster/calico.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: calico_manifests
short_description: The Kubernetes objects of a manifest-based Calico install with the Kubernetes datastore
version_added: 0.2.0
description:
  - Returns, in apply order, Calico's CustomResourceDefinitions, the default IPPool with the pod CIDR, the
    ServiceAccounts, ClusterRoles and bindings of calico-node, the CNI plugin and calico-kube-controllers, the
    C(calico-config) ConfigMap, the calico-node DaemonSet (tolerating the robot taint) and the
    calico-kube-controllers Deployment with its PodDisruptionBudget.
  - The MTU of pods and tunnels is O(base_mtu) minus the encapsulation overhead (IP-in-IP 20, VXLAN 50, or 70
    for an IPv6 pool) minus 60 for WireGuard when O(vpn=true).
  - Invalid settings fail with every problem at once, each naming the role variable (C(calico_) and the option's
    name), the value and the reason.
  - The CRDs type the IPPool fields this collection sets and keep every other field as written; Calico's own
    complete schemas are not included.
options:
  _input:
    description: The pod network, in CIDR notation (IPv4 or IPv6).
    type: str
    required: true
  version:
    description: Calico release tag of the images.
    type: str
    default: v3.31.3
  image_registry:
    description: Registry path the C(node), C(cni) and C(kube-controllers) images are pulled from.
    type: str
    default: quay.io/calico
  block_size:
    description: Prefix length of the address block each node takes (20-32 for IPv4, 116-128 for IPv6).
    type: int
    default: 26 for IPv4, 122 for IPv6
  encapsulation:
    description: How pod traffic between nodes is carried.
    type: str
    choices: [ipip, vxlan, none]
    default: vxlan
  encapsulation_mode:
    description: Encapsulate always, or only between nodes of different subnets.
    type: str
    choices: [Always, CrossSubnet]
    default: Always
  base_mtu:
    description: MTU of the nodes' network.
    type: int
    default: 1500
  vpn:
    description: Pod traffic crosses the site's WireGuard VPN (cloud VMs), which takes 60 bytes more per packet.
    type: bool
    default: false
  ip_autodetection_method:
    description: How calico-node finds each node's address (C(first-found), C(kubernetes-internal-ip),
      C(can-reach=...), C(interface=...), C(skip-interface=...), C(cidr=...)).
    type: str
    default: first-found
  nat_outgoing:
    description: Masquerade traffic from pods to addresses outside the pod network.
    type: bool
    default: true
  admin_network_policy_crds:
    description: Include the CRDs of the AdminNetworkPolicy API (policy.networking.k8s.io), which calico-node watches;
      false when the cluster has them already.
    type: bool
    default: true
  namespace:
    description: Namespace of Calico's workloads.
    type: str
    default: kube-system
"""

EXAMPLES = r"""
- name: Apply Calico with a VXLAN pool over the VPN
  kubernetes.core.k8s:
    definition: "{{ '10.244.0.0/16' | kuberos.platform.calico_manifests(encapsulation='vxlan', vpn=true) }}"
    apply: true
    server_side_apply:
      field_manager: kuberos
"""

RETURN = r"""
_value:
  description: Kubernetes objects, in apply order (CustomResourceDefinitions first).
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import calico_objects, settings_from
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def calico_manifests(pod_cidr, **options):
    return calico_objects(settings_from(pod_cidr, options))


class FilterModule:
    def filters(self):
        return {"calico_manifests": calico_manifests}
