#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Check an inventory as a site before any machine is touched (documentation; the action plugin of the same name
does the work, on the controller)."""

from __future__ import annotations

DOCUMENTATION = r"""
module: site_check
short_description: Check the inventory as a site before site.yml touches any machine
version_added: 0.3.0
description:
  - Checks everything the cluster setup roles will need from the inventory, for every machine of the groups
    C(robots), C(edge) and C(cloud) - the resource model (P(kuberos.platform.fleet_inventory#filter)), the control
    plane group, the networks, the control-plane endpoint and every host's addresses
    (P(kuberos.platform.kubeadm_config#filter)), and the VPN (exactly one C(vpn_gateway) when there are cloud VMs,
    a C(kuberos_vpn_address) of its own on each of its hosts).
  - On failure, C(msg) is one line and C(problems) lists every problem once, one line each, naming the host and the
    variable, however many machines share it.
  - Reads the inventory only; contacts no machine. Runs on the controller (an action plugin).
attributes:
  action:
    support: full
  check_mode:
    support: full
  diff_mode:
    support: none
options:
  kubernetes_version:
    description: The site's Kubernetes version (C(kuberos_kubernetes_version)).
    type: str
    default: v1.34.4
  pod_cidr:
    description: The pods' network (C(kuberos_pod_cidr)).
    type: str
    default: 10.244.0.0/16
  service_cidr:
    description: The services' network (C(kuberos_service_cidr)).
    type: str
    default: 10.96.0.0/12
  control_plane_endpoint:
    description:
      - C(host:port) of the API servers' virtual IP or load balancer (C(kuberos_control_plane_endpoint)).
      - Empty for the first control plane's address, or the virtual IP's and port 6443 when C(control_plane_vip) is set.
    type: str
    default: ""
  control_plane_vip:
    description:
      - The API servers' virtual IP (C(kuberos_control_plane_vip)), held by keepalived among the control planes (role
        C(kuberos.platform.control_plane_vip)). It must be an IPv4 address no control plane has, and the endpoint must
        name it (or a DNS name).
    type: str
    default: ""
extends_documentation_fragment:
  - kuberos.platform.attributes
  - kuberos.platform.attributes.action
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Check the inventory before any machine is touched
  kuberos.platform.site_check:
    pod_cidr: "{{ kuberos_pod_cidr | default('10.244.0.0/16') }}"
    control_plane_endpoint: "{{ kuberos_control_plane_endpoint | default('') }}"
    control_plane_vip: "{{ kuberos_control_plane_vip | default('') }}"
"""

RETURN = r"""
problems:
  description: Every problem, once, one line each (host, variable, reason).
  returned: failure
  type: str
"""
