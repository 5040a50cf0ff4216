# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Calico's published objects adapted to the site: a thin adapter over module_utils/kuberos_cluster/calico.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: calico_manifests
short_description: Calico's published VXLAN manifest adapted to the site
version_added: 0.2.0
description:
  - Takes the objects of Calico's published C(manifests/calico-vxlan.yaml) for O(version) (the manifest install with
    the Kubernetes datastore) and returns them in apply order, CustomResourceDefinitions first, changed only where a
    site's choices go.
  - Every Calico image (C(node), C(cni), C(kube-controllers)) from O(image_registry) at O(version); the manifest must
    be that release's.
  - The C(calico-config) ConfigMap's C(veth_mtu) is O(base_mtu) (or O(vpn_mtu) when O(vpn=true) and smaller) less
    VXLAN's 50 bytes; calico-node's pool is O(pod_cidr) with O(block_size), VXLAN O(encapsulation_mode), IP-in-IP
    never, NAT outgoing per O(nat_outgoing); its address autodetection and CPU request are set; a hash of the
    ConfigMap in its pod template rolls it when the MTU changes.
  - Invalid settings or a manifest without the objects this needs fail with every problem at once, each naming the
    role variable (C(calico_) and the option's name) or the manifest, the value and the reason.
options:
  _input:
    description: The objects of Calico's published C(calico-vxlan.yaml)
      (for example C(lookup('file', path) | from_yaml_all | list)).
    type: list
    elements: dict
    required: true
  pod_cidr:
    description: The pod network, in CIDR notation (IPv4); kubeadm's podSubnet.
    type: str
    required: true
  source:
    description: Where the manifest was read from, for the messages.
    type: str
    default: the manifest
  version:
    description: Calico release of the manifest and the images.
    type: str
    default: v3.31.3
  image_registry:
    description: Registry path the C(node), C(cni) and C(kube-controllers) images are pulled from.
    type: str
    default: quay.io/calico
  block_size:
    description: Prefix length of the address block each node takes (20-32).
    type: int
    default: 26
  encapsulation_mode:
    description: VXLAN between all nodes, or only between nodes of different subnets.
    type: str
    choices: [Always, CrossSubnet]
    default: Always
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
  ip_autodetection_method:
    description: How calico-node finds each node's address (C(first-found), C(kubernetes-internal-ip),
      C(can-reach=...), C(interface=...), C(skip-interface=...), C(cidr=...)).
    type: str
    default: first-found
  nat_outgoing:
    description: Masquerade traffic from pods to addresses outside the pod network.
    type: bool
    default: true
  node_cpu_request:
    description: calico-node's CPU request (C(0) for none).
    type: str
    default: 250m
"""

EXAMPLES = r"""
- name: Apply Calico's published release over the VPN
  kubernetes.core.k8s:
    definition: >-
      {{ lookup('ansible.builtin.file', 'calico-vxlan.yaml') | from_yaml_all | list
         | kuberos.platform.calico_manifests(pod_cidr='10.244.0.0/16', version='v3.31.3', vpn=true) }}
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
def calico_manifests(published, pod_cidr=None, source="the manifest", **options):
    return calico_objects(published, settings_from(pod_cidr, options), source=source)


class FilterModule:
    def filters(self):
        return {"calico_manifests": calico_manifests}
