"""Names of the Kubernetes objects KubeROS creates: valid DNS labels, stable and unique."""

from __future__ import annotations

import hashlib
import re

_INVALID = re.compile(r"[^a-z0-9-]+")
DISCOVERY_PREFIX = "kuberos-discovery"


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


def fleet_namespace(fleet: str) -> str:
    return dns_label("kuberos", fleet)


def dedicated_instance_name(deployment: str, module: str, robot: str) -> str:
    # 52 characters leave room for the ReplicaSet and Pod suffixes Kubernetes appends.
    return dns_label(deployment, module, robot, max_len=52)


def shared_instance_name(deployment: str, module: str, index: int) -> str:
    return dns_label(deployment, module, f"shared-{index}", max_len=52)


def discovery_server_name(server_id: int) -> str:
    return f"{DISCOVERY_PREFIX}-{server_id}"


def discovery_server_address(namespace: str, server_id: int, port: int, cluster_domain: str = "cluster.local") -> str:
    return f"{discovery_server_name(server_id)}.{namespace}.svc.{cluster_domain}:{port}"


def bridge_server_name(cluster: str) -> str:
    """The main cluster's bridge server to a third-party cluster (Deployment and Service, in the fleet namespace)."""
    return dns_label("kuberos-bridge", cluster)


BRIDGE_CLIENT = "kuberos-bridge-client"
BRIDGE_PORT = 50051
BRIDGE_NODE_PORT = 30711
