# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The kubeadm configuration of one host: a thin adapter over module_utils/kuberos_cluster/kubeadm_config.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: kubeadm_config
short_description: The kubeadm configuration (v1beta4) of one robot, edge server or cloud VM
version_added: 0.2.0
description:
  - For the first host of O(control_planes), C(kubeadm init) documents (InitConfiguration, ClusterConfiguration
    with a control-plane endpoint, stacked etcd, the pod and service networks and the API server's certificate
    names, KubeletConfiguration with the systemd cgroup driver).
  - For the other control planes, a JoinConfiguration with C(controlPlane) (their own API endpoint and the
    certificate key); for every other host, a worker JoinConfiguration. Discovery is by bootstrap token and
    CA certificate hash.
  - Every node registers under its node name with the KubeROS labels (C(--node-labels)) and taints of
    docs/inventory.md; robots carry C(kuberos.io/robot=<robot>:NoSchedule). Labels a kubelet may not set on
    itself (under C(kubernetes.io) and C(k8s.io)) are left out and returned in C(labels_for_api).
  - Cloud VMs register with their C(kuberos_vpn_address) as node IP; other hosts with C(kuberos_address) when
    it is an IP address. A host's address is C(kuberos_address), else C(ansible_host), else its inventory name.
  - Without O(join_command) and O(certificate_key) the join secrets are placeholders (C(placeholders) is true),
    so the result can be shown and validated. With them, the result holds secrets; use it under C(no_log).
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
  hostvars:
    description: The C(hostvars) magic variable (for C(kuberos_address), C(ansible_host), C(kuberos_vpn_address)).
    type: raw
    required: true
  host:
    description: The inventory name of the host (C(inventory_hostname)).
    type: str
    required: true
  control_planes:
    description: The hosts running the control plane, the first one first (C(groups['control_plane'])).
    type: list
    elements: str
    required: true
  kubernetes_version:
    description: Kubernetes version of the control plane.
    type: str
    default: v1.34.4
  pod_cidr:
    description: The pods' network.
    type: str
    default: 10.244.0.0/16
  service_cidr:
    description: The services' network.
    type: str
    default: 10.96.0.0/12
  control_plane_endpoint:
    description:
      - C(host:port) of the API servers' load balancer or virtual IP.
      - Empty for the first control plane's address and port 6443.
    type: str
    default: ""
  cri_socket:
    description: The container runtime's socket.
    type: str
    default: unix:///run/containerd/containerd.sock
  bind_port:
    description: The port each API server listens on.
    type: int
    default: 6443
  cgroup_driver:
    description: The kubelets' cgroup driver, the same as containerd's (C(systemd) or C(cgroupfs)).
    type: str
    default: systemd
  image_repository:
    description: Registry path of the control-plane images (a mirror); empty for kubeadm's default (registry.k8s.io).
    type: str
    default: ""
  etcd_image_tag:
    description: Tag of the etcd image, when the site runs another etcd than kubeadm's default (e.g. C(3.5.35-0)).
    type: str
    default: ""
  coredns_image_tag:
    description: Tag of the CoreDNS image, when the site runs another CoreDNS than kubeadm's default.
    type: str
    default: ""
  conntrack_max_per_core:
    description:
      - kube-proxy's C(conntrack.maxPerCore) (a KubeProxyConfiguration document); unset for kube-proxy's default.
      - C(0) leaves the host's connection-tracking limit alone, for nodes that cannot set it (nested in a container).
    type: int
  eviction_hard:
    description:
      - "The kubelets' C(evictionHard) thresholds (eviction signal to threshold, such as C(nodefs.available) C(5%)),
        empty for the kubelet's defaults."
      - It replaces the defaults as a whole, so name every signal the nodes should watch.
    type: dict
    default: {}
  control_plane_schedulable:
    description: Control planes run modules too (no C(node-role.kubernetes.io/control-plane) taint).
    type: bool
    default: true
  extra_labels:
    description: More node labels for this host, on top of the KubeROS ones.
    type: dict
    default: {}
  join_command:
    description: Output of C(kubeadm token create --print-join-command) (the token and CA certificate hash are read from it).
    type: str
  certificate_key:
    description: The certificate key, or the output of C(kubeadm init phase upload-certs --upload-certs).
    type: str
  init_host:
    description:
      - The control plane that runs C(kubeadm init). Unset, the first of O(control_planes); empty, none does (the
        cluster exists, and every control plane without a node joins it, the first one too when it was rebuilt).
    type: str
"""

EXAMPLES = r"""
- name: Render this host's kubeadm configuration (placeholders for the secrets)
  ansible.builtin.set_fact:
    kubeadm: >-
      {{ groups | kuberos.platform.fleet_inventory(hostvars)
      | kuberos.platform.kubeadm_config(hostvars, inventory_hostname, groups['control_plane']) }}

- name: The same with the join secrets
  ansible.builtin.set_fact:
    kubeadm: >-
      {{ groups | kuberos.platform.fleet_inventory(hostvars)
      | kuberos.platform.kubeadm_config(hostvars, inventory_hostname, groups['control_plane'],
      join_command=join.stdout, certificate_key=certs.stdout) }}
  no_log: true
"""

RETURN = r"""
_value:
  description: What kubeadm needs on the host.
  type: dict
  contains:
    action:
      description: C(init) (O(init_host), by default the first control plane), C(join-control-plane) or C(join-worker).
      type: str
    node_name:
      description: The node name the host registers.
      type: str
    control_plane_endpoint:
      description: C(host:port) of the API.
      type: str
    cert_sans:
      description: Extra names in the API server certificate (the endpoint host, every control plane's addresses).
      type: list
      elements: str
    labels:
      description: Labels the kubelet sets on its node (C(--node-labels)).
      type: dict
    labels_for_api:
      description: Labels the kubelet may not set on itself, with the reason; the C(node_labels) role applies them.
      type: dict
    taints:
      description: Taints the node registers with.
      type: list
      elements: dict
    placeholders:
      description: The join secrets are placeholders.
      type: bool
    documents:
      description: The kubeadm documents.
      type: list
      elements: dict
    content:
      description: The documents as one YAML file, for C(kubeadm --config).
      type: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import kubeadm_config as core
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import host_address, plain

_SETTINGS = (
    "kubernetes_version", "pod_cidr", "service_cidr", "control_plane_endpoint", "cri_socket", "bind_port", "cgroup_driver",
    "image_repository", "etcd_image_tag", "coredns_image_tag", "conntrack_max_per_core", "eviction_hard",
)  # fmt: skip


@reports_kuberos_errors
def kubeadm_config(
    raw, hostvars, host, control_planes, extra_labels=None, join_command=None, certificate_key=None, init_host=None, **settings
):
    unknown = sorted(set(settings) - {*_SETTINGS, "control_plane_schedulable"})
    if unknown:
        raise SpecError([Problem("kubeadm_config", name, "unknown option") for name in unknown], "invalid filter options")
    inventory = load_inventory(raw)
    node_names = {h: str(v.get("kuberos_node_name", h)) for h, v in raw["hosts"].items()}
    addresses = {}
    for name in node_names:
        variables = hostvars[name]
        addresses[name] = {"address": host_address(variables, name), "vpn_address": plain(variables.get("kuberos_vpn_address"))}
    settings = plain(settings)
    for name in ("bind_port", "conntrack_max_per_core"):
        if isinstance(settings.get(name), str) and settings[name].isdigit():
            settings[name] = int(settings[name])
    return core.kubeadm_config(
        inventory,
        str(host),
        node_names,
        addresses,
        [str(h) for h in control_planes or []],
        settings={k: v for k, v in settings.items() if v not in (None, "", {})},
        extra_labels=plain(extra_labels or {}),
        join_command=None if join_command in (None, "") else str(join_command),
        certificate_key=None if certificate_key in (None, "") else str(certificate_key),
        init_host=None if init_host is None else str(init_host),
    )


class FilterModule:
    def filters(self):
        return {"kubeadm_config": kubeadm_config}
