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
  pin_images:
    description:
      - Deploy and rollouts resolve each image that names no digest to the digest its registry serves now and render
        C(image:tag@digest), so a tag that moves changes nothing until the next deploy or rollout (docs/security.md).
      - An image that cannot be resolved stops the deploy before anything is applied.
      - False renders images by tag as written (a lab whose nodes hold their images and no registry serves them).
    type: bool
    default: true
  registry_mirrors:
    description:
      - The site's registry mirrors, asked before a registry itself, in the form of C(node_prereqs_registry_mirrors)
        (registry host to a list of C(url) and C(ca); C(insecure=true) allows a plain C(http://) mirror).
      - A registry's credentials (from the pull secrets) go only to that registry's own address; a mirror is sent
        only the credentials given under its own address.
    type: dict
    default: {}
  registry_token_realms:
    description:
      - Registry address (host[:port]) to the token services (realm URLs or hosts) on another host that may be sent
        its credentials when the registry's bearer challenge names them. Any other realm is asked without them.
        Docker Hub's (C(auth.docker.io) for C(registry-1.docker.io)) is known.
    type: dict
    default: {}
"""
