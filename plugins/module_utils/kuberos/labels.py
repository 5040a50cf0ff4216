"""The one node label scheme, shared by the node labeller, the local cluster and the manifests."""

from __future__ import annotations

from .inventory import Node

DOMAIN = "kuberos.io"
ROLE = "kuberos.io/role"
HOSTNAME = "device.kuberos.io/hostname"
ROBOT = "robot.kuberos.io/name"
FLEET = "fleet.kuberos.io/name"
RESOURCE_GROUP = "resource-group.kuberos.io/name"
SHARED = "kuberos.io/shared"
ARCH = "kuberos.io/arch"
DEVICE_PREFIX = "devices.kuberos.io/"
FLEET_ACCESS_PREFIX = "fleet-access.kuberos.io/"
ROBOT_TAINT = "kuberos.io/robot"
ROLES = {"onboard": "robot", "edge": "edge", "cloud": "cloud"}


def node_labels(node: Node) -> dict[str, str]:
    """Labels a cluster node carries, derived from the inventory only."""
    labels = {
        ROLE: ROLES[node.tier],
        HOSTNAME: node.name,
        ARCH: node.arch,
        RESOURCE_GROUP: node.resource_group,
    }
    if node.tier == "onboard":
        labels[ROBOT] = node.robot or ""
        labels[FLEET] = node.fleet or ""
    else:
        labels[SHARED] = "true" if node.shared else "false"
        for fleet in node.fleets:
            labels[FLEET_ACCESS_PREFIX + fleet] = "true"
    for device in sorted(node.devices):
        labels[DEVICE_PREFIX + device] = "true"
    return dict(sorted(labels.items()))


def node_taints(node: Node) -> list[dict[str, str]]:
    """A robot's computer only takes the modules KubeROS placed there."""
    if node.tier != "onboard":
        return []
    return [{"key": ROBOT_TAINT, "value": node.robot or "", "effect": "NoSchedule"}]
