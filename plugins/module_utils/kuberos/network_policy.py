"""The NetworkPolicies that keep each fleet to itself.

In every fleet namespace (this cluster's and a third-party cluster's), ingress is denied by default and allowed
from the pods of the same namespace: a fleet's discovery servers and modules take traffic only from the fleet's own
pods, whatever their node or tier. On top of that, each opening is named:

- a bridge server takes its gRPC port from anywhere: its partner reaches it through a NodePort, whose source address
  kube-proxy replaces, and mutual TLS (the fleet's own CA) is what admits only the partner;
- the metrics ports (a bridge's, a scaled module's gauge that the controller reads) are open to the namespaces of
  ``metrics_namespaces`` (the controller's, by default: ``rosdeployment_metrics_namespaces``).

Traffic from a pod's own node (the kubelet's probes) is always allowed (NetworkPolicy semantics); egress is not
restricted (modules reach their discovery servers, DNS, registries and their bridge's partner). The policies are
enforced where the CNI enforces NetworkPolicy (Calico or Cilium on a site); elsewhere they are kept and change nothing.

Pure: plain data in, plain data out.
"""

from __future__ import annotations

API_VERSION = "networking.k8s.io/v1"
DEFAULT_DENY = "kuberos-default-deny"
SAME_FLEET = "kuberos-same-fleet"
COMPONENT_VALUE = "network-policy"  # the component label of the fleet's own policies (removed with its last deployment)
NAMESPACE_NAME = "kubernetes.io/metadata.name"  # every namespace carries its name as this label
DEFAULT_METRICS_NAMESPACES = ("kuberos-system",)


def _policy(name: str, namespace: str, labels: dict, pod_selector: dict, ingress: list[dict]) -> dict:
    return {
        "apiVersion": API_VERSION,
        "kind": "NetworkPolicy",
        "metadata": {"name": name, "namespace": namespace, "labels": dict(labels)},
        "spec": {"podSelector": pod_selector, "policyTypes": ["Ingress"], "ingress": ingress},
    }


def fleet_policies(namespace: str, labels: dict) -> list[dict]:
    """Default deny, and every pod of the namespace open to the namespace's pods (on every port and protocol)."""
    return [
        _policy(DEFAULT_DENY, namespace, labels, {}, []),
        _policy(SAME_FLEET, namespace, labels, {}, [{"from": [{"podSelector": {}}]}]),
    ]


def _from_namespaces(namespaces) -> list[dict]:
    return [
        {"namespaceSelector": {"matchExpressions": [{"key": NAMESPACE_NAME, "operator": "In", "values": sorted(namespaces)}]}}
    ]


def metrics_policy(name: str, namespace: str, labels: dict, pod_selector: dict, ports, namespaces) -> dict:
    """``ports`` (TCP) of the pods ``pod_selector`` picks, open to the pods of ``namespaces``."""
    return _policy(
        name,
        namespace,
        labels,
        pod_selector,
        [{"from": _from_namespaces(namespaces), "ports": [{"protocol": "TCP", "port": p} for p in sorted(set(ports))]}],
    )


def bridge_policy(name: str, namespace: str, labels: dict, pod_selector: dict, grpc_port: int, metrics_port: int, namespaces):
    """A bridge server: its gRPC port open to any address (mutual TLS admits only its partner), its metrics port to
    the pods of ``namespaces``."""
    return _policy(
        name,
        namespace,
        labels,
        pod_selector,
        [
            {"ports": [{"protocol": "TCP", "port": grpc_port}]},
            {"from": _from_namespaces(namespaces), "ports": [{"protocol": "TCP", "port": metrics_port}]},
        ],
    )
