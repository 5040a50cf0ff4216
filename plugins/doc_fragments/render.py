# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Options shared by the modules that render a placement into manifests."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  cluster_domain:
    description: DNS domain of the cluster, used in the discovery server addresses.
    type: str
    default: cluster.local
  discovery_image:
    description: Container image that provides C(fast-discovery-server).
    type: str
    default: ros:jazzy-ros-base
  bridge_image:
    description: Container image of the KubeROS-Bridge (for modules in third-party clusters).
    type: str
    default: ghcr.io/kuberos/bridge:0.2.0
  metrics_namespaces:
    description:
      - The namespaces whose pods may read the fleet's metrics ports (the bridges', the gauges of scaled modules).
      - Every other ingress to a fleet's pods comes from the fleet's own namespace (NetworkPolicy, docs/security.md).
    type: list
    elements: str
    default: [kuberos-system]
"""
