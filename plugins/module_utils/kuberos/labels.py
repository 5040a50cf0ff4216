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
TIER_OF_ROLE = {role: tier for tier, role in ROLES.items()}
LATENCY_ANNOTATION = "kuberos.io/latency-ms"  # a node that joined after deploy: its latency to the robots
# Kubernetes' own taints of a node whose kubelet stopped reporting (its node lifecycle controller sets them)
UNREACHABLE_TAINT = "node.kubernetes.io/unreachable"
NOT_READY_TAINT = "node.kubernetes.io/not-ready"

# The labels and annotations of the objects KubeROS renders (the manifests, the record, what the controller reads).
MANAGED_BY = "app.kubernetes.io/managed-by"
FIELD_MANAGER = "kuberos"  # who owns the fields KubeROS applies (server-side apply), unless a site names another
COMPONENT = "kuberos.io/component"
DEPLOYMENT = "kuberos.io/deployment"
MODULE = "kuberos.io/module"
INSTANCE = "kuberos.io/instance"
DISCOVERY_ID = "kuberos.io/discovery-id"
ROBOTS_ANNOTATION = "kuberos.io/robots"
REASON_ANNOTATION = "kuberos.io/placement-reason"
TIER_ANNOTATION = "kuberos.io/tier"
CLUSTER_ANNOTATION = "kuberos.io/cluster"
KWOK_NODE = "kwok.x-k8s.io/node"  # a node kwok simulates: it runs no container
GRAPH = "kuberos.io/graph"  # a deployment's last live graph check per robot (a ConfigMap the dashboard shows)
DEVELOPER_ANNOTATION = "kuberos.io/developer"  # a development deployment's instances: whose robots they run on
VERSION = "kuberos.io/version"  # a catalog module's resolved version
CATALOG_MODULE = "kuberos.io/catalog-module"
MAPS_ANNOTATION = "kuberos.io/parameter-maps"  # a hash of the maps a pod reads: a changed map restarts its readers


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


def node_from_cluster(obj: dict, default_latency_ms: float) -> Node | None:
    """The resource model's node of an edge or cloud Kubernetes Node that carries KubeROS's labels (the inverse of
    ``node_labels``), with its allocatable capacity; its latency from the ``kuberos.io/latency-ms`` annotation, else
    ``default_latency_ms``. None for a node without the labels, a robot's computer or unreadable capacity."""
    from . import quantities

    meta = obj.get("metadata") or {}
    found = meta.get("labels") or {}
    tier = TIER_OF_ROLE.get(found.get(ROLE, ""))
    name = found.get(HOSTNAME) or meta.get("name", "")
    if tier not in ("edge", "cloud") or not name:
        return None
    allocatable = (obj.get("status") or {}).get("allocatable") or {}
    try:
        latency = float((meta.get("annotations") or {}).get(LATENCY_ANNOTATION, default_latency_ms))
        return Node(
            name=name,
            tier=tier,
            cpu_millis=quantities.parse_cpu(allocatable.get("cpu", "0")),
            memory_bytes=quantities.parse_memory(allocatable.get("memory", "0")),
            gpu=int(allocatable.get("nvidia.com/gpu", 0)),
            pods=int(allocatable.get("pods", 110)),
            arch=found.get(ARCH, "amd64"),
            devices=frozenset(k[len(DEVICE_PREFIX) :] for k, v in found.items() if k.startswith(DEVICE_PREFIX) and v == "true"),
            fleets=tuple(
                sorted(
                    k[len(FLEET_ACCESS_PREFIX) :] for k, v in found.items() if k.startswith(FLEET_ACCESS_PREFIX) and v == "true"
                )
            ),
            shared=found.get(SHARED, "false") == "true",
            resource_group=found.get(RESOURCE_GROUP, ""),
            latency_ms=latency,
        )
    except (TypeError, ValueError):
        return None
