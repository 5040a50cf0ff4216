"""Parts of the controller that need no cluster: the watch cache, the cluster view, the in-cluster objects."""

from __future__ import annotations

import json
import threading

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.controller import RTT_ANNOTATION, Controller
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.liveness import NodeProbe, server_targets
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import (
    FLEET_RULES,
    LEASE_ROLE,
    LEASE_RULES,
    READ_RULES,
    REVIEW_RULES,
    VIEWER_RULES,
    controller_objects,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store


def _node(name, labels=None, annotations=None, ready="True", since="2026-11-22T01:00:00Z"):
    return {
        "metadata": {"name": name, "labels": labels or {}, "annotations": annotations or {}, "resourceVersion": "1"},
        "status": {"conditions": [{"type": "Ready", "status": ready, "reason": "KubeletReady", "lastTransitionTime": since}]},
    }


def test_the_watch_cache_applies_events_and_asks_to_relist_after_an_error():
    store = Store("nodes", None, threading.Event())
    assert store.handle({"type": "ADDED", "object": _node("edge-1")}, "0") == "1"
    assert store.changed.is_set()
    store.changed.clear()
    assert store.handle({"type": "BOOKMARK", "object": {"metadata": {"resourceVersion": "7"}}}, "1") == "7"
    assert not store.changed.is_set(), "a bookmark changes nothing"
    assert store.handle({"type": "DELETED", "object": _node("edge-1")}, "7") == "1"
    assert store.snapshot() == []
    assert store.handle({"type": "ERROR", "object": {"code": 410, "message": "too old resource version"}}, "7") is None


def test_the_cluster_view_maps_nodes_readiness_rtt_and_pods():
    controller = Controller.__new__(Controller)
    controller.probe = None
    controller.nodes = Store("nodes", None, threading.Event())
    controller.pods = Store("pods", None, threading.Event())
    controller.nodes.items = {
        ("", "k8s-edge-1"): _node("k8s-edge-1", {"device.kuberos.io/hostname": "edge-1"}, ready="Unknown"),
        ("", "fetch-1"): _node("fetch-1", {"robot.kuberos.io/name": "fetch-1"}, {RTT_ANNOTATION: json.dumps({"edge-1": 7})}),
        ("", "fetch-2"): _node("fetch-2", {"robot.kuberos.io/name": "fetch-2"}, {RTT_ANNOTATION: "not json"}),
    }  # fmt: skip
    controller.pods.items = {
        ("ns", "p"): {
            "metadata": {"name": "p", "namespace": "ns", "labels": {"kuberos.io/instance": "i"}, "deletionTimestamp": "x"},
            "spec": {"nodeName": "k8s-edge-1"},
            "status": {
                "phase": "Running",
                "containerStatuses": [{"restartCount": 4, "state": {"waiting": {"reason": "CrashLoopBackOff"}}}],
            },
        }
    }
    view = controller.cluster_view()
    assert not view.nodes["edge-1"].ready and view.nodes["edge-1"].since == 1795309200.0  # 2026-11-22T01:00:00Z
    assert view.nodes["fetch-1"].ready
    assert view.measured == {"fetch-1": {"edge-1": 7.0}}, "a malformed annotation is ignored (and logged)"
    (pod,) = view.pods["ns/i"]
    assert (pod.node, pod.restarts, pod.waiting_reason, pod.deleting) == ("edge-1", 4, "CrashLoopBackOff", True)


def test_a_server_node_whose_kubelet_stopped_answering_is_down_at_once_a_robot_never():
    """The controller's own probe (liveness.py) makes a Ready edge node down, from its first failed probe, with the
    probe's words; a robot's computer is never probed, and a node that never answered is left to Kubernetes."""
    answers = {"10.0.0.1": [True, False, False, False], "10.0.0.2": [False] * 4, "10.0.0.3": [True, True, False, False]}
    clock = iter(range(100, 200))
    probe = NodeProbe(1.0, connect=lambda address, port, timeout: answers[address].pop(0), clock=lambda: next(clock))

    def server(name, address, role="edge"):
        node = _node(name, {"kuberos.io/role": role})
        node["status"]["addresses"] = [{"type": "Hostname", "address": name}, {"type": "InternalIP", "address": address}]
        return node

    nodes = [server("edge-1", "10.0.0.1"), server("edge-2", "10.0.0.2", "cloud"), server("edge-3", "10.0.0.3")]
    nodes.append(server("fetch-1", "10.0.0.9", "robot"))
    assert server_targets(nodes) == {"edge-1": "10.0.0.1", "edge-2": "10.0.0.2", "edge-3": "10.0.0.3"}, "no robot"
    changes = [probe.probe(server_targets(nodes)) for _round in range(4)]
    assert changes == [False, False, False, True], "down after 3 failed probes in a row, not before"
    assert probe.down() == {"edge-1": 101}, "from its first failed probe; edge-2 never answered; edge-3 failed twice"
    controller = Controller.__new__(Controller)
    controller.probe = probe
    controller.nodes = Store("nodes", None, threading.Event())
    controller.pods = Store("pods", None, threading.Event())
    controller.nodes.items = {("", n["metadata"]["name"]): n for n in nodes}
    view = controller.cluster_view()
    edge = view.nodes["edge-1"]
    assert not edge.ready and edge.since == 101 and "has not answered the controller's probes since" in edge.probe
    assert all(view.nodes[n].ready for n in ("edge-2", "edge-3", "fetch-1"))
    answers["10.0.0.1"].append(True)
    answers["10.0.0.2"].append(False)
    answers["10.0.0.3"].append(True)
    assert probe.probe(server_targets(nodes)) and probe.down() == {}, "one answer and it is up again"
    assert probe.probe({}) is False


def pod_labels(deployment: dict) -> dict:
    return deployment["spec"]["template"]["metadata"]["labels"]


def test_the_in_cluster_rights_are_narrow():
    objects = controller_objects("kuberos-system", "img", ["a", "b"], ["--grace", "5"])
    kinds = [o["kind"] for o in objects]
    bindings = {(o["metadata"]["namespace"], o["roleRef"]["name"]) for o in objects if o["kind"] == "RoleBinding"}
    assert bindings == {
        ("kuberos-a", "kuberos-controller-fleet"),
        ("kuberos-b", "kuberos-controller-fleet"),
        ("kuberos-system", LEASE_ROLE),
    }, "fleet rights in fleet namespaces only; Lease rights in the controller's own namespace only"
    (role,) = [o for o in objects if o["kind"] == "Role"]
    assert role["metadata"]["namespace"] == "kuberos-system" and role["rules"] == LEASE_RULES
    for rule in READ_RULES + FLEET_RULES + LEASE_RULES:
        assert "*" not in rule["verbs"] and "*" not in rule["resources"] and "secrets" not in rule["resources"]
    assert all(set(r["verbs"]) <= {"list", "watch"} for r in READ_RULES), "cluster-wide rights are read-only"
    assert {(r["resources"][0], *r["verbs"]) for r in REVIEW_RULES} == {
        ("tokenreviews", "create"),
        ("subjectaccessreviews", "create"),
    }, "the dashboard may only ask who a token is and what it may do (reviews are answered, not stored)"
    read = next(o for o in objects if o["kind"] == "ClusterRole" and o["metadata"]["name"] == "kuberos-controller-read")
    assert read["rules"] == READ_RULES + REVIEW_RULES
    viewer = next(o for o in objects if o["kind"] == "ClusterRole" and o["rules"] == VIEWER_RULES)
    assert all("resources" not in r and r["verbs"] == ["get"] for r in viewer["rules"]), "viewers read two URLs, nothing else"
    service = next(o for o in objects if o["kind"] == "Service")
    assert service["spec"]["ports"] == [{"name": "http", "port": 8611, "targetPort": "http", "protocol": "TCP"}]
    deployment = next(o for o in objects if o["kind"] == "Deployment")
    pod = deployment["spec"]["template"]["spec"]
    container = pod["containers"][0]
    assert deployment["spec"]["replicas"] == 2 and container["securityContext"]["runAsNonRoot"]
    assert container["args"][-2:] == ["--grace", "5"] and "--lease-namespace" in container["args"]
    auth = container["args"].index("--dashboard-auth")
    assert container["args"][auth + 1] == "kubernetes", "in a pod the dashboard listens on every address: tokens required"
    assert container["ports"] == [{"name": "http", "containerPort": 8611, "protocol": "TCP"}]
    assert service["spec"]["selector"].items() <= pod_labels(deployment).items()
    assert {e["name"] for e in container["env"]} == {"POD_NAME", "KUBEROS_NODE_NAME"}
    assert pod["affinity"]["podAntiAffinity"], "replicas spread over nodes where they can"
    (term,) = pod["affinity"]["nodeAffinity"]["requiredDuringSchedulingIgnoredDuringExecution"]["nodeSelectorTerms"]
    assert term == {"matchExpressions": [{"key": "kuberos.io/role", "operator": "In", "values": ["edge"]}]}, "edge servers only"
    assert "PodDisruptionBudget" in kinds
    single = controller_objects("kuberos-system", "img", ["a"], [], replicas=1)
    assert "PodDisruptionBudget" not in [o["kind"] for o in single], "a budget of one replica would block every drain"


def test_the_failover_picture_is_drawn_from_the_recorded_benchmark(root):
    import sys

    sys.path.insert(0, f"{root}/bench")
    try:
        from plot_failover import draw
    finally:
        sys.path.pop(0)
    with open(f"{root}/bench/results/controller-failover.json", encoding="utf-8") as handle:
        data = json.load(handle)
    with open(f"{root}/docs/images/controller-failover.svg", encoding="utf-8") as handle:
        assert handle.read() == draw(data), "run bench/plot_failover.py again"
    assert data["summary"]["ok"] >= 10 and data["summary"]["failed"] == 0


def test_the_controllers_patterns_end_at_the_end_of_the_text_not_before_a_line_break(root):
    """``$`` also matches before a final line break: the patterns end with ``\\Z``, so '10m\\n' is no duration."""
    import pytest
    import yaml

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import monitoring, signals

    with open(f"{root}/roles/controller/files/prometheus/kuberos-rules.yml", encoding="utf-8") as handle:
        rules = yaml.safe_load(handle)
    assert monitoring.monitoring_objects("kuberos-system", rules, False, False, True, robot_offline_after="1h30m")
    for bad in ("10m\n", "1h\n30m"):
        with pytest.raises(SpecError, match="robot_offline_after: expected a Prometheus duration"):
            monitoring.monitoring_objects("kuberos-system", rules, False, False, True, robot_offline_after=bad)
    assert monitoring.DURATION.match("10m\n") is None and signals._CPU_USAGE.match("250m\n") is None
    assert signals.cpu_millis(" 250m ") == 250.0
