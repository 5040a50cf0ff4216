"""The in-cluster KubeROS controller's objects: a thin adapter over module_utils/kuberos_controller/manifests.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: controller_manifests
short_description: ServiceAccount, least-privilege RBAC and Deployment of the in-cluster KubeROS controller
version_added: 0.2.0
description:
  - Returns the Namespace, ServiceAccount, a ClusterRole to list and watch nodes, pods, Deployments and ConfigMaps,
    a ClusterRole bound in each fleet namespace only (patch Deployments, delete pods, get/create/patch ConfigMaps,
    create Events), their bindings, a Role to get, create and update Leases in the controller's namespace (leader
    election) and its binding, the dashboard viewer's ServiceAccount, ClusterRole and binding, the Service of the
    dashboard and C(/metrics), a headless Service C(kuberos-controller-pods) listing each Ready replica by DNS (for a
    Prometheus that discovers its targets by DNS), the controller's Deployment and, with more than one replica, a
    PodDisruptionBudget.
options:
  _input:
    description: Names of the fleets whose namespaces the controller may act in.
    type: list
    elements: str
    required: true
  namespace:
    description: Namespace of the controller.
    type: str
    default: kuberos-system
  image:
    description: Container image of the controller.
    type: str
    required: true
  args:
    description: Command-line options of the controller (e.g. C(--grace 5)).
    type: list
    elements: str
    default: []
  replicas:
    description:
      - How many controller replicas run; the holder of the Lease C(kuberos-controller) in O(namespace) acts.
      - With more than one, a PodDisruptionBudget keeps one through voluntary evictions.
    type: int
    default: 2
  tls_secret:
    description:
      - A C(kubernetes.io/tls) Secret in O(namespace) (C(tls.crt), C(tls.key)); the dashboard and C(/metrics) are then
        served over HTTPS with it. Empty serves plain HTTP (reach it through C(kubectl port-forward)).
    type: str
    default: ""
"""

EXAMPLES = r"""
- name: Apply the in-cluster controller
  kubernetes.core.k8s:
    definition: "{{ ['test-fleet'] | kuberos.platform.controller_manifests(image='ghcr.io/kuberos/controller:0.2.0') }}"
    apply: true
    server_side_apply:
      field_manager: kuberos
"""

RETURN = r"""
_value:
  description: Kubernetes objects, in apply order.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import controller_objects
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def controller_manifests(fleets, image, namespace="kuberos-system", args=(), replicas=2, tls_secret=""):
    return controller_objects(
        str(namespace), str(image), [str(f) for f in fleets], [str(a) for a in args], int(replicas), str(tls_secret or "")
    )


class FilterModule:
    def filters(self):
        return {"controller_manifests": controller_manifests}
