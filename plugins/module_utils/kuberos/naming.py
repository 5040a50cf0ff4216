"""Names of the Kubernetes objects KubeROS creates: valid DNS labels, stable and unique."""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass

_INVALID = re.compile(r"[^a-z0-9-]+")
DISCOVERY_PREFIX = "kuberos-discovery"
# KubeROS's own objects in a fleet namespace (discovery servers, bridges, deployment records, revisions, status,
# the catalog) are named kuberos-...; a deployment may not take that prefix, so that its objects never clash with them.
RESERVED_PREFIX = "kuberos"


def dns_label(*parts: str, max_len: int = 63) -> str:
    """Join parts into a DNS-1123 label.

    A name that is already valid and short enough is kept as it is; any other is cleaned,
    cut and given a hash suffix of the original, so that distinct inputs stay distinct.
    """
    raw = "-".join(str(p) for p in parts if p != "")
    name = re.sub(r"-{2,}", "-", _INVALID.sub("-", raw.lower())).strip("-") or "x"
    if name == raw and len(name) <= max_len:
        return name
    digest = hashlib.sha256(raw.encode()).hexdigest()[:8]
    return f"{name[: max_len - 9].rstrip('-')}-{digest}"


def robot_ros_name(robot: str) -> str:
    """A robot's name as a ROS 2 name token (``fetch-1`` -> ``fetch_1``): ROS names allow letters, digits and
    underscores and may not start with a digit (``7x`` -> ``r_7x``). ``{robot}`` in a bridged topic becomes this, the
    namespace the pick-and-place app gives each robot's topics too."""
    cleaned = "".join(c if c.isascii() and c.isalnum() else "_" for c in robot)
    return cleaned if cleaned and not cleaned[0].isdigit() else f"r_{cleaned}"


def fleet_namespace(fleet: str) -> str:
    return dns_label("kuberos", fleet)


def dedicated_instance_name(deployment: str, module: str, robot: str) -> str:
    # 52 characters leave room for the ReplicaSet and Pod suffixes Kubernetes appends.
    return dns_label(deployment, module, robot, max_len=52)


def shared_instance_name(deployment: str, module: str, index: int) -> str:
    return dns_label(deployment, module, f"shared-{index}", max_len=52)


def parameters_configmap_name(deployment: str, module: str) -> str:
    """The ConfigMap of a module's ROS parameters (one per module of a deployment)."""
    return dns_label(deployment, module, "params")


def parameter_map_name(deployment: str, parameter_map: str) -> str:
    """The ConfigMap of one of a deployment's parameter maps (``parameterMaps``; '.' and '_' become '-')."""
    return dns_label(deployment, "map", parameter_map)


def cyclonedds_configmap_name(deployment: str) -> str:
    """The ConfigMap of a Cyclone DDS deployment's peer lists (one configuration file per instance)."""
    return dns_label(deployment, "cyclonedds")


def metrics_policy_name(deployment: str, module: str) -> str:
    """The NetworkPolicy that opens a scaled module's gauge port to the namespaces that read it."""
    return dns_label(deployment, module, "metrics")


def robots_configmap_name(deployment: str, module: str) -> str:
    """The ConfigMap that tells a scaled shared module's instances which robots each serves (one per module)."""
    return dns_label(deployment, module, "robots")


def reserved_name_problem(deployment: str) -> str | None:
    """Why ``deployment`` may not be a deployment's name (it would share KubeROS's own names), or None."""
    if deployment == RESERVED_PREFIX or deployment.startswith(RESERVED_PREFIX + "-"):
        return (
            f"'{deployment}' starts with '{RESERVED_PREFIX}', the prefix of KubeROS's own objects in a fleet namespace "
            "(discovery servers, bridges, records); expected another name"
        )
    return None


@dataclass(frozen=True)
class PlannedName:
    """The name one object of a module of a deployment will get, and what it is for."""

    kind: str  # Deployment or ConfigMap
    namespace: str
    name: str
    deployment: str
    module: str
    what: str  # "the instance of robot fetch-1", "shared instance 0", "the ROS parameters"


def module_object_names(
    fleet: str, deployment: str, module: str, shared: bool, robots, parameters: bool, scaled: bool = False
) -> list[PlannedName]:
    """The names a module's objects will get in its fleet's namespace: a Deployment per robot (dedicated) or up to
    one per robot (shared, numbered from 0), its parameter ConfigMap when it has ``rosParameters`` and its robots
    ConfigMap when it scales. With
    ``robots`` None (all robots of the fleet, not known here) one symbolic name ``<deployment>-<module>-<robot>``
    stands for the instances: equal for two modules exactly when their instances would clash for every robot."""
    namespace = fleet_namespace(fleet)
    names = []
    if robots is None:  # the fleet's robots, not known here: one symbolic name stands for them all
        stem = dns_label(deployment, module)
        name, what = (f"{stem}-shared-<n>", "its shared instances") if shared else (f"{stem}-<robot>", "each robot's instance")
        names.append(PlannedName("Deployment", namespace, name, deployment, module, what))
        robots = ()
    for index, robot in enumerate(robots):
        if shared:
            name, what = shared_instance_name(deployment, module, index), f"shared instance {index}"
        else:
            name, what = dedicated_instance_name(deployment, module, robot), f"the instance of robot {robot}"
        names.append(PlannedName("Deployment", namespace, name, deployment, module, what))
    if parameters:
        names.append(
            PlannedName(
                "ConfigMap", namespace, parameters_configmap_name(deployment, module), deployment, module, "ROS parameters"
            )
        )
    if scaled:
        names.append(
            PlannedName("ConfigMap", namespace, robots_configmap_name(deployment, module), deployment, module, "robots served")
        )
    return names


def discovery_server_name(server_id: int) -> str:
    return f"{DISCOVERY_PREFIX}-{server_id}"


ROBOT_DISCOVERY_PREFIX = "kuberos-robot-discovery"


def robot_discovery_server_name(deployment: str, robot: str) -> str:
    """The discovery server of one deployment on one robot's computer (a Deployment, ``kuberos-`` like the fleet's)."""
    return dns_label(ROBOT_DISCOVERY_PREFIX, deployment, robot, max_len=52)


def robot_discovery_service_name(deployment: str) -> str:
    """The one Service of a deployment's robot discovery servers: node-local (``internalTrafficPolicy: Local``), so its
    address reaches, on each robot computer, the server that runs there."""
    return dns_label(ROBOT_DISCOVERY_PREFIX, deployment)


def discovery_server_address(namespace: str, server_id: int, port: int, cluster_domain: str = "cluster.local") -> str:
    """The server's cluster DNS name and port: for people and tools; modules name it by its Service's address."""
    return f"{discovery_server_name(server_id)}.{namespace}.svc.{cluster_domain}:{port}"


def service_host_variable(service: str) -> str:
    """The variable the kubelet sets in every container of a Service's namespace to the Service's cluster IP
    (Kubernetes' service links: ``kuberos-discovery-0`` -> ``KUBEROS_DISCOVERY_0_SERVICE_HOST``)."""
    return service.upper().replace("-", "_") + "_SERVICE_HOST"


def bridge_server_name(cluster: str) -> str:
    """The main cluster's bridge server to a third-party cluster (Deployment and Service, in the fleet namespace)."""
    return dns_label("kuberos-bridge", cluster)


BRIDGE_CLIENT = "kuberos-bridge-client"
BRIDGE_PORT = 50051
BRIDGE_NODE_PORT = 30711


def object_key(obj: dict) -> tuple[str, str, str]:
    """(kind, namespace, name): one object of a cluster ('' for a cluster-scoped one's namespace)."""
    meta = obj["metadata"]
    return obj["kind"], meta.get("namespace") or "", meta["name"]


def object_label(obj: dict) -> str:
    kind, namespace, name = object_key(obj)
    return f"{kind} {namespace}/{name}" if namespace else f"{kind} {name}"
