"""Parts of the controller that need no cluster: the watch cache, the cluster view, the in-cluster objects."""

from __future__ import annotations

import json
import threading

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.controller import RTT_ANNOTATION, Controller
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
