"""The Prometheus Operator objects of the in-cluster controller (kuberos_controller/monitoring.py and the filter
controller_monitoring): their shape, what they select and how they authenticate, the rules they carry."""

from __future__ import annotations

import copy
import os

import kubernetes_validate
import pytest
import yaml
from ansible.errors import AnsibleFilterError
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.filter.controller_monitoring import FilterModule, controller_monitoring
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import controller_objects
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.monitoring import monitoring_objects

NAMESPACE = "kuberos-ops"
RULES_FILE = os.path.join(ROOT, "roles", "controller", "files", "prometheus", "kuberos-rules.yml")
TOKEN_FILE = "/var/run/secrets/kubernetes.io/serviceaccount/token"
CLUSTER_SCOPED = {"ClusterRole", "ClusterRoleBinding"}
# The fields of the monitoring.coreos.com/v1 kinds this collection may set (the Prometheus Operator's CRDs, a subset):
# an unknown field would be pruned by the API server, and a PodMonitor has no bearerTokenFile (on purpose upstream).
ENDPOINT_FIELDS = {
    "port",
    "targetPort",
    "path",
    "scheme",
    "interval",
    "scrapeTimeout",
    "honorLabels",
    "tlsConfig",
    "authorization",
}
SERVICE_MONITOR_FIELDS = {"selector", "namespaceSelector", "endpoints", "jobLabel", "targetLabels", "podTargetLabels"}
POD_MONITOR_FIELDS = {"selector", "namespaceSelector", "podMetricsEndpoints", "jobLabel", "podTargetLabels"}
RULE_GROUP_FIELDS = {"name", "interval", "rules", "limit", "partial_response_strategy", "query_offset", "labels"}
RULE_FIELDS = {"record", "alert", "expr", "for", "keep_firing_for", "labels", "annotations"}


@pytest.fixture(scope="module")
def rules() -> dict:
    with open(RULES_FILE, encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def by_kind(objects: list[dict]) -> dict[str, dict]:
    kinds = [o["kind"] for o in objects]
    assert len(kinds) == len(set(kinds)), kinds
    return {o["kind"]: o for o in objects}


def controller() -> dict[str, dict]:
    """The controller's own Deployment and Service (manifests.py); its headless twin as ``HeadlessService``."""
    objects = controller_objects(NAMESPACE, "img", ["a"], [])
    found = {o["kind"]: o for o in objects if o["kind"] == "Deployment" or o["metadata"]["name"] == "kuberos-controller"}
    found["HeadlessService"] = next(o for o in objects if o["metadata"]["name"] == "kuberos-controller-pods")
    return found


def matches(selector: dict, labels: dict) -> bool:
    assert set(selector) == {"matchLabels"}, "only matchLabels are used"
    return all(labels.get(k) == v for k, v in selector["matchLabels"].items())


def test_nothing_asked_for_gives_no_objects(rules):
    assert monitoring_objects(NAMESPACE, rules, False, False, False) == []
    assert monitoring_objects(NAMESPACE, {}, False, False, False) == [], "the rules are not read when not applied"


@pytest.mark.parametrize(
    ("flags", "kinds"),
    [
        ((True, False, False), ["ClusterRole", "ServiceMonitor"]),
        ((False, True, False), ["ClusterRole", "ServiceAccount", "Secret", "ClusterRoleBinding", "PodMonitor"]),
        ((False, False, True), ["PrometheusRule"]),
        (
            (True, True, True),
            ["ClusterRole", "ServiceAccount", "Secret", "ClusterRoleBinding", "ServiceMonitor", "PodMonitor", "PrometheusRule"],
        ),
    ],
    ids=["service-monitor", "pod-monitor", "prometheus-rule", "all"],
)
def test_each_flag_brings_its_objects_in_apply_order(rules, flags, kinds):
    assert [o["kind"] for o in monitoring_objects(NAMESPACE, rules, *flags)] == kinds


def test_the_objects_have_the_shape_of_their_kind(rules):
    objects = monitoring_objects(NAMESPACE, rules, True, True, True, labels={"release": "kube-prometheus-stack"})
    for obj in objects:
        metadata = obj["metadata"]
        assert obj["apiVersion"] and metadata["name"], obj
        assert ("namespace" in metadata) == (obj["kind"] not in CLUSTER_SCOPED), obj
        assert metadata.get("namespace", NAMESPACE) == NAMESPACE
        assert metadata["labels"]["release"] == "kube-prometheus-stack", "the user's labels are on every object"
        assert metadata["labels"]["app.kubernetes.io/managed-by"] == "kuberos"
        if obj["apiVersion"].startswith("monitoring.coreos.com/"):
            assert obj["apiVersion"] == "monitoring.coreos.com/v1"
        else:
            kubernetes_validate.validate(obj, "1.34", strict=True)
    objs = by_kind(objects)
    assert set(objs["ServiceMonitor"]["spec"]) <= SERVICE_MONITOR_FIELDS
    for endpoint in objs["ServiceMonitor"]["spec"]["endpoints"]:
        assert set(endpoint) <= ENDPOINT_FIELDS | {"bearerTokenFile"}
    assert set(objs["PodMonitor"]["spec"]) <= POD_MONITOR_FIELDS
    for endpoint in objs["PodMonitor"]["spec"]["podMetricsEndpoints"]:
        assert set(endpoint) <= ENDPOINT_FIELDS, "a PodMonitor endpoint has no bearerTokenFile"
    assert set(objs["PrometheusRule"]["spec"]) == {"groups"}
    for group in objs["PrometheusRule"]["spec"]["groups"]:
        assert set(group) <= RULE_GROUP_FIELDS
        assert all(set(rule) <= RULE_FIELDS and ("alert" in rule) != ("record" in rule) for rule in group["rules"])
    assert yaml.safe_load(yaml.safe_dump(objects)) == objects, "plain data, no shared objects (YAML aliases)"
    assert "&id" not in yaml.safe_dump(objects)


def test_the_service_monitor_scrapes_the_controllers_service_with_a_token(rules):
    monitor = by_kind(monitoring_objects(NAMESPACE, rules, True, False, False))["ServiceMonitor"]
    ours = controller()
    service = ours["Service"]
    assert service["metadata"]["name"] == "kuberos-controller" and service["metadata"]["namespace"] == NAMESPACE
    assert matches(monitor["spec"]["selector"], service["metadata"]["labels"])
    assert not matches(monitor["spec"]["selector"], ours["HeadlessService"]["metadata"]["labels"]), "each replica scraped once"
    assert monitor["spec"]["namespaceSelector"] == {"matchNames": [NAMESPACE]}
    (endpoint,) = monitor["spec"]["endpoints"]
    assert endpoint["port"] in {p.get("name") for p in service["spec"]["ports"]}
    assert endpoint == {
        "port": "http",
        "path": "/metrics",
        "scheme": "http",
        "interval": "15s",
        "honorLabels": True,
        "bearerTokenFile": TOKEN_FILE,
    }
    deployment = ours["Deployment"]
    assert matches(monitor["spec"]["selector"], deployment["spec"]["template"]["metadata"]["labels"])
    assert matches({"matchLabels": service["spec"]["selector"]}, deployment["spec"]["template"]["metadata"]["labels"])


def test_the_pod_monitor_scrapes_the_controllers_pods_with_its_own_token(rules):
    objs = by_kind(monitoring_objects(NAMESPACE, rules, False, True, False))
    monitor, account, secret, binding, role = (
        objs[k] for k in ("PodMonitor", "ServiceAccount", "Secret", "ClusterRoleBinding", "ClusterRole")
    )
    template = controller()["Deployment"]["spec"]["template"]
    assert matches(monitor["spec"]["selector"], template["metadata"]["labels"])
    assert monitor["spec"]["namespaceSelector"] == {"matchNames": [NAMESPACE]}
    (endpoint,) = monitor["spec"]["podMetricsEndpoints"]
    ports = {p.get("name") for c in template["spec"]["containers"] for p in c.get("ports", [])}
    if not ports:
        pytest.skip("the controller's container has no named port yet (the controller's /metrics work adds http)")
    assert endpoint["port"] in ports
    assert (endpoint["port"], endpoint["path"], endpoint["scheme"], endpoint["interval"]) == ("http", "/metrics", "http", "15s")
    # The token: a Secret beside the PodMonitor, of the ServiceAccount bound to the reader role.
    credentials = endpoint["authorization"]["credentials"]
    assert endpoint["authorization"]["type"] == "Bearer" and credentials["key"] == "token"
    assert credentials["name"] == secret["metadata"]["name"] and secret["metadata"]["namespace"] == NAMESPACE
    assert secret["type"] == "kubernetes.io/service-account-token"
    assert secret["metadata"]["annotations"] == {"kubernetes.io/service-account.name": account["metadata"]["name"]}
    assert binding["subjects"] == [{"kind": "ServiceAccount", "name": account["metadata"]["name"], "namespace": NAMESPACE}]
    assert binding["roleRef"] == {
        "apiGroup": "rbac.authorization.k8s.io",
        "kind": "ClusterRole",
        "name": role["metadata"]["name"],
    }


@pytest.mark.parametrize("flags", [(True, False), (False, True)], ids=["service-monitor", "pod-monitor"])
def test_the_reader_role_may_get_metrics_and_nothing_else(rules, flags):
    (role,) = [o for o in monitoring_objects(NAMESPACE, rules, *flags, False) if o["kind"] == "ClusterRole"]
    assert role["metadata"]["name"] == "kuberos-metrics-reader"
    assert role["rules"] == [{"nonResourceURLs": ["/metrics"], "verbs": ["get"]}]


def test_the_prometheus_rule_carries_exactly_the_files_groups(rules):
    before = copy.deepcopy(rules)
    (rule,) = monitoring_objects(NAMESPACE, rules, False, False, True)
    assert rule["kind"] == "PrometheusRule" and rule["metadata"]["namespace"] == NAMESPACE
    assert rule["spec"] == {"groups": rules["groups"]}
    rule["spec"]["groups"][0]["rules"].clear()
    assert rules == before, "the objects are copies: changing them leaves the parsed file alone"


def test_the_robot_offline_alert_fires_after_the_sites_own_duration(rules):
    def offline_rule(objects):
        (rule,) = objects
        return next(r for g in rule["spec"]["groups"] for r in g["rules"] if r.get("alert") == "KubeROSRobotOffline")

    default = offline_rule(monitoring_objects(NAMESPACE, rules, False, False, True))
    assert default["for"] == "10m" and "for 10m or more" in default["annotations"]["description"]
    later = offline_rule(controller_monitoring(rules, prometheus_rule=True, robot_offline_after="1h30m"))
    assert later["for"] == "1h30m" and "for 1h30m or more" in later["annotations"]["description"]
    assert "10m" not in later["annotations"]["description"]
    for bad in ("ten minutes", "10", "", 600, None):
        with pytest.raises(SpecError, match=r"robot_offline_after: expected a Prometheus duration such as 10m"):
            monitoring_objects(NAMESPACE, rules, False, False, True, robot_offline_after=bad)


@pytest.mark.parametrize("bad", [{}, {"groups": []}, {"groups": [{"name": "x"}]}, ["groups"], None])
def test_a_rule_file_that_is_not_one_is_refused(bad):
    with pytest.raises(SpecError, match="groups"):
        monitoring_objects(NAMESPACE, bad, False, False, True)


@pytest.mark.parametrize("bad", [["release"], {"release": 1}, "release=x"])
def test_labels_must_be_a_mapping_of_strings(rules, bad):
    with pytest.raises(SpecError, match="labels"):
        monitoring_objects(NAMESPACE, rules, True, False, False, labels=bad)


def test_the_filter_is_the_function(rules):
    assert FilterModule().filters()["controller_monitoring"] is controller_monitoring
    assert controller_monitoring(rules) == []
    objects = controller_monitoring(rules, namespace=NAMESPACE, service_monitor="yes", prometheus_rule=True, labels={"tier": 1})
    assert objects == monitoring_objects(NAMESPACE, rules, True, False, True, labels={"tier": "1"})
    assert controller_monitoring(rules, service_monitor="false", pod_monitor="no") == []
    with pytest.raises(AnsibleFilterError, match="groups"):
        controller_monitoring({"groups": "x"}, prometheus_rule=True)


def test_the_role_reads_the_rule_file_it_ships():
    with open(os.path.join(ROOT, "roles", "controller", "tasks", "in_cluster.yml"), encoding="utf-8") as handle:
        tasks = handle.read()
    assert "lookup('ansible.builtin.file', 'prometheus/kuberos-rules.yml')" in tasks
    assert "kuberos.platform.controller_monitoring(" in tasks
    with open(os.path.join(ROOT, "roles", "controller", "defaults", "main.yml"), encoding="utf-8") as handle:
        defaults = yaml.safe_load(handle)
    assert {k: defaults[k] for k in ("controller_service_monitor", "controller_pod_monitor", "controller_prometheus_rule")} == {
        "controller_service_monitor": False,
        "controller_pod_monitor": False,
        "controller_prometheus_rule": False,
    }


def deployment_of(objects: list[dict]) -> dict:
    return next(o for o in objects if o["kind"] == "Deployment")


def test_with_a_tls_secret_the_controller_serves_https_and_the_monitors_verify_it(rules):
    secret = "kuberos-dashboard-tls"
    pod = deployment_of(controller_objects(NAMESPACE, "img", ["a"], [], tls_secret=secret))["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    assert pod["volumes"] == [{"name": "dashboard-tls", "secret": {"secretName": secret}}]
    (mount,) = container["volumeMounts"]
    assert mount["readOnly"] and container["args"][container["args"].index("--dashboard-tls-cert") + 1].startswith(
        mount["mountPath"]
    )
    assert container["readinessProbe"]["httpGet"]["scheme"] == "HTTPS"
    plain = deployment_of(controller_objects(NAMESPACE, "img", ["a"], []))["spec"]["template"]["spec"]
    assert "volumes" not in plain and "--dashboard-tls-cert" not in plain["containers"][0]["args"]
    monitors = by_kind(monitoring_objects(NAMESPACE, rules, True, True, False, tls_secret=secret))
    for endpoint in (
        monitors["ServiceMonitor"]["spec"]["endpoints"][0],
        monitors["PodMonitor"]["spec"]["podMetricsEndpoints"][0],
    ):
        assert endpoint["scheme"] == "https"
        assert endpoint["tlsConfig"] == {
            "ca": {"secret": {"name": secret, "key": "ca.crt"}},
            "serverName": f"kuberos-controller.{NAMESPACE}.svc",
        }
