"""The dashboard and /metrics on the real local control plane, seen by a real browser and a real Prometheus.

The pick-and-place example is deployed and the controller started with its playbook (two replicas, each
serving the dashboard and /metrics on its own port). A headless Chromium (Debian's chromium and
chromium-driver, driven by selenium) loads the page: every module of every robot is shown on the node the
cluster runs it on, and after a node fails, the modules the controller moves appear in their new place
within the update window (2 s after the record changes). A Prometheus (Debian's prometheus) scrapes both
replicas and a KubeROS-Bridge server and client on loopback, with the collection's alerting rules loaded;
PromQL answers before and after the node failure. With KUBEROS_DASHBOARD_SCREENSHOTS=<dir> the browser test
also saves a screenshot of every view there (docs/images holds the committed ones).

In-cluster access control is tested here too: bearer tokens of real ServiceAccounts, checked by the API
server with TokenReview and SubjectAccessReview.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

import pytest
from helpers import ROOT, free_ports, playbook
from test_controller import SPEC, Fleet, wait_for

pytestmark = pytest.mark.cluster

UPDATE_WINDOW_S = 2.0
RULES = os.path.join(ROOT, "roles", "controller", "files", "prometheus", "kuberos-rules.yml")
BRIDGE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge"
TOPICS = "topics:\n- {name: /chatter, type: std_msgs/msg/String, direction: to_client}\n"
VIEWS = ("deployments", "resources", "fleets", "software", "events", "map")


def require(program: str, package: str) -> str:
    path = shutil.which(program)
    if path:
        return path
    message = f"{program} is not installed (Debian package {package}; scripts/setup.sh installs it)"
    if os.environ.get("CI"):
        pytest.fail(message, pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="module")
def fleet(cluster, tmp_path_factory):
    render = tmp_path_factory.mktemp("render-dashboard")
    deployed = cluster.deploy(SPEC, render)
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    fleet = Fleet(cluster, tmp_path_factory.mktemp("controller-dashboard"))
    started = fleet.controller()
    assert started.returncode == 0, started.stdout[-3000:]
    try:
        fleet.converge()
        wait_for(lambda: fetch(fleet.dashboard(1) + "healthz")[0] == 200, 20, "the first replica's dashboard")
        wait_for(lambda: fetch(fleet.dashboard(2) + "healthz")[0] == 200, 20, "the second replica's dashboard")
        yield fleet
    finally:
        fleet.controller("stopped")
        fleet.restore_nodes()
        cluster.undeploy(SPEC)


# Ansible's open_url installs its own opener process-wide (one that may refuse redirects): the tests keep theirs.
OPENER = urllib.request.build_opener()


def fetch(url: str, token: str = "", data: bytes | None = None) -> tuple[int, bytes]:
    request = urllib.request.Request(url, data=data, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with OPENER.open(request, timeout=10) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
    except OSError:
        return 0, b""


# -- the browser ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    chromium = require("chromium", "chromium")
    driver_path = require("chromedriver", "chromium-driver")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,900"):
        options.add_argument(argument)
    options.binary_location = chromium
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    driver.set_page_load_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()


ROWS = """return Array.from(document.querySelectorAll('#modules tbody tr')).map(tr => [
  tr.dataset.instance, tr.dataset.robot, tr.querySelector('td.node').textContent, tr.querySelector('.phase').textContent])"""


def shown(browser) -> dict[tuple[str, str], tuple[str, str]]:
    """(instance, robot) -> (node, phase) as the page shows them now."""
    return {(i, r): (n, p) for i, r, n, p in browser.execute_script(ROWS)}


def open_view(browser, base: str, view: str, timeout=20) -> None:
    browser.get(f"{base}#{view}")
    wait_for(
        lambda: (
            browser.execute_script("return document.body.dataset.tab") == view
            and browser.execute_script("return document.body.dataset.generation")
        ),
        timeout,
        f"the {view} view drawn",
        lambda: browser.execute_script("return document.getElementById('live-text').textContent"),
    )


def truth(fleet) -> dict[tuple[str, str], str]:
    """(instance, robot) -> the node its one Running pod is on, for every module of every robot."""
    pods = fleet.pods()
    found = {}
    for inst in fleet.record().placement.instances:
        running = [p for p in pods.get(inst.name, []) if p.status.phase == "Running" and not p.metadata.deletion_timestamp]
        assert len(running) == 1, (inst.name, [p.metadata.name for p in running])
        for robot in inst.robots:
            found[(inst.name, robot)] = running[0].spec.node_name
    return found


def test_the_page_shows_every_module_where_it_runs_and_a_move_within_the_update_window(fleet, browser):
    base = fleet.dashboard(2)  # a standby's page is the same: every replica builds it from the cluster
    open_view(browser, base, "deployments")
    expected = truth(fleet)
    wait_for(lambda: shown(browser) == {k: (n, "Running") for k, n in expected.items()}, 10,
             "the page showing every module Running on its pod's node", lambda: f"{shown(browser)}\n{expected}")  # fmt: skip

    node, leaving = fleet.busiest_edge()
    before = fleet.placed()
    fleet.node_down(node)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            after = fleet.placed()
            if all(after[i] != before[i] for i in leaving):
                break
            time.sleep(0.05)
        recorded_at = time.monotonic()
        moved = {i: after[i] for i in leaving if i in {inst for inst, _robot in expected}}
        assert moved, f"no module moved off {node}"
        seen_at = None
        while time.monotonic() < recorded_at + 10:
            rows = shown(browser)
            if all(rows.get(k, ("",))[0] == moved[k[0]] for k in expected if k[0] in moved):
                seen_at = time.monotonic()
                break
            time.sleep(0.05)
        assert seen_at is not None, f"the page never showed {moved}: {shown(browser)}"
        delay = seen_at - recorded_at
        assert delay <= UPDATE_WINDOW_S, f"the move reached the page {delay:.2f} s after the record changed"
        print(f"the move of {sorted(moved)} reached the page {delay:.2f} s after the record changed")
        fleet.converge()
        expected = truth(fleet)
        wait_for(lambda: shown(browser) == {k: (n, "Running") for k, n in expected.items()}, 10,
                 "the moved modules Running in their new place", lambda: f"{shown(browser)}\n{expected}")  # fmt: skip
        open_view(browser, base, "resources")
        wait_for(lambda: browser.execute_script(f"return document.querySelector('tr[data-node=\"{node}\"] .phase').textContent")
                 == "NotReady", 10, f"{node} shown NotReady")  # fmt: skip
        open_view(browser, base, "events")
        text = browser.execute_script("return document.getElementById('events').textContent")
        assert "ModuleMoved" in text and node in text, text[:2000]
        screenshots = os.environ.get("KUBEROS_DASHBOARD_SCREENSHOTS")
        if screenshots:
            os.makedirs(screenshots, exist_ok=True)
            for view in VIEWS:
                open_view(browser, base, view)
                time.sleep(0.5)  # the map's picture loads after the page is drawn
                browser.save_screenshot(os.path.join(screenshots, f"dashboard-{view}.png"))
    finally:
        fleet.node_up(node)
    fleet.converge()


# -- Prometheus ----------------------------------------------------------------------------------------
class Prometheus:
    def __init__(self, workdir, targets: dict[str, list[str]], scrape_configs=()):
        program = require("prometheus", "prometheus")
        self.port = free_ports(1)
        config = {
            "global": {"scrape_interval": "1s", "evaluation_interval": "1s"},
            "rule_files": [RULES],
            "scrape_configs": [{"job_name": job, "static_configs": [{"targets": hosts}]} for job, hosts in targets.items()]
            + list(scrape_configs),
        }
        path = os.path.join(workdir, "prometheus.yml")
        with open(path, "w", encoding="utf-8") as handle:
            json.dump(config, handle)
        self.log = open(os.path.join(workdir, "prometheus.log"), "w+", encoding="utf-8")
        self.process = subprocess.Popen(
            [program, f"--config.file={path}", f"--storage.tsdb.path={workdir}/data",
             f"--web.listen-address=127.0.0.1:{self.port}"],
            stdout=self.log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        wait_for(lambda: fetch(f"http://127.0.0.1:{self.port}/-/ready")[0] == 200, 30, "Prometheus ready", self.output)

    def output(self) -> str:
        self.log.seek(0)
        return self.log.read()[-3000:]

    def query(self, promql: str) -> list[dict]:
        status, body = fetch(f"http://127.0.0.1:{self.port}/api/v1/query?" + urllib.parse.urlencode({"query": promql}))
        assert status == 200, body[:500]
        return json.loads(body)["data"]["result"]

    def value(self, promql: str) -> float | None:
        result = self.query(promql)
        return float(result[0]["value"][1]) if result else None

    def wait(self, promql: str, check, what: str, timeout=30.0) -> float | None:
        wait_for(lambda: check(self.value(promql)), timeout, what, lambda: f"{promql} = {self.value(promql)}")
        return self.value(promql)

    def close(self):
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.log.close()


@pytest.fixture
def bridge(tmp_path):
    """A KubeROS-Bridge server and client connected over loopback (mutual TLS), each serving /metrics."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import generate_certificates

    certs = generate_certificates(str(tmp_path / "certs"), "kuberos-bridge.test")
    topics = tmp_path / "topics.yml"
    topics.write_text(TOPICS, encoding="utf-8")
    grpc, server_metrics, client_metrics = free_ports(1), free_ports(1), free_ports(1)
    env = {**os.environ, "PYTHONPATH": os.path.join(ROOT, ".collections"), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_DOMAIN_ID": "77", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}  # fmt: skip
    processes = []
    for role, metrics in (("server", server_metrics), ("client", client_metrics)):
        if role == "server":
            where = ["--listen", f"127.0.0.1:{grpc}"]
        else:
            where = ["--connect", f"127.0.0.1:{grpc}", "--server-name", "kuberos-bridge.test", "--backoff-max", "1"]
        tls = ["--cert", certs[f"{role}_cert"], "--key", certs[f"{role}_key"], "--ca", certs["ca_cert"]]
        command = [sys.executable, "-m", BRIDGE, role, *where, *tls, "--topics", str(topics), "--metrics-port", str(metrics),
                   "--metrics-host", "127.0.0.1"]  # fmt: skip
        log = open(tmp_path / f"bridge-{role}.log", "w", encoding="utf-8")
        processes.append((subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT), log))
    try:
        yield [f"127.0.0.1:{server_metrics}", f"127.0.0.1:{client_metrics}"]
    finally:
        for process, log in processes:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
            log.close()


def test_prometheus_scrapes_the_controller_and_a_bridge_before_and_after_a_node_failure(fleet, bridge, tmp_path):
    controllers = [fleet.dashboard(i)[len("http://") : -1] for i in (1, 2)]
    prometheus = Prometheus(str(tmp_path), {"kuberos-controller": controllers, "kuberos-bridge": bridge})
    try:
        prometheus.wait('count(up{job="kuberos-controller"} == 1)', lambda v: v == 2, "both controller replicas scraped")
        prometheus.wait('count(up{job="kuberos-bridge"} == 1)', lambda v: v == 2, "both bridge ends scraped")
        prometheus.wait("min(kuberos_bridge_connected)", lambda v: v == 1, "the bridge's two ends connected")
        instances = len(fleet.record().placement.instances)
        running = 'sum(max without (instance) (kuberos_module_instances{phase="Running"}))'
        prometheus.wait(running, lambda v: v == instances, f"{instances} instances Running")
        assert prometheus.value("sum(kuberos_controller_leader)") == 1, "exactly one replica leads"
        assert prometheus.value("count(kuberos_controller_leader)") == 2
        moves = 'sum(kuberos_module_moves_total{reason="node_failure"})'
        before = prometheus.value(moves)
        node, leaving = fleet.busiest_edge()
        ready = f'max(kuberos_node_ready{{node="{node}"}})'
        assert prometheus.value(ready) == 1
        assert prometheus.value(f'sum(kuberos_node_allocated{{node="{node}", resource="pods"}}) / 2') == len(leaving)
        fleet.node_down(node)
        try:
            fleet.converge()
            prometheus.wait(ready, lambda v: v == 0, f"{node} not Ready in Prometheus")
            prometheus.wait(moves, lambda v: v == before + len(leaving), f"{len(leaving)} node_failure moves counted")
            prometheus.wait(running, lambda v: v == instances, "every instance Running again after the moves")
            prometheus.wait(f'max(kuberos_node_allocated{{node="{node}", resource="pods"}})', lambda v: v == 0,
                            f"nothing left allocated on {node}")  # fmt: skip
            assert prometheus.value("sum(rate(kuberos_reconcile_duration_seconds_count[1m])) > 0") is not None
            rules = json.loads(fetch(f"http://127.0.0.1:{prometheus.port}/api/v1/rules")[1])["data"]["groups"]
            assert rules and all(r["health"] == "ok" for g in rules for r in g["rules"]), rules
        finally:
            fleet.node_up(node)
        fleet.converge()
        online = 'max without (instance, pod) (kuberos_robot_online{robot="fetch-1"})'
        assert prometheus.value(online) == 1
        fleet.node_down("fetch-1")
        try:
            prometheus.wait(online, lambda v: v == 0, "the offline robot counted offline")
            prometheus.wait('count(ALERTS{alertname="KubeROSRobotOffline"})', lambda v: v == 1,
                            "one KubeROSRobotOffline alert (pending), not one per replica")  # fmt: skip
            offline = 'sum(max without (instance, pod) (kuberos_module_instances{module="controller", phase="Offline"}))'
            prometheus.wait(offline, lambda v: v == 1, "its onboard module counted Offline")
            stranded = 'sum(max without (instance, pod) (kuberos_module_stranded{module="controller"}))'
            assert prometheus.value(stranded) == 0, "an offline robot strands nothing"
        finally:
            fleet.node_up("fetch-1")
        prometheus.wait(online, lambda v: v == 1, "the robot online again")
        fleet.converge()
    finally:
        prometheus.close()


# -- access control in a cluster -------------------------------------------------------------------------
def test_in_a_cluster_only_tokens_the_api_server_accepts_and_rbac_allows_get_in(fleet, tmp_path):
    from kubernetes import client

    core = fleet.core
    rbac = client.RbacAuthorizationV1Api(core.api_client)
    namespace = "kuberos-system"
    port = free_ports(1)
    names = ("dashboard-viewer-test", "dashboard-nobody-test")
    try:
        core.create_namespace({"metadata": {"name": namespace}})
    except client.exceptions.ApiException as exc:
        assert exc.status == 409
    for name in names:
        core.create_namespaced_service_account(namespace, {"metadata": {"name": name}})
    rbac.create_cluster_role(
        {"metadata": {"name": names[0]}, "rules": [{"nonResourceURLs": ["/kuberos/dashboard"], "verbs": ["get"]}]}
    )
    rbac.create_cluster_role_binding({
        "metadata": {"name": names[0]},
        "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": names[0]},
        "subjects": [{"kind": "ServiceAccount", "name": names[0], "namespace": namespace}],
    })  # fmt: skip
    tokens = {
        name: core.create_namespaced_service_account_token(name, namespace, {"spec": {"expirationSeconds": 600}}).status.token
        for name in names
    }
    env = {**os.environ, "PYTHONPATH": os.path.join(ROOT, ".collections")}
    log = open(tmp_path / "controller.log", "w+", encoding="utf-8")
    process = subprocess.Popen(
        [sys.executable, "-m", "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller",
         "--kubeconfig", fleet.cluster.kubeconfig, "--lease-name", "kuberos-controller-auth-test", "--dashboard-port",
         str(port), "--dashboard-host", "127.0.0.1", "--dashboard-auth", "kubernetes"],
        env=env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    try:
        wait_for(lambda: fetch(base + "/healthz")[0] == 200, 30, "the dashboard up", lambda: log.seek(0) or log.read()[-2000:])
        assert fetch(base + "/api/summary")[0] == 401, "no token: who is asking is unknown"
        assert fetch(base + "/api/summary", "not-a-token")[0] == 401
        assert fetch(base + "/api/summary", tokens[names[1]])[0] == 403, "a valid token without the right is refused"
        status, body = fetch(base + "/api/summary", tokens[names[0]])
        assert status == 200 and json.loads(body)["auth"] is True
        assert fetch(base + "/metrics", tokens[names[0]])[0] == 403, "/metrics is its own right"
        status, body = fetch(base + "/", "")
        assert status == 200 and b"Sign in" in body, "a browser without a session is sent to the sign-in page"
        login = urllib.parse.urlencode({"token": tokens[names[0]]}).encode()
        opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor())
        with opener.open(base + "/login", data=login, timeout=10) as response:
            assert response.status == 200 and b"/static/app.js" in response.read(), "signed in: the page itself"
        with opener.open(base + "/api/summary", timeout=10) as response:
            assert response.status == 200, "the session cookie carries the sign-in"
        log.seek(0)
        assert tokens[names[0]] not in log.read(), "tokens are never logged"
    finally:
        process.terminate()
        process.wait(10)
        log.close()
        for name in names:
            core.delete_namespaced_service_account(name, namespace)
        rbac.delete_cluster_role_binding(names[0])
        rbac.delete_cluster_role(names[0])


# -- the Prometheus Operator's objects ------------------------------------------------------------------------
OPERATOR_KINDS = {"ServiceMonitor": "servicemonitors", "PodMonitor": "podmonitors", "PrometheusRule": "prometheusrules"}


def operator_crds() -> list[dict]:
    """The CRDs of the three kinds the role applies, from the Prometheus Operator's Go module (scripts/operator-crds.sh;
    make test fetches it)."""
    import yaml

    done = subprocess.run([os.path.join(ROOT, "scripts", "operator-crds.sh")], capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        message = f"the Prometheus Operator's CRDs are not available: {done.stderr.strip()[-500:]}"
        if os.environ.get("CI"):
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    folder = done.stdout.strip()
    crds = []
    for plural in OPERATOR_KINDS.values():
        with open(os.path.join(folder, f"monitoring.coreos.com_{plural}.yaml"), encoding="utf-8") as handle:
            crds.append(yaml.safe_load(handle))
    return crds


def test_the_prometheus_operator_objects_apply_to_its_own_crds(fleet):
    """With the Operator's real CRDs in the cluster, the role applies the ServiceMonitor, PodMonitor and PrometheusRule
    (with the in-cluster controller) and the API server keeps every field (its schemas prune unknown ones); stopped
    removes them."""
    import yaml
    from kubernetes import client

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.monitoring import monitoring_objects

    crds = operator_crds()
    extensions = client.ApiextensionsV1Api(fleet.core.api_client)
    custom = client.CustomObjectsApi(fleet.core.api_client)
    for crd in crds:
        extensions.create_custom_resource_definition(crd)
    settings = {
        "controller_mode": "in_cluster", "controller_kubeconfig": fleet.cluster.kubeconfig, "controller_fleets": ["test-fleet"],
        "controller_image": "registry.invalid/kuberos-controller:test", "controller_service_monitor": True,
        "controller_pod_monitor": True, "controller_prometheus_rule": True, "controller_monitoring_labels": {"release": "kps"},
    }  # fmt: skip
    try:
        wait_for(
            lambda: all(
                any(c.type == "Established" and c.status == "True" for c in extensions.read_custom_resource_definition(
                    crd["metadata"]["name"]).status.conditions or [])
                for crd in crds
            ),
            30, "the CRDs established",
        )  # fmt: skip
        applied = playbook("controller.yml", "-e", json.dumps({**settings, "controller_state": "started"}))
        assert applied.returncode == 0, applied.stdout[-3000:]
        with open(RULES, encoding="utf-8") as handle:
            rules = yaml.safe_load(handle)
        wanted = monitoring_objects("kuberos-system", rules, True, True, True, {"release": "kps"})
        for obj in (o for o in wanted if o["kind"] in OPERATOR_KINDS):
            live = custom.get_namespaced_custom_object(
                "monitoring.coreos.com", "v1", "kuberos-system", OPERATOR_KINDS[obj["kind"]], obj["metadata"]["name"]
            )
            assert live["spec"] == obj["spec"], f"{obj['kind']}: the API server dropped or changed fields"
            assert live["metadata"]["labels"]["release"] == "kps"
        stopped = playbook("controller.yml", "-e", json.dumps({**settings, "controller_state": "stopped"}))
        assert stopped.returncode == 0, stopped.stdout[-3000:]
        for kind, plural in OPERATOR_KINDS.items():
            left = custom.list_namespaced_custom_object("monitoring.coreos.com", "v1", "kuberos-system", plural)["items"]
            assert left == [], f"{kind} left after controller_state=stopped"
    finally:
        for crd in crds:
            extensions.delete_custom_resource_definition(crd["metadata"]["name"])
