"""The dashboard's view and the controller's /metrics, from objects shaped as the API server serves them, and the
dashboard's HTTP server itself (aiohttp on a loopback port) over stores filled by hand: filters, paging, hostile
query strings, security headers, the live stream and the metrics text."""

from __future__ import annotations

import asyncio
import http.client
import json
import threading
import time
import urllib.error
import urllib.request

import pytest
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import INSTANCE, MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    NodeView,
    PodView,
    Settings,
    latency_fault,
    node_fault,
    pod_fault,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import build_records, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import dashboard_page
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.dashboard import Dashboard
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.metrics import ControllerMetrics, move_reason
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import (
    Snapshot,
    build_view,
    live_placement,
    page,
    select,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store, store_key

SPEC = "examples/pick-and-place.yml"
NAMESPACE = "kuberos-test-fleet"


@pytest.fixture(scope="module")
def deployed(local_raw, local_inventory, root):
    """The example placed on the local inventory: (record ConfigMap, Record, node objects, pod objects)."""
    deployments, placement = load_and_place(f"{root}/{SPEC}", local_raw)
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        text = handle.read()
    _revision, configmap = build_records(text, SPEC, deployments, placement, local_raw, RenderOptions(), "kuberos")
    configmap["metadata"]["resourceVersion"] = "1"
    record = parse_record(configmap)
    nodes = [node_object(n) for n in local_inventory.nodes.values()]
    pods = [pod_object(i.name, i.node, f"{i.name}-1", "registry.example/x:0.1") for i in record.placement.instances]
    pods += [pod_object(s.name, s.node, f"{s.name}-1", "ros:jazzy") for ss in record.placement.discovery.values() for s in ss]
    return configmap, record, nodes, pods


def node_object(node, ready=True, rtt=None) -> dict:
    annotations = {"kuberos.io/rtt-ms": json.dumps(rtt)} if rtt else {}
    return {
        "metadata": {"name": node.name, "labels": node_labels.node_labels(node), "annotations": annotations},
        "status": {
            "allocatable": {
                "cpu": f"{node.cpu_millis}m",
                "memory": str(node.memory_bytes),
                "pods": "110",
                **({"nvidia.com/gpu": str(node.gpu)} if node.gpu else {}),
            },
            "conditions": [
                {
                    "type": "Ready",
                    "status": "True" if ready else "Unknown",
                    "reason": "" if ready else "NodeStatusUnknown",
                    "lastTransitionTime": "2026-11-25T10:00:00Z",
                }
            ],
        },
    }


def pod_object(instance, node, name, image, phase="Running", ready=True) -> dict:
    return {
        "metadata": {"name": name, "namespace": NAMESPACE, "labels": {INSTANCE: instance, MANAGED_BY: "kuberos"}},
        "spec": {
            "nodeName": node,
            "containers": [{"image": image, "resources": {"requests": {"cpu": "250m", "memory": "128Mi"}}}],
        },
        "status": {
            "phase": phase,
            "conditions": [{"type": "Ready", "status": "True" if ready else "False"}],
            "containerStatuses": [{"restartCount": 0, "state": {"running": {}}}],
        },
    }


def snapshot(deployed, **changes) -> Snapshot:
    configmap, record, nodes, pods = deployed
    base = {"nodes": nodes, "pods": pods, "records": [(configmap, record, "")]}
    return Snapshot(**{**base, **changes})


def test_every_module_of_every_robot_is_shown_where_its_pod_runs(deployed):
    _configmap, record, nodes, _pods = deployed
    view = build_view(snapshot(deployed))
    shown = {(r["robot"], r["module"]): (r["node"], r["phase"], r["version"]) for r in view.modules}
    expected = {(r["robot"], r["module"]): (r["node"], "Running", "0.1") for r in record.placement.rows()}
    assert shown == expected
    assert view.summary["instances"] == len(record.placement.instances) and view.summary["stranded"] == 0
    assert view.summary["nodes"] == view.summary["ready"] == len(nodes)
    reasons = {r["instance"]: r["reason"] for r in view.modules}
    assert all(reasons[i.name] == i.reason and i.reason for i in record.placement.instances), "the placement's reasons"
    assert {f["fleet"] for f in view.fleets} == {"test-fleet", "warehouse-fleet"}, "every fleet of the inventory"
    fleet = next(f for f in view.fleets if f["fleet"] == "test-fleet")
    assert fleet["robots"] == ["fetch-1", "fetch-2"] and fleet["deployments"] == ["pick-and-place"]
    assert [s["node"] for s in fleet["discovery"]] == [s.node for s in record.placement.discovery["test-fleet"]]
    assert all(s["phase"] == "Running" for s in fleet["discovery"])
    assert fleet["offline"] == []


def test_an_offline_robot_is_shown_offline_with_its_modules_not_stranded(deployed):
    """A robot whose node is not Ready: its fleet lists it offline since the node's transition, its modules are in
    phase Offline with the time in their note (not Stranded), and the timeline says RobotOffline."""
    _configmap, _record, nodes, _pods = deployed
    changed = []
    for node in nodes:
        node = json.loads(json.dumps(node))
        if node["metadata"]["name"] == "fetch-1":
            node["status"]["conditions"] = [
                {
                    "type": "Ready",
                    "status": "Unknown",
                    "reason": "NodeStatusUnknown",
                    "lastTransitionTime": "2026-11-27T09:00:00Z",
                }
            ]
        changed.append(node)
    view = build_view(snapshot(deployed, nodes=changed))
    fleet = next(f for f in view.fleets if f["fleet"] == "test-fleet")
    assert [(r["robot"], r["since"]) for r in fleet["offline"]] == [("fetch-1", "2026-11-27T09:00:00Z")]
    rows = [r for r in view.modules if r["node"] == "fetch-1"]
    assert rows and all(r["phase"] == "Offline" and r["note"].startswith("robot offline") for r in rows), rows
    assert view.summary["stranded"] == 0
    (event,) = [e for e in view.events if e["object"] == "fetch-1" and e["kind"] == "node"]
    assert event["reason"] == "RobotOffline" and event["message"].startswith("robot fetch-1 is offline")


def test_allocated_is_what_the_kubernetes_pods_on_a_node_request(deployed):
    _configmap, record, _nodes, _pods = deployed
    view = build_view(snapshot(deployed))
    per_node: dict[str, int] = {}
    for i in record.placement.instances:
        per_node[i.node] = per_node.get(i.node, 0) + 1
    for s in (s for ss in record.placement.discovery.values() for s in ss):
        per_node[s.node] = per_node.get(s.node, 0) + 1
    for row in view.resources:
        count = per_node.get(row["name"], 0)
        assert row["allocated"]["pods"] == count and row["allocated"]["cpu"] == pytest.approx(0.25 * count)
        assert row["allocatable"]["pods"] == 110


def test_a_move_a_stranding_a_pod_elsewhere_and_a_slow_link_show(deployed):
    _configmap, record, nodes, pods = deployed
    planner = next(i for i in record.placement.instances if i.module == "motion-planner")
    onboard = next(i for i in record.placement.instances if i.tier == "onboard")
    robot = planner.robots[0]
    moved_pod = [p for p in pods if p["metadata"]["labels"][INSTANCE] != planner.name]
    moved_pod.append(pod_object(planner.name, "edge-3", "elsewhere", "registry.example/x:0.2"))
    status = {
        "metadata": {"name": "kuberos-status-pick-and-place", "namespace": NAMESPACE},
        "data": {
            "status.json": json.dumps({"deployment": "pick-and-place", "rows": [{"instance": onboard.name, "note": "onboard"}]}),
            "moves.json": json.dumps({planner.name: {"at": "2026-11-25T10:00:05Z", "from": "x", "to": planner.node, "why": "w"}}),
        },
    }
    robot_node = next(n for n in nodes if (n["metadata"]["labels"].get(node_labels.ROBOT)) == robot)
    slow = dict(
        robot_node, metadata={**robot_node["metadata"], "annotations": {"kuberos.io/rtt-ms": json.dumps({planner.node: 999})}}
    )
    view = build_view(
        snapshot(deployed, pods=moved_pod, statuses=[status], nodes=[slow if n is robot_node else n for n in nodes])
    )
    rows = {(r["robot"], r["module"]): r for r in view.modules}
    row = rows[(robot, "motion-planner")]
    assert row["phase"] == "Moving", "its pod runs on another node than the record says"
    assert row["last_move"]["why"] == "w" and row["rtt_ms"] == 999 and row["over_latency"]
    assert rows[(onboard.robots[0], onboard.module)]["phase"] == "Stranded"
    assert view.summary["stranded"] == 1 and view.summary["over_latency"] == 1


def test_node_failures_rollouts_and_controller_events_make_one_timeline(deployed):
    configmap, _record, nodes, _pods = deployed
    down = [node_object_like(n, ready=False) if n["metadata"]["name"] == "edge-1" else n for n in nodes]
    rolling = parse_record(configmap)
    first, second = (i.name for i in rolling.placement.instances[:2])
    rolling.rollout = {"revision": 2, "from": 1, "started": "2026-11-25T10:01:00Z", "instances": [first, second]}
    pods = [p for p in _pods if p["metadata"]["labels"][INSTANCE] != first]
    replaced = pod_object(first, rolling.placement.instances[0].node, "new", "registry.example/x:0.2")
    replaced["metadata"]["creationTimestamp"] = "2026-11-25T10:01:30Z"  # a pod of the rollout's, Running
    event = {
        "metadata": {"name": "e1", "namespace": NAMESPACE, "creationTimestamp": "2026-11-25T10:02:00Z"},
        "involvedObject": {"name": "pick-and-place-perception-fetch-1"},
        "reason": "ModuleMoved", "message": "moved from edge-1 to edge-2", "type": "Normal",
        "lastTimestamp": "2026-11-25T10:02:00Z",
    }  # fmt: skip
    view = build_view(snapshot(deployed, nodes=down, pods=[*pods, replaced], records=[(configmap, rolling, "")], events=[event]))
    kinds = [(e["kind"], e["object"]) for e in view.events]
    assert kinds[0] == ("move", "pick-and-place-perception-fetch-1"), "newest first"
    assert ("rollout", "pick-and-place") in kinds and ("node", "edge-1") in kinds
    (rollout,) = view.software["rollouts"]
    assert (rollout["from"], rollout["to"], rollout["instances"], rollout["done"]) == (1, 2, 2, 1), "one replaced of two"


def node_object_like(node: dict, ready: bool) -> dict:
    copy = json.loads(json.dumps(node))
    copy["status"]["conditions"][0].update(status="True" if ready else "Unknown", reason="NodeStatusUnknown")
    return copy


def test_an_unreadable_record_is_named_and_does_not_hide_the_others(deployed):
    configmap, _record, _nodes, _pods = deployed
    bad = {"metadata": {"name": "kuberos-record-broken", "namespace": NAMESPACE}, "data": {}}
    view = build_view(snapshot(deployed, records=[(bad, None, "not a readable KubeROS record"), (configmap, _record, "")]))
    assert view.summary["unreadable_records"] == [
        {"namespace": NAMESPACE, "name": "kuberos-record-broken", "error": "not a readable KubeROS record"}
    ]
    assert view.modules, "the readable record is still shown"


def test_the_live_map_shows_only_the_chosen_robots_on_live_capacity(deployed):
    view = build_view(snapshot(deployed))
    key = next(iter(view.placements))
    part = live_placement(view, key, {"fetch-1"})
    assert part.instances and all("fetch-1" in i.robots for i in part.instances)
    names = {n["name"] for n in part.nodes}
    assert {i.node for i in part.instances} <= names and "fetch-2" not in names
    edge = next(n for n in part.nodes if n["name"] == "edge-1")
    assert edge["free_cpu_millis"] < edge["cpu_millis"], "the pods' requests are taken off"


@pytest.mark.parametrize(
    "query",
    [
        {"page": "abc", "size": "-5"},
        {"page": "999999999999", "size": "1e9"},
        {"q": "\x00<script>alert(1)</script>", "phase": "Running"},
        {"q": "ü" * 5000},
        {"over_latency": "true"},
    ],
)
def test_filters_and_paging_never_fail_on_odd_input(deployed, query):
    view = build_view(snapshot(deployed))
    found = select(view.modules, query, ("robot", "module"))
    result = page(found, query.get("page"), query.get("size", 100))
    assert 1 <= result["size"] <= 1000 and 0 <= result["page"] < result["pages"]
    assert len(result["rows"]) <= result["size"]


def test_search_and_exact_filters(deployed):
    view = build_view(snapshot(deployed))
    fields = ("robot", "module", "node")
    assert {r["robot"] for r in select(view.modules, {"q": "FETCH-1"}, fields)} == {"fetch-1"}
    assert {r["tier"] for r in select(view.modules, {"tier": "edge"}, fields)} == {"edge"}
    assert select(view.modules, {"tier": "edge", "q": "controller"}, fields) == []
    assert len(page(view.modules, 1, 3)["rows"]) == 3 and page(view.modules, 1, 3)["rows"][0] == view.modules[3]


# -- metrics ------------------------------------------------------------------------------------------
def test_a_moves_reason_label_comes_from_the_fault_the_controller_saw(deployed):
    _configmap, record, _nodes, _pods = deployed
    inst = next(i for i in record.placement.instances if i.module == "perception")
    cluster = ClusterView(nodes={inst.node: NodeView(inst.node, False, "Ready=Unknown (NodeStatusUnknown)", 1.0)})
    assert move_reason(node_fault(inst.node, cluster)[0]) == "node_failure"
    assert move_reason(node_fault("gone", cluster)[0]) == "node_failure"
    pod = PodView("p", NAMESPACE, inst.name, inst.node, "Running", False, 9, "CrashLoopBackOff", False)
    failing = ClusterView(pods={inst.name: [pod]})
    assert move_reason(pod_fault(inst, failing, Settings())) == "pod_failure"
    slow = ClusterView(measured={inst.robots[0]: {inst.node: 1e6}})
    assert move_reason(latency_fault(inst, record, slow)) == "latency"
    assert move_reason("an operator asked") == "other"


def metric_values(text: str) -> dict[tuple[str, frozenset], float]:
    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def test_the_metrics_count_what_the_view_shows(deployed):
    _configmap, record, nodes, _pods = deployed
    planner = next(i for i in record.placement.instances if i.module == "motion-planner")
    robot_node = next(n for n in nodes if n["metadata"]["labels"].get(node_labels.ROBOT) == planner.robots[0])
    measured = json.loads(json.dumps(robot_node))
    measured["metadata"]["annotations"] = {"kuberos.io/rtt-ms": json.dumps({planner.node: 12.5})}
    view = build_view(snapshot(deployed, nodes=[measured if n is robot_node else n for n in nodes]))
    metrics = ControllerMetrics(lambda: view, lambda: ("replica-a", True))
    metrics.moved("node edge-1 is NotReady (Ready=Unknown)")
    metrics.reconcile.observe(0.02)
    values = metric_values(generate_latest(metrics.registry).decode())
    running = sum(v for (n, labels), v in values.items() if n == "kuberos_module_instances" and ("phase", "Running") in labels)
    assert running == len(record.placement.instances)
    assert values[("kuberos_module_moves_total", frozenset({("reason", "node_failure")}))] == 1
    assert values[("kuberos_module_moves_total", frozenset({("reason", "latency")}))] == 0, "every reason exists from the start"
    assert values[("kuberos_controller_leader", frozenset({("identity", "replica-a")}))] == 1
    assert values[("kuberos_reconcile_duration_seconds_count", frozenset())] == 1
    edge = frozenset({("node", "edge-1"), ("resource", "cpu")})
    assert values[("kuberos_node_allocatable", edge)] == 16 and values[("kuberos_node_allocated", edge)] > 0
    labels = {("namespace", NAMESPACE), ("deployment", "pick-and-place"), ("module", "motion-planner")}
    assert values[("kuberos_module_rtt_ms", frozenset(labels | {("robot", planner.robots[0]), ("node", planner.node)}))] == 12.5
    assert values[("kuberos_module_max_latency_ms", frozenset(labels))] == 200
    assert values[("kuberos_node_rtt_ms", frozenset({("node", planner.robots[0]), ("peer", planner.node)}))] == 12.5
    assert sum(v for (n, _l), v in values.items() if n == "kuberos_module_stranded") == 0


# -- the page's script ---------------------------------------------------------------------------------
def test_the_page_never_turns_cluster_data_into_html():
    for unsafe in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "eval(", "new Function"):
        assert unsafe not in dashboard_page.SCRIPT, unsafe
    assert "<script>" not in dashboard_page.HTML, "no inline script: the Content-Security-Policy allows only /static/app.js"


# -- the HTTP server ----------------------------------------------------------------------------------
class HandFed:
    """What the dashboard reads of a controller, with stores filled by the test instead of watches."""

    def __init__(self, deployed):
        configmap, _record, nodes, pods = deployed
        self.changed = threading.Event()
        self.stop_event = threading.Event()
        self.nodes, self.pods, self.deployments, self.records = (
            Store(name, None, self.changed) for name in ("nodes", "pods", "deployments", "records")
        )
        self.stores = (self.nodes, self.pods, self.deployments, self.records)
        self.put(self.nodes, *nodes)
        self.put(self.pods, *pods)
        self.put(self.records, configmap)
        self.kube = None
        self.identity, self.leading, self.elector, self.passes, self.moves = "hand-fed", True, None, 0, 0

    @staticmethod
    def put(store: Store, *objects: dict) -> None:
        with store.lock:
            for obj in objects:
                store.items[store_key(obj)] = obj
            store.generation += 1


@pytest.fixture
def served(deployed):
    controller = HandFed(deployed)
    dashboard = Dashboard(controller, "127.0.0.1", 0, watch_extra=False, refresh_s=0.05)
    dashboard.start()
    try:
        yield controller, dashboard, f"http://127.0.0.1:{dashboard.port}"
    finally:
        controller.stop_event.set()
        dashboard.stop()


# Ansible's open_url installs its own opener process-wide (one that may refuse redirects): the tests keep theirs.
OPENER = urllib.request.build_opener()


def fetch(url: str) -> tuple[int, dict, bytes]:
    try:
        with OPENER.open(url, timeout=5) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def wait_for_view(dashboard, generation=1):
    """Nothing is built before somebody asks: the first request builds the view."""
    assert dashboard.view.generation == 0
    status, _headers, body = fetch(f"http://127.0.0.1:{dashboard.port}/api/summary")
    assert status == 200 and json.loads(body)["generation"] >= generation


def test_the_server_answers_every_route_with_safe_headers(served):
    _controller, dashboard, base = served
    wait_for_view(dashboard)
    for path in ("/", "/static/app.js", "/static/app.css", "/api/summary", "/api/modules", "/api/resources", "/api/fleets",
                 "/api/software", "/api/events", "/api/placement.svg", "/metrics", "/healthz"):  # fmt: skip
        status, headers, body = fetch(base + path)
        assert status == 200, (path, body[:300])
        assert headers["X-Content-Type-Options"] == "nosniff" and "default-src 'none'" in headers["Content-Security-Policy"]
    status, _headers, body = fetch(base + "/api/modules?page=abc&size=-1&q=%00%3Cscript%3E&phase=Running")
    assert status == 200 and json.loads(body)["size"] == 1
    assert fetch(base + "/api/placement.svg?deployment=nope")[0] == 404
    assert fetch(base + "/login")[0] == 200 and b"Sign in" not in fetch(base + "/login")[2], "no login without auth"


def test_a_change_reaches_an_open_stream_within_the_update_window(served, deployed):
    controller, dashboard, base = served
    wait_for_view(dashboard)
    _configmap, record, _nodes, pods = deployed
    target = record.placement.instances[0]

    async def listen():
        reader, writer = await asyncio.open_connection("127.0.0.1", dashboard.port)
        writer.write(f"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1:{dashboard.port}\r\n\r\n".encode())
        await writer.drain()
        seen = []
        changed_at = None
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            line = (await asyncio.wait_for(reader.readline(), 10)).decode()
            if line.startswith("data: "):
                seen.append(json.loads(line[6:])["generation"])
                if len(seen) == 1:
                    changed_at = time.monotonic()
                    gone = [p for p in pods if p["metadata"]["labels"][INSTANCE] == target.name]
                    with controller.pods.lock:
                        for pod in gone:
                            controller.pods.items.pop(store_key(pod))
                        controller.pods.generation += 1
                else:
                    writer.close()
                    return seen, time.monotonic() - changed_at
        writer.close()
        return seen, None

    seen, delay = asyncio.run(listen())
    assert len(seen) == 2 and seen[1] > seen[0], seen
    assert delay is not None and delay < 2.0, f"a change took {delay} s to reach the page"
    rows = json.loads(fetch(f"{base}/api/modules?q={target.robots[0]}&module={target.module}")[2])["rows"]
    assert rows[0]["phase"] == "Missing", "the page refetches and sees the pod gone"


def test_nothing_is_built_while_nobody_looks_but_node_transitions_are_noted(served, deployed):
    controller, dashboard, base = served
    wait_for_view(dashboard)
    _configmap, _record, nodes, _pods = deployed
    edge = next(n for n in nodes if n["metadata"]["name"] == "edge-2")
    controller.put(controller.nodes, node_object_like(edge, ready=False))
    time.sleep(0.5)
    controller.put(controller.nodes, node_object_like(edge, ready=True))
    time.sleep(0.5)
    assert dashboard.view.generation == 1, "no page open, no scrape: no view built"
    events = json.loads(fetch(base + "/api/events?q=edge-2")[2])["rows"]
    assert [e["reason"] for e in events if e["kind"] == "node"] == ["NodeReady", "NodeNotReady"], events
    assert dashboard.view.generation == 2, "the request built what it read"


def test_with_a_certificate_it_serves_https_only(deployed, tmp_path):
    """--dashboard-tls-cert/--dashboard-tls-key (the in-cluster controller's with controller_dashboard_tls_secret):
    HTTPS with the certificate, verified against its CA; a plain-HTTP request gets no page."""
    import ssl

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.cli import parse_args
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

    ca_cert, ca_key = pki.new_ca("kuberos-test-ca", days=1)
    cert, key = pki.issue(ca_cert, ca_key, "kuberos-controller", usage=pki.SERVER, days=1, alt_names=["127.0.0.1"])
    for name, obj in (("ca.crt", ca_cert), ("tls.crt", cert), ("tls.key", key)):
        pki.write_pem(str(tmp_path / name), obj)
    with pytest.raises(SystemExit):
        parse_args(["--kubeconfig", "k", "--dashboard-tls-cert", str(tmp_path / "tls.crt")])  # a key is needed too
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    server.load_cert_chain(str(tmp_path / "tls.crt"), str(tmp_path / "tls.key"))
    controller = HandFed(deployed)
    dashboard = Dashboard(controller, "127.0.0.1", 0, watch_extra=False, tls=server)
    dashboard.start()
    try:
        client = ssl.create_default_context(cafile=str(tmp_path / "ca.crt"))
        with urllib.request.urlopen(f"https://127.0.0.1:{dashboard.port}/api/summary", timeout=5, context=client) as response:
            assert response.status == 200 and json.loads(response.read())["rows"] > 0
        with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
            urllib.request.urlopen(f"https://127.0.0.1:{dashboard.port}/healthz", timeout=5, context=ssl.create_default_context())
        try:
            plain = fetch(f"http://127.0.0.1:{dashboard.port}/healthz")[0]
        except http.client.HTTPException:
            plain = 0
        assert plain != 200, "no plain HTTP beside HTTPS"
    finally:
        controller.stop_event.set()
        dashboard.stop()


class LogKube:
    """The two reads the dashboard's log panel makes: the instance's pods, and a container's log."""

    def __init__(self, volumes=()):
        self.volumes, self.asked = list(volumes), []

    def list(self, kind, namespace, selector=""):
        assert kind == "Pod" and selector.startswith("kuberos.io/instance=")
        instance = selector.split("=", 1)[1]
        spec = {"nodeName": "edge-1", "containers": [{"name": "main"}, {"name": "side"}], "volumes": self.volumes}
        return [{"metadata": {"name": f"{instance}-abc", "creationTimestamp": "2026-11-28T10:00:00Z"}, "spec": spec}]

    def log(self, pod, namespace, container="", tail_lines=None):
        self.asked.append((pod, namespace, container, tail_lines))
        return f"{container} says hello\nAuthorization: Bearer abcdefghijklmnop\n"


def test_the_log_panel_reads_an_instances_last_lines_labelled_and_never_a_secret(served):
    controller, dashboard, base = served
    wait_for_view(dashboard)
    row = json.loads(fetch(base + "/api/modules")[2])["rows"][0]
    controller.kube = LogKube()
    status, headers, body = fetch(f"{base}/api/logs?instance={row['instance']}&lines=5")
    assert status == 200 and headers["X-Content-Type-Options"] == "nosniff"
    found = json.loads(body)
    assert found["lines"] == ["[main] main says hello", "[main] Authorization: Bearer [redacted: token]",
                              "[side] side says hello", "[side] Authorization: Bearer [redacted: token]"]  # fmt: skip
    assert found["robot"] == row["robot"] and found["node"] == "edge-1"
    assert controller.kube.asked[0] == (f"{row['instance']}-abc", row["namespace"], "main", 5)
    controller.kube = LogKube(volumes=[{"name": "tls", "secret": {"secretName": "bridge-tls"}}])
    refused = json.loads(fetch(f"{base}/api/logs?instance={row['instance']}")[2])
    assert "can read Secret bridge-tls" in refused["refused"] and "lines" not in refused and not controller.kube.asked
    assert fetch(f"{base}/api/logs?instance=nothing-here")[0] == 404
    assert fetch(f"{base}/api/logs?instance={row['instance']}&lines=many")[0] == 400


def test_the_ros_graph_view_shows_each_robots_last_check_and_a_reservation_shows_in_its_fleet(served):
    import dataclasses

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import Snapshot, build_view

    topic = {"name": "/fetch_1/a", "type": "t", "publishers": [], "subscribers": ["/fetch_1/b"], "rate": None}
    graph = {"deployment": "pnp", "robots": {
        "fetch-1": {"at": "2026-11-28T10:00:00Z", "ok": False, "problems": ["/fetch_1/a: nobody publishes it"],
                    "topics": [topic]},
        "fetch-2": {"at": "2026-11-28T10:00:00Z", "ok": True, "problems": [], "topics": []},
    }}  # fmt: skip
    configmap = {"metadata": {"name": "kuberos-graph-pnp", "namespace": "kuberos-f"}, "data": {"graph.json": json.dumps(graph)}}
    broken = {"metadata": {"name": "kuberos-graph-x", "namespace": "kuberos-f"}, "data": {"graph.json": "{"}}
    reservation = {"metadata": {"name": "kuberos-reservation-fetch-2"}, "data": {
        "robot": "fetch-2", "fleet": "f", "owner": "alice", "reason": "tests", "until": "2099-01-01T00:00:00Z",
        "since": "2026-11-28T10:00:00Z"}}  # fmt: skip
    view = build_view(Snapshot(nodes=[], pods=[], records=[], graphs=[configmap, broken], reservations=[reservation]))
    assert view.graphs == {"kuberos-f/pnp": graph["robots"]}
    (fleet,) = view.fleets
    assert fleet["fleet"] == "f" and fleet["reservations"][0]["owner"] == "alice" and fleet["reservations"][0]["active"]

    _controller, dashboard, base = served
    wait_for_view(dashboard)
    dashboard.view = dataclasses.replace(dashboard.view, graphs=view.graphs)
    found = json.loads(fetch(base + "/api/graph?q=1")[2])
    assert found["deployment"] == "kuberos-f/pnp" and found["total"] == 2 and list(found["robots"]) == ["fetch-1"]
    assert found["robots"]["fetch-1"]["problems"] == ["/fetch_1/a: nobody publishes it"]
    assert b"renderGraph" in fetch(base + "/static/app.js")[2] and b'data-tab="graph"' in fetch(base + "/")[2]


# -- issue 44: the auth-less dashboard answers only under its own loopback name; a bad reservation stops nothing --
def ask(port: int, path: str, host: str | None) -> tuple[int, dict, bytes]:
    """A real HTTP request to the dashboard on 127.0.0.1:``port`` with the ``Host`` header ``host`` (None: none)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        connection.putrequest("GET", path, skip_host=True)
        if host is not None:
            connection.putheader("Host", host)
        connection.endheaders()
        response = connection.getresponse()
        return response.status, dict(response.headers), response.read()
    finally:
        connection.close()


def test_without_a_login_the_dashboard_refuses_any_host_but_its_own_loopback_address_and_port(served):
    _controller, dashboard, _base = served
    port = dashboard.port
    for host in (f"evil.example:{port}", "evil.example", f"127.0.0.1.evil.example:{port}", f"127.0.0.1:{port + 1}",
                 "127.0.0.1", f"localhost:{port}:x", f"[::1]x:{port}", f"attacker.test:{port}", ""):  # fmt: skip
        for path in ("/api/logs?instance=x", "/api/summary", "/", "/metrics"):
            status, headers, body = ask(port, path, host)
            assert status == 421, (host, path, status, body[:200])
            assert b"this dashboard answers only as 127.0.0.1:" in body and b"DNS rebinding" in body, body
            assert "default-src 'none'" in headers["Content-Security-Policy"] and headers["X-Frame-Options"] == "DENY"
    assert ask(port, "/api/summary", None)[0] == 400, "no Host header at all: HTTP/1.1 requires one (aiohttp says so)"
    assert dashboard.view.generation == 0, "a refused request builds nothing"
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}", f"[::1]:{port}"):
        status, headers, body = ask(port, "/api/summary", host)
        assert status == 200 and json.loads(body)["rows"] > 0, (host, status, body[:200])
        assert "default-src 'none'" in headers["Content-Security-Policy"]


def test_the_host_rule_is_the_auth_less_dashboards_alone(deployed):
    """In a cluster the dashboard checks tokens and is reached under any name (a Service, a port-forward, an
    ingress): there the Host header is not checked, the token is."""

    class Refusing:
        def check(self, token, path):
            from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.auth import Verdict

            return Verdict(200, "alice") if token == "good" else Verdict(401, why="no bearer token")

        def session_token(self, session):
            return ""

    controller = HandFed(deployed)
    dashboard = Dashboard(controller, "127.0.0.1", 0, auth=Refusing(), watch_extra=False)
    dashboard.start()
    try:
        assert ask(dashboard.port, "/api/summary", "kuberos-controller.kuberos-system.svc:8611")[0] == 401
        connection = http.client.HTTPConnection("127.0.0.1", dashboard.port, timeout=5)
        connection.request("GET", "/api/summary", headers={"Host": "dashboard.example.org", "Authorization": "Bearer good"})
        assert connection.getresponse().status == 200
        connection.close()
    finally:
        controller.stop_event.set()
        dashboard.stop()
    assert Dashboard(controller, "127.0.0.1", 443, watch_extra=False, tls=object()).own_host("localhost")
    assert not Dashboard(controller, "127.0.0.1", 8611, watch_extra=False).own_host("localhost")


def _reservation(robot: str, until: str, owner: str = "alice") -> dict:
    return {"metadata": {"name": f"kuberos-reservation-{robot}", "namespace": "kuberos-f", "resourceVersion": "1"},
            "data": {"robot": robot, "fleet": "f", "owner": owner, "reason": "", "until": until,
                     "since": "2026-11-28T10:00:00Z"}}  # fmt: skip


def test_a_reservation_out_of_range_is_ignored_with_a_warning_and_the_view_stays_fresh(served, caplog):
    _controller, dashboard, base = served
    extra = tuple(Store(name, None, threading.Event()) for name in ("statuses", "catalogs", "events", "reservations", "graphs"))
    dashboard.extra = extra
    bad = _reservation("fetch-9", "9999-12-31T23:59:59-12:00")
    HandFed.put(extra[3], _reservation("fetch-2", "2099-01-01T00:00:00Z"), bad)
    with caplog.at_level("WARNING", logger="kuberos.controller"):
        status, _headers, body = fetch(base + "/api/fleets")
        fetch(base + "/api/fleets")
    assert status == 200
    fleet = next(f for f in json.loads(body)["fleets"] if f["fleet"] == "f")
    assert [r["robot"] for r in fleet["reservations"]] == ["fetch-2"]
    (warning,) = json.loads(fetch(base + "/api/summary")[2])["unreadable_reservations"]
    assert warning.startswith("reservation kuberos-f/kuberos-reservation-fetch-9 ignored (it holds nothing): until:")
    assert [r.getMessage() for r in caplog.records] == [f"dashboard: {warning}"], "logged once, not at every rebuild"
    generation = dashboard.view.generation
    HandFed.put(extra[3], _reservation("fetch-3", "2099-01-01T00:00:00Z", owner="bob"))
    found = json.loads(fetch(base + "/api/fleets")[2])
    assert found["generation"] > generation, "a fresh view, not the last one kept"
    fleet = next(f for f in found["fleets"] if f["fleet"] == "f")
    assert [r["robot"] for r in fleet["reservations"]] == ["fetch-2", "fetch-3"]
