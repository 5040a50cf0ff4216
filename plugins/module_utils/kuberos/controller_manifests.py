"""The objects that run the KubeROS controller inside a cluster, with least-privilege RBAC.

Read access is cluster-wide because the controller finds records, pods and nodes in every fleet
namespace: nodes, pods, Deployments and ConfigMaps may be listed and watched. Write access is granted
only in the fleet namespaces, by a RoleBinding each: patch Deployments (re-pin a module), delete pods
(left on a dead node), get/create/patch ConfigMaps (the record and the status) and create Events.
Nothing else: no Secrets, no node changes, no creating Deployments or pods, nothing in other namespaces.
"""

from __future__ import annotations

from . import naming
from .manifests import MANAGED_BY

NAME = "kuberos-controller"
READ_ROLE = "kuberos-controller-read"
FLEET_ROLE = "kuberos-controller-fleet"
ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"

READ_RULES = [
    {"apiGroups": [""], "resources": ["nodes", "pods", "configmaps"], "verbs": ["list", "watch"]},
    {"apiGroups": ["apps"], "resources": ["deployments"], "verbs": ["list", "watch"]},
]
FLEET_RULES = [
    {"apiGroups": [""], "resources": ["configmaps"], "verbs": ["get", "create", "patch"]},
    {"apiGroups": [""], "resources": ["pods"], "verbs": ["delete"]},
    {"apiGroups": [""], "resources": ["events"], "verbs": ["create"]},
    {"apiGroups": ["apps"], "resources": ["deployments"], "verbs": ["patch"]},
]


def controller_objects(namespace: str, image: str, fleets: list[str], args: list[str]) -> list[dict]:
    """Namespace, ServiceAccount, the two ClusterRoles, their bindings (one per fleet) and the Deployment."""
    labels = {MANAGED_BY: "kuberos", "app.kubernetes.io/name": NAME}
    subject = {"kind": "ServiceAccount", "name": NAME, "namespace": namespace}
    objects = [
        {"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": namespace, "labels": labels}},
        {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": {"name": NAME, "namespace": namespace, "labels": labels}},
        {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRole",
            "metadata": {"name": READ_ROLE, "labels": labels},
            "rules": READ_RULES,
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
                "replicas": 1,  # one controller: a second one would decide the same moves twice
                "strategy": {"type": "Recreate"},
                "selector": {"matchLabels": {"app.kubernetes.io/name": NAME}},
                "template": {
                    "metadata": {"labels": labels},
                    "spec": {
                        "serviceAccountName": NAME,
                        "containers": [
                            {
                                "name": "controller",
                                "image": image,
                                "args": ["python", "-m", ENTRY, *args],
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
    return objects
