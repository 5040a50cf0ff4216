"""Prometheus Operator objects for the in-cluster KubeROS controller: what scrapes it and the collection's rules.

The controller serves ``/metrics`` on its port ``http``, and in the cluster it asks for a Kubernetes bearer token
that may ``get`` the non-resource URL ``/metrics`` (checked with a TokenReview and a SubjectAccessReview). The
ClusterRole ``kuberos-metrics-reader`` grants exactly that; whoever scrapes is bound to it:

- the ServiceMonitor sends the token of the Prometheus pod's own ServiceAccount (``bearerTokenFile``): the user
  binds that ServiceAccount to ``kuberos-metrics-reader`` (a ClusterRoleBinding; docs/monitoring.md);
- the PodMonitor cannot read a file of the Prometheus pod (the Prometheus Operator leaves ``bearerTokenFile`` out
  of PodMonitors on purpose), so it sends the token of a ServiceAccount of its own, ``kuberos-metrics-scraper``,
  from a ``kubernetes.io/service-account-token`` Secret beside it; that ServiceAccount is bound to the reader here.

The PrometheusRule carries the groups of ``roles/controller/files/prometheus/kuberos-rules.yml`` unchanged.
Endpoints keep the metrics' own labels (``honorLabels``): the controller's ``namespace`` label names a fleet's
namespace, not the controller's, and would otherwise be renamed ``exported_namespace`` by the scrape.
"""

from __future__ import annotations

import copy
import re

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import (
    DASHBOARD_PORT,
    NAME,
    PODS_SERVICE,
)

API_VERSION = "monitoring.coreos.com/v1"
READER_ROLE = "kuberos-metrics-reader"
SCRAPER = "kuberos-metrics-scraper"
SCRAPER_TOKEN = "kuberos-metrics-scraper-token"
RULES_NAME = "kuberos"
PORT = "http"
PATH = "/metrics"
INTERVAL = "15s"
TOKEN_FILE = "/var/run/secrets/kubernetes.io/serviceaccount/token"
READER_RULES = [{"nonResourceURLs": [PATH], "verbs": ["get"]}]
SELECTOR = {"matchLabels": {"app.kubernetes.io/name": NAME}}
ROBOT_OFFLINE_ALERT = "KubeROSRobotOffline"
ROBOT_OFFLINE_FOR = "10m"  # the rule file's own
DURATION = re.compile(r"^([0-9]+(ms|s|m|h|d|w|y))+\Z")  # a Prometheus duration


def _checked_labels(labels) -> dict[str, str]:
    if labels is None:
        return {}
    if not isinstance(labels, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in labels.items()):
        raise SpecError([Problem("controller_monitoring", "labels", f"expected a mapping of strings, got {describe(labels)}")])
    return dict(labels)


def _checked_groups(rules) -> list:
    groups = rules.get("groups") if isinstance(rules, dict) else None
    if (
        not isinstance(groups, list)
        or not groups
        or not all(isinstance(g, dict) and "name" in g and "rules" in g for g in groups)
    ):
        raise SpecError(
            [Problem("controller_monitoring", "groups", "expected a Prometheus rule file: groups, each with a name and rules")]
        )
    return copy.deepcopy(groups)


def _robot_offline_after(groups: list, after: str) -> list:
    """The rules with KubeROSRobotOffline firing after ``after`` (its ``for``, and the same duration in its text)."""
    if not isinstance(after, str) or not DURATION.match(after):
        raise SpecError(
            [
                Problem(
                    "controller_monitoring",
                    "robot_offline_after",
                    f"expected a Prometheus duration such as 10m or 1h30m, got {describe(after)}",
                )
            ]
        )
    for group in groups:
        for rule in group.get("rules") or []:
            if isinstance(rule, dict) and rule.get("alert") == ROBOT_OFFLINE_ALERT:
                rule["for"] = after
                annotations = rule.get("annotations") or {}
                if isinstance(annotations.get("description"), str):
                    annotations["description"] = annotations["description"].replace(
                        f"for {ROBOT_OFFLINE_FOR} or more", f"for {after} or more"
                    )
    return groups


def _service_name(namespace: str) -> str:
    """The name the controller's certificate is checked for: its Service's."""
    return f"{NAME}.{namespace}.svc"


def scrape_config(namespace: str, ca_file: str = "", discovery: str = "kubernetes", domain: str = "cluster.local") -> dict:
    """The scrape job of a Prometheus without the Operator, what the ServiceMonitor stands for: every replica of the
    in-cluster controller in ``namespace``, port ``http`` (8611), path ``/metrics``, every 15 s, the metrics' own
    labels kept, with the token of the Prometheus pod's ServiceAccount (bound to ``kuberos-metrics-reader``).
    ``discovery``: ``kubernetes`` finds the replicas as the endpoints of the Service ``kuberos-controller``
    (``kubernetes_sd_configs``, role ``endpoints``; each target labelled with its ``pod``); ``dns`` as the addresses
    of the headless Service ``kuberos-controller-pods`` (``dns_sd_configs``: for a Prometheus built without
    Kubernetes discovery, such as Debian's package). ``ca_file``: the controller serves HTTPS
    (``controller_dashboard_tls_secret``); the job checks its certificate against that file (the Secret's ``ca.crt``
    mounted in the Prometheus pod) for the Service's name."""
    job = {
        "job_name": NAME,
        "scrape_interval": INTERVAL,
        "metrics_path": PATH,
        "honor_labels": True,
        "authorization": {"type": "Bearer", "credentials_file": TOKEN_FILE},
    }
    if discovery == "kubernetes":
        job["kubernetes_sd_configs"] = [{"role": "endpoints", "namespaces": {"names": [namespace]}}]
        job["relabel_configs"] = [
            {"source_labels": ["__meta_kubernetes_service_label_app_kubernetes_io_name"], "regex": NAME, "action": "keep"},
            {"source_labels": ["__meta_kubernetes_endpoint_port_name"], "regex": PORT, "action": "keep"},
            {"source_labels": ["__meta_kubernetes_pod_name"], "target_label": "pod"},
        ]
    elif discovery == "dns":
        name = f"{PODS_SERVICE}.{namespace}.svc.{domain}"
        job["dns_sd_configs"] = [{"names": [name], "type": "A", "port": DASHBOARD_PORT, "refresh_interval": "15s"}]
    else:
        raise ValueError(f"discovery {discovery!r}: expected kubernetes or dns")
    if ca_file:
        job["scheme"] = "https"
        job["tls_config"] = {"ca_file": ca_file, "server_name": _service_name(namespace)}
    return job


def monitoring_objects(
    namespace: str,
    rules: dict,
    service_monitor: bool,
    pod_monitor: bool,
    prometheus_rule: bool,
    labels: dict | None = None,
    tls_secret: str = "",
    robot_offline_after: str = ROBOT_OFFLINE_FOR,
) -> list[dict]:
    """The objects, in apply order: with a ServiceMonitor or a PodMonitor the ClusterRole ``kuberos-metrics-reader``;
    with a PodMonitor its ServiceAccount, token Secret and binding; the ServiceMonitor, the PodMonitor and the
    PrometheusRule (``rules``: the parsed rule file, ``{"groups": [...]}``). ``labels`` are added to every object's
    labels, for a Prometheus that selects its monitors and rules by label (kube-prometheus-stack: ``release``).
    Nothing is asked for: no objects. ``tls_secret``: the controller serves HTTPS with that Secret
    (``controller_objects``); the monitors scrape with ``https`` and check the certificate against its ``ca.crt``."""
    extra = _checked_labels(labels)
    own = {**extra, MANAGED_BY: "kuberos", "app.kubernetes.io/name": NAME}

    def metadata(name: str, namespaced: bool = True, **more) -> dict:
        return {"name": name, **({"namespace": namespace} if namespaced else {}), "labels": dict(own), **more}

    groups = _robot_offline_after(_checked_groups(rules), robot_offline_after) if prometheus_rule else None
    endpoint = {"port": PORT, "path": PATH, "scheme": "http", "interval": INTERVAL, "honorLabels": True}
    if tls_secret:  # the controller serves HTTPS with this Secret: verify it with the Secret's ca.crt
        endpoint["scheme"] = "https"
        endpoint["tlsConfig"] = {"ca": {"secret": {"name": tls_secret, "key": "ca.crt"}}, "serverName": _service_name(namespace)}
    objects: list[dict] = []
    if service_monitor or pod_monitor:
        objects.append(
            {
                "apiVersion": "rbac.authorization.k8s.io/v1",
                "kind": "ClusterRole",
                "metadata": metadata(READER_ROLE, namespaced=False),
                "rules": copy.deepcopy(READER_RULES),
            }
        )
    if pod_monitor:
        objects += [
            {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": metadata(SCRAPER)},
            {
                # Filled in by Kubernetes' token controller with a token of the ServiceAccount above.
                "apiVersion": "v1",
                "kind": "Secret",
                "type": "kubernetes.io/service-account-token",
                "metadata": metadata(SCRAPER_TOKEN, annotations={"kubernetes.io/service-account.name": SCRAPER}),
            },
            {
                "apiVersion": "rbac.authorization.k8s.io/v1",
                "kind": "ClusterRoleBinding",
                "metadata": metadata(SCRAPER, namespaced=False),
                "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": READER_ROLE},
                "subjects": [{"kind": "ServiceAccount", "name": SCRAPER, "namespace": namespace}],
            },
        ]
    if service_monitor:
        objects.append(
            {
                "apiVersion": API_VERSION,
                "kind": "ServiceMonitor",
                "metadata": metadata(NAME),
                "spec": {
                    "selector": copy.deepcopy(SELECTOR),
                    "namespaceSelector": {"matchNames": [namespace]},
                    "endpoints": [{**endpoint, "bearerTokenFile": TOKEN_FILE}],
                },
            }
        )
    if pod_monitor:
        objects.append(
            {
                "apiVersion": API_VERSION,
                "kind": "PodMonitor",
                "metadata": metadata(NAME),
                "spec": {
                    "selector": copy.deepcopy(SELECTOR),
                    "namespaceSelector": {"matchNames": [namespace]},
                    "podMetricsEndpoints": [
                        {**endpoint, "authorization": {"type": "Bearer", "credentials": {"name": SCRAPER_TOKEN, "key": "token"}}}
                    ],
                },
            }
        )
    if prometheus_rule:
        objects.append(
            {
                "apiVersion": API_VERSION,
                "kind": "PrometheusRule",
                "metadata": metadata(RULES_NAME),
                "spec": {"groups": groups},
            }
        )
    return objects
