"""Prometheus Operator objects for the in-cluster KubeROS controller: a thin adapter over
module_utils/kuberos_controller/monitoring.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: controller_monitoring
short_description: ServiceMonitor, PodMonitor and PrometheusRule of the in-cluster KubeROS controller
version_added: 0.2.0
description:
  - Returns the Prometheus Operator (C(monitoring.coreos.com/v1)) objects that scrape the in-cluster controller's
    C(/metrics) and load the collection's alerting rules, each only when asked for.
  - With O(service_monitor) or O(pod_monitor), the ClusterRole C(kuberos-metrics-reader) (C(get) on the
    non-resource URL C(/metrics)); the controller's C(/metrics) wants a Kubernetes bearer token allowed that.
  - The ServiceMonitor selects the Service of the controller (label C(app.kubernetes.io/name=kuberos-controller)) in
    O(namespace), port C(http), path C(/metrics), every 15 s, and sends the Prometheus pod's ServiceAccount token
    (C(bearerTokenFile)); bind that ServiceAccount to C(kuberos-metrics-reader) with a ClusterRoleBinding.
  - The PodMonitor selects the controller's pods (same label), port C(http); it sends the token of the ServiceAccount
    C(kuberos-metrics-scraper) (returned with its token Secret and its binding to the reader), because PodMonitors
    cannot read a file of the Prometheus pod.
  - The PrometheusRule C(kuberos) carries the groups of the rule file unchanged.
options:
  _input:
    description:
      - The parsed Prometheus rule file, a mapping with C(groups); the role reads
        C(roles/controller/files/prometheus/kuberos-rules.yml).
    type: dict
    required: true
  namespace:
    description: Namespace of the controller, and of the objects.
    type: str
    default: kuberos-system
  service_monitor:
    description: Return a ServiceMonitor (and the reader ClusterRole).
    type: bool
    default: false
  pod_monitor:
    description: Return a PodMonitor (and the reader ClusterRole, the scraper's ServiceAccount, token Secret and binding).
    type: bool
    default: false
  prometheus_rule:
    description: Return a PrometheusRule with the rule file's groups.
    type: bool
    default: false
  labels:
    description: Labels added to every object, for a Prometheus that selects monitors and rules by label (e.g. C(release)).
    type: dict
    default: {}
  tls_secret:
    description:
      - The C(kubernetes.io/tls) Secret the controller serves HTTPS with (the role's C(controller_dashboard_tls_secret));
        the monitors then scrape over HTTPS and verify the certificate with the Secret's C(ca.crt). Empty is HTTP.
    type: str
    default: ""
  robot_offline_after:
    description:
      - How long a robot must be offline before the alert C(KubeROSRobotOffline) fires (a Prometheus duration, the
        alert's C(for)). Robots drop off the network many times a day; their modules stay and run on them meanwhile.
    type: str
    default: 10m
"""

EXAMPLES = r"""
- name: Apply the controller's ServiceMonitor and PrometheusRule
  kubernetes.core.k8s:
    definition: >-
      {{ lookup('ansible.builtin.file', 'prometheus/kuberos-rules.yml') | from_yaml
         | kuberos.platform.controller_monitoring(service_monitor=true, prometheus_rule=true,
                                                  labels={'release': 'kube-prometheus-stack'}) }}
    apply: true
    server_side_apply:
      field_manager: kuberos
"""

RETURN = r"""
_value:
  description: Kubernetes objects, in apply order; none when nothing is asked for.
  type: list
  elements: dict
"""

from ansible.module_utils.parsing.convert_bool import boolean

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.monitoring import monitoring_objects
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def controller_monitoring(
    rules,
    namespace="kuberos-system",
    service_monitor=False,
    pod_monitor=False,
    prometheus_rule=False,
    labels=None,
    tls_secret="",
    robot_offline_after="10m",
):
    if isinstance(labels, dict):  # label values such as 1 or true become the strings Kubernetes wants
        labels = {str(k): str(v) for k, v in labels.items()}
    return monitoring_objects(
        str(namespace),
        rules,
        boolean(service_monitor, strict=True),
        boolean(pod_monitor, strict=True),
        boolean(prometheus_rule, strict=True),
        labels,
        str(tls_secret or ""),
        robot_offline_after,
    )


class FilterModule:
    def filters(self):
        return {"controller_monitoring": controller_monitoring}
