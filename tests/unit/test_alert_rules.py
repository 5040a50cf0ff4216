"""The collection's Prometheus rules (roles/controller/files/prometheus/kuberos-rules.yml): promtool accepts them,
its unit tests (tests/unit/data/promtool/) pass, every alert is tested firing and not firing, and every metric
the rules read is one the controller or a bridge exports."""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import pytest
import yaml
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.metrics import HELP as BRIDGE_HELP

RULES = os.path.join(ROOT, "roles", "controller", "files", "prometheus", "kuberos-rules.yml")
RULE_TESTS = os.path.join(ROOT, "tests", "unit", "data", "promtool", "kuberos-rules.test.yml")
# What the controller exports (plugins/module_utils/kuberos_controller/metrics.py, docs/monitoring.md); a histogram
# is read through its series.
CONTROLLER_METRICS = {
    "kuberos_module_instances",
    "kuberos_module_moves_total",
    "kuberos_module_stranded",
    "kuberos_robot_online",
    "kuberos_node_allocatable",
    "kuberos_node_allocated",
    "kuberos_node_ready",
    "kuberos_node_rtt_ms",
    "kuberos_module_rtt_ms",
    "kuberos_module_max_latency_ms",
    *(f"kuberos_reconcile_duration_seconds_{suffix}" for suffix in ("bucket", "sum", "count")),
    "kuberos_controller_leader",
    "kuberos_apiserver_certificate_expiry_seconds",
}


def _load(path: str) -> dict:
    with open(path, encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def _rules() -> list[dict]:
    return [rule for group in _load(RULES)["groups"] for rule in group["rules"]]


def _promtool() -> str:
    path = shutil.which("promtool")
    if not path:
        message = "promtool is not installed (Debian's prometheus package; scripts/setup.sh installs it)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.mark.parametrize(
    ("command", "path"),
    [(["check", "rules"], RULES), (["test", "rules"], RULE_TESTS)],
    ids=["check-rules", "test-rules"],
)
def test_promtool_accepts_the_rules_and_their_unit_tests_pass(command, path):
    result = subprocess.run([_promtool(), *command, path], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, f"promtool {' '.join(command)} {os.path.relpath(path, ROOT)}:\n{result.stdout}{result.stderr}"


def test_the_unit_tests_load_the_rule_file():
    folder = os.path.dirname(RULE_TESTS)
    files = [os.path.normpath(os.path.join(folder, name)) for name in _load(RULE_TESTS)["rule_files"]]
    assert files == [RULES]


def test_every_alert_is_tested_firing_and_not_firing():
    alerts = {rule["alert"] for rule in _rules() if "alert" in rule}
    assert alerts, "the rule file has alerts"
    fired, quiet = set(), set()
    for case in _load(RULE_TESTS)["tests"]:
        for check in case.get("alert_rule_test", []):
            (fired if check.get("exp_alerts") else quiet).add(check["alertname"])
    assert sorted(alerts - fired) == [], "alerts never tested firing"
    assert sorted(alerts - quiet) == [], "alerts never tested not firing"
    assert sorted((fired | quiet) - alerts) == [], "tests of alerts the rule file does not have"


def test_every_alert_has_a_severity_a_summary_and_a_description():
    for rule in _rules():
        if "alert" in rule:
            assert rule["labels"]["severity"] in ("critical", "warning", "info"), rule["alert"]
            assert {"summary", "description"} <= set(rule["annotations"]), rule["alert"]
            assert re.fullmatch(r"KubeROS[A-Z][A-Za-z]+", rule["alert"])


def test_every_recording_rule_is_tested():
    records = {rule["record"] for rule in _rules() if "record" in rule}
    tested = {check["expr"] for case in _load(RULE_TESTS)["tests"] for check in case.get("promql_expr_test", [])}
    assert sorted(records - tested) == []


# Enough of PromQL to find the metric names of an expression: strings, label matchers, durations, modifiers (offset,
# @), the label lists of by/without/on/ignoring/group_left/group_right and numbers go; a name followed by "(" is a
# function; keywords go.
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"|\'(?:[^\'\\]|\\.)*\'|`[^`]*`')
_MATCHERS = re.compile(r"\{[^}]*\}")
_RANGE = re.compile(r"\[[^\]]*\]")
_MODIFIER = re.compile(r"\boffset\s+-?\w+|@\s*(start\(\)|end\(\)|[\d.]+)")
_LABEL_LIST = re.compile(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)")
_NUMBER = re.compile(r"(?<![\w:])\d+(\.\d+)?(e[+-]?\d+)?")
_NAME = re.compile(r"[a-zA-Z_:][a-zA-Z0-9_:]*")
_KEYWORDS = {"and", "or", "unless", "bool", "offset", "inf", "nan", "atan2"}


def metric_names(expr: str) -> set[str]:
    text = _LABEL_LIST.sub(" ", _MODIFIER.sub(" ", _RANGE.sub(" ", _MATCHERS.sub(" ", _STRING.sub(" ", expr)))))
    text = _NUMBER.sub(" ", text)
    names = set()
    for match in _NAME.finditer(text):
        rest = text[match.end() :].lstrip()
        if not rest.startswith("(") and match.group().lower() not in _KEYWORDS:
            names.add(match.group())
    return names


def test_metric_names_are_found_in_expressions():
    expr = 'sum by (reason) (max by (instance) (increase(a_total{x="y(z)"}[10m]))) > 5 or on (n) group_left () absent(b) * 2e3'
    assert metric_names(expr) == {"a_total", "b"}
    assert metric_names("max(kuberos:x:ratio offset 5m) > bool 0.5 unless up @ 1609746000") == {"kuberos:x:ratio", "up"}


def test_the_rules_read_only_exported_metrics():
    records = {rule["record"] for rule in _rules() if "record" in rule}
    known = CONTROLLER_METRICS | set(BRIDGE_HELP) | records
    used = {}
    for rule in _rules():
        name = rule.get("alert") or rule.get("record")
        for metric in metric_names(str(rule["expr"])):
            used.setdefault(metric, []).append(name)
        for text in rule.get("annotations", {}).values():  # queries in annotation templates
            for metric in re.findall(r"\bkuberos[a-z0-9_:]*", text):
                used.setdefault(metric, []).append(name)
    assert {m: rules for m, rules in used.items() if m not in known} == {}
    assert "kuberos_controller_leader" in used and "kuberos_bridge_connected" in used


def test_the_controller_exports_the_metrics_the_rules_know():
    """CONTROLLER_METRICS above follows the controller's metrics.py (a counter or a histogram adds its suffixes)."""
    path = os.path.join(ROOT, "plugins", "module_utils", "kuberos_controller", "metrics.py")
    with open(path, encoding="utf-8") as handle:
        source = handle.read()
    families = {re.sub(r"_(total|bucket|sum|count)$", "", name) for name in CONTROLLER_METRICS}
    assert sorted(f for f in families if f'"{f}"' not in source) == []


def test_the_scrape_job_for_a_prometheus_without_the_operator_is_the_service_monitors_and_promtool_accepts_it(tmp_path):
    """monitoring.scrape_config: what the ServiceMonitor declares, as a plain prometheus.yml job (docs/monitoring.md),
    by Kubernetes discovery (upstream Prometheus) or by DNS over the headless Service (Debian's, built without it)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import controller_objects
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.monitoring import (
        TOKEN_FILE,
        monitoring_objects,
        scrape_config,
    )

    objects = monitoring_objects("kuberos-ops", {}, True, False, False, tls_secret="tls")
    (monitor,) = [o for o in objects if o["kind"] == "ServiceMonitor"]
    (endpoint,) = monitor["spec"]["endpoints"]
    selected = monitor["spec"]["selector"]["matchLabels"]["app.kubernetes.io/name"]
    for discovery in ("kubernetes", "dns"):
        job = scrape_config("kuberos-ops", ca_file="/etc/prometheus/tls/ca.crt", discovery=discovery)
        assert (job["scheme"], job["metrics_path"], job["scrape_interval"]) == (
            endpoint["scheme"],
            endpoint["path"],
            endpoint["interval"],
        )
        assert job["honor_labels"] is endpoint["honorLabels"] is True
        assert job["tls_config"]["server_name"] == endpoint["tlsConfig"]["serverName"]
        assert job["authorization"]["credentials_file"] == endpoint["bearerTokenFile"] == TOKEN_FILE
    kubernetes = scrape_config("kuberos-ops", discovery="kubernetes")
    keep = {tuple(r["source_labels"]): r["regex"] for r in kubernetes["relabel_configs"] if r.get("action") == "keep"}
    assert keep == {
        ("__meta_kubernetes_service_label_app_kubernetes_io_name",): selected,
        ("__meta_kubernetes_endpoint_port_name",): endpoint["port"],
    }
    assert kubernetes["kubernetes_sd_configs"][0]["namespaces"]["names"] == monitor["spec"]["namespaceSelector"]["matchNames"]
    assert "scheme" not in kubernetes, "plain HTTP without a CA file"
    # DNS: the headless Service of the controller's objects, which the ServiceMonitor does not also select.
    services = {o["metadata"]["name"]: o for o in controller_objects("kuberos-ops", "img", ["f"], []) if o["kind"] == "Service"}
    dns = scrape_config("kuberos-ops", discovery="dns")
    (sd,) = dns["dns_sd_configs"]
    headless = services["kuberos-controller-pods"]
    assert sd["names"] == ["kuberos-controller-pods.kuberos-ops.svc.cluster.local"] and sd["type"] == "A"
    assert headless["spec"]["clusterIP"] == "None" and sd["port"] == headless["spec"]["ports"][0]["port"]
    assert headless["spec"]["selector"] == services["kuberos-controller"]["spec"]["selector"]
    assert headless["metadata"]["labels"]["app.kubernetes.io/name"] != selected, "scraped once, not twice"
    with pytest.raises(ValueError, match="expected kubernetes or dns"):
        scrape_config("kuberos-ops", discovery="consul")

    # promtool (Debian's, without Kubernetes discovery) checks the DNS job and the files it names.
    for name in ("token", "ca.crt"):
        (tmp_path / name).write_text("x\n")
    job = scrape_config("kuberos-ops", ca_file=str(tmp_path / "ca.crt"), discovery="dns")
    job["authorization"]["credentials_file"] = str(tmp_path / "token")
    config = tmp_path / "prometheus.yml"
    config.write_text(yaml.safe_dump({"rule_files": [RULES], "scrape_configs": [job]}))
    result = subprocess.run(
        [_promtool(), "check", "config", str(config)], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_docs_show_the_dns_scrape_job_as_the_code_writes_it():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.monitoring import scrape_config

    with open(os.path.join(ROOT, "docs", "monitoring.md"), encoding="utf-8") as handle:
        text = handle.read()
    section = text[text.index("## A Prometheus without the Operator") :]
    block = section[section.index("```yaml\n") + 8 : section.index("```\n", section.index("```yaml\n") + 8)]
    assert yaml.safe_load(block) == {
        "scrape_configs": [scrape_config("kuberos-system", ca_file="/etc/prometheus/tls/ca.crt", discovery="dns")]
    }
