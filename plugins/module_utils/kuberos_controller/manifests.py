"""The objects that run the KubeROS controller inside a cluster, with least-privilege RBAC.

Read access is cluster-wide because the controller finds records, pods and nodes in every fleet
namespace: nodes, pods, Deployments and ConfigMaps may be listed and watched. Write access is granted
only in the fleet namespaces, by a RoleBinding each: patch Deployments (re-pin a module), delete pods
(left on a dead node), get/create/patch ConfigMaps (the record and the status) and create Events.
In its own namespace it may get, create and update Leases: the replicas elect their leader on the Lease
``kuberos-controller`` (the controller's ``leader_election``). Nothing else: no Secrets, no node changes,
no creating Deployments or pods, nothing in other namespaces.

Every replica serves the read-only dashboard and ``/metrics`` on port 8611 (named ``http``), behind the Service
``kuberos-controller``. There every request needs a Kubernetes bearer token: the controller asks the API
server (TokenReview, SubjectAccessReview) whether it may ``get`` ``/kuberos/dashboard`` (or ``/metrics``). The
ClusterRole ``kuberos-dashboard-viewer`` grants both; it is bound to the ServiceAccount of the same name, whose
token a person gets with ``kubectl create token kuberos-dashboard-viewer -n kuberos-system``.

Several replicas run (two by default) on edge servers (nodes labelled ``kuberos.io/role=edge``: on site, beside
the robots and the control plane, never on a robot or a cloud VM behind a long link), spread over them where
possible, each knowing its pod's name (its identity in the Lease) and its node (a replica whose node is NotReady
does not lead). A
PodDisruptionBudget keeps one replica through voluntary evictions such as a node drain.
"""

from __future__ import annotations

import copy

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import naming, pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import MANAGED_BY

NAME = "kuberos-controller"
READ_ROLE = "kuberos-controller-read"
FLEET_ROLE = "kuberos-controller-fleet"
LEASE_ROLE = "kuberos-controller-lease"
ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"

READ_RULES = [
    {"apiGroups": [""], "resources": ["nodes", "pods", "configmaps", "events"], "verbs": ["list", "watch"]},
    {"apiGroups": ["apps"], "resources": ["deployments"], "verbs": ["list", "watch"]},
    {"apiGroups": ["metrics.k8s.io"], "resources": ["pods"], "verbs": ["list"]},  # cpu scaling (docs/scaling.md)
]
# The dashboard and /metrics ask the API server who a bearer token is and whether it may read them (reviews are
# answered, not stored). Part of the read ClusterRole.
REVIEW_RULES = [
    {"apiGroups": ["authentication.k8s.io"], "resources": ["tokenreviews"], "verbs": ["create"]},
    {"apiGroups": ["authorization.k8s.io"], "resources": ["subjectaccessreviews"], "verbs": ["create"]},
]
VIEWER_ROLE = "kuberos-dashboard-viewer"
VIEWER_RULES = [{"nonResourceURLs": ["/kuberos/dashboard", "/metrics"], "verbs": ["get"]}]
DASHBOARD_PORT = 8611
PODS_SERVICE = f"{NAME}-pods"  # the headless Service: one DNS address per Ready replica
TLS_DIR = "/etc/kuberos/dashboard-tls"
FLEET_RULES = [
    {"apiGroups": [""], "resources": ["configmaps"], "verbs": ["get", "create", "patch"]},
    # delete: a pod that fails on its node; create and get: the live graph check's pod (--graph-every)
    {"apiGroups": [""], "resources": ["pods"], "verbs": ["create", "get", "delete"]},
    # the dashboard's last lines of each instance; the graph check's verdict
    {"apiGroups": [""], "resources": ["pods/log"], "verbs": ["get"]},
    {"apiGroups": [""], "resources": ["events"], "verbs": ["create"]},
    # patch: re-pinning; create and delete: instances added and removed by scaling (docs/scaling.md)
    {"apiGroups": ["apps"], "resources": ["deployments"], "verbs": ["create", "patch", "delete"]},
]
LEASE_RULES = [{"apiGroups": ["coordination.k8s.io"], "resources": ["leases"], "verbs": ["get", "create", "update"]}]


def controller_objects(
    namespace: str, image: str, fleets: list[str], args: list[str], replicas: int = 2, tls_secret: str = ""
) -> list[dict]:
    """Namespace, ServiceAccount, the two ClusterRoles, their bindings (one per fleet), the Lease Role and its
    binding, the dashboard viewer's ServiceAccount, ClusterRole and binding, the Service and its headless twin
    ``kuberos-controller-pods``, the Deployment and, with
    more than one replica, its PodDisruptionBudget. ``tls_secret``: a ``kubernetes.io/tls`` Secret in ``namespace``
    (``tls.crt``, ``tls.key``) mounted into the pods, and the dashboard serves HTTPS with it."""
    tls_args = ["--dashboard-tls-cert", f"{TLS_DIR}/tls.crt", "--dashboard-tls-key", f"{TLS_DIR}/tls.key"] if tls_secret else []
    labels = {MANAGED_BY: "kuberos", "app.kubernetes.io/name": NAME}
    ports = [{"name": "http", "port": DASHBOARD_PORT, "targetPort": "http", "protocol": "TCP"}]  # both Services
    subject = {"kind": "ServiceAccount", "name": NAME, "namespace": namespace}
    objects = [
        {
            "apiVersion": "v1",
            "kind": "Namespace",
            "metadata": {"name": namespace, "labels": {**labels, **pod_security.namespace_labels("restricted")}},
        },
        {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": {"name": NAME, "namespace": namespace, "labels": labels}},
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRole",
            "metadata": {"name": READ_ROLE, "labels": labels},
            "rules": READ_RULES + REVIEW_RULES,
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRoleBinding",
            "metadata": {"name": READ_ROLE, "labels": labels},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": READ_ROLE},
            "subjects": [subject],
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRole",
            "metadata": {"name": FLEET_ROLE, "labels": labels},
            "rules": FLEET_RULES,
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "Role",
            "metadata": {"name": LEASE_ROLE, "namespace": namespace, "labels": labels},
            "rules": LEASE_RULES,
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "RoleBinding",
            "metadata": {"name": LEASE_ROLE, "namespace": namespace, "labels": labels},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "Role", "name": LEASE_ROLE},
            "subjects": [subject],
        },
    ]
    viewer = {"kind": "ServiceAccount", "name": VIEWER_ROLE, "namespace": namespace}
    objects += [
        {
            "apiVersion": "v1",
            "kind": "ServiceAccount",
            "metadata": {"name": VIEWER_ROLE, "namespace": namespace, "labels": labels},
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRole",
            "metadata": {"name": VIEWER_ROLE, "labels": labels},
            "rules": VIEWER_RULES,
        },
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRoleBinding",
            "metadata": {"name": VIEWER_ROLE, "labels": labels},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": VIEWER_ROLE},
            "subjects": [viewer],
        },
        {
            "apiVersion": "v1",
            "kind": "Service",
            "metadata": {"name": NAME, "namespace": namespace, "labels": labels},
            "spec": {
                "selector": {"app.kubernetes.io/name": NAME},
                "ports": copy.deepcopy(ports),
            },
        },
        {
            # Headless: DNS lists each Ready replica's address, for a Prometheus that discovers targets by DNS
            # (monitoring.scrape_config). Labelled apart from the Service above, which the ServiceMonitor selects.
            "apiVersion": "v1",
            "kind": "Service",
            "metadata": {
                "name": PODS_SERVICE,
                "namespace": namespace,
                "labels": {MANAGED_BY: "kuberos", "app.kubernetes.io/name": PODS_SERVICE},
            },
            "spec": {
                "clusterIP": "None",
                "selector": {"app.kubernetes.io/name": NAME},
                "ports": copy.deepcopy(ports),
            },
        },
    ]
    for fleet in sorted(set(fleets)):
        # The RoleBinding needs its namespace; deploy creates it too (both apply, each with its own field manager).
        objects.append({"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": naming.fleet_namespace(fleet)}})
        objects.append(
            {
                "apiVersion": "rbac.authorization.k8s.io/v1",
                "kind": "RoleBinding",
                "metadata": {"name": NAME, "namespace": naming.fleet_namespace(fleet), "labels": labels},
                "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": FLEET_ROLE},
                "subjects": [subject],
            }
        )
    objects.append(
        {
            "apiVersion": "apps/v1",
            "kind": "Deployment",
            "metadata": {"name": NAME, "namespace": namespace, "labels": labels},
            "spec": {
                "replicas": replicas,  # every replica watches; the holder of the Lease acts
                "selector": {"matchLabels": {"app.kubernetes.io/name": NAME}},
                "template": {
                    "metadata": {"labels": labels},
                    "spec": {
                        "serviceAccountName": NAME,
                        "securityContext": pod_security.pod_security_context(),
                        **({"volumes": [{"name": "dashboard-tls", "secret": {"secretName": tls_secret}}]} if tls_secret else {}),
                        "affinity": {
                            "nodeAffinity": {
                                "requiredDuringSchedulingIgnoredDuringExecution": {
                                    "nodeSelectorTerms": [
                                        {"matchExpressions": [{"key": node_labels.ROLE, "operator": "In", "values": ["edge"]}]}
                                    ]
                                }
                            },
                            "podAntiAffinity": {
                                "preferredDuringSchedulingIgnoredDuringExecution": [
                                    {
                                        "weight": 100,
                                        "podAffinityTerm": {
                                            "topologyKey": "kubernetes.io/hostname",
                                            "labelSelector": {"matchLabels": {"app.kubernetes.io/name": NAME}},
                                        },
                                    }
                                ]
                            },
                        },
                        "containers": [
                            {
                                "name": "controller",
                                "image": image,
                                "args": [
                                    "python",
                                    "-m",
                                    ENTRY,
                                    "--lease-namespace",
                                    namespace,
                                    "--dashboard-host",
                                    "0.0.0.0",
                                    "--dashboard-auth",
                                    "kubernetes",
                                    *tls_args,
                                    *args,
                                ],
                                "ports": [{"name": "http", "containerPort": DASHBOARD_PORT, "protocol": "TCP"}],
                                "readinessProbe": {
                                    "httpGet": {"path": "/healthz", "port": "http", "scheme": "HTTPS" if tls_secret else "HTTP"},
                                    "periodSeconds": 10,
                                },
                                **(
                                    {"volumeMounts": [{"name": "dashboard-tls", "mountPath": TLS_DIR, "readOnly": True}]}
                                    if tls_secret
                                    else {}
                                ),
                                "env": [
                                    {"name": "POD_NAME", "valueFrom": {"fieldRef": {"fieldPath": "metadata.name"}}},
                                    {"name": "KUBEROS_NODE_NAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}},
                                ],
                                "resources": {"requests": {"cpu": "100m", "memory": "128Mi"}, "limits": {"memory": "512Mi"}},
                                "securityContext": {
                                    "runAsNonRoot": True,
                                    "runAsUser": 65532,
                                    "allowPrivilegeEscalation": False,
                                    "readOnlyRootFilesystem": True,
                                    "capabilities": {"drop": ["ALL"]},
                                },
                            }
                        ],
                    },
                },
            },
        }
    )
    # Its pods take connections on the dashboard's port only (the dashboard and /metrics authenticate every request);
    # other pods of the namespace are the site's and keep their own policies.
    objects.append(
        {
            "apiVersion": "networking.k8s.io/v1",
            "kind": "NetworkPolicy",
            "metadata": {"name": NAME, "namespace": namespace, "labels": labels},
            "spec": {
                "podSelector": {"matchLabels": {"app.kubernetes.io/name": NAME}},
                "policyTypes": ["Ingress"],
                "ingress": [{"ports": [{"protocol": "TCP", "port": DASHBOARD_PORT}]}],
            },
        }
    )
    if replicas > 1:
        objects.append(
            {
                "apiVersion": "policy/v1",
                "kind": "PodDisruptionBudget",
                "metadata": {"name": NAME, "namespace": namespace, "labels": labels},
                "spec": {"minAvailable": 1, "selector": {"matchLabels": {"app.kubernetes.io/name": NAME}}},
            }
        )
    return objects
