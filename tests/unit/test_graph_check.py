"""The live graph check's pod and verdict (plugins/module_utils/kuberos_deploy/graph_check.py), without a cluster:
the pod copies a module's node and ROS environment, runs the probe, and its log is read back as a verdict."""

from __future__ import annotations

import dataclasses
import json
import os

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import (
    CHECK_LABEL,
    GraphCheck,
    check_pod,
    graph_check_problem,
    read_verdict,
    template_of,
)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _example(local_inventory):
    (dep,) = load_rosdeployment_file(os.path.join(ROOT, "examples", "pick-and-place.yml"))
    placement = place_modules([dep], local_inventory)
    objects = render_deployment([dep], placement, RenderOptions())
    return dep, [o for o in objects if o["kind"] == "Deployment"]


def test_the_check_runs_beside_an_edge_module_with_its_ros_environment_and_no_more(local_inventory):
    _dep, deployments = _example(local_inventory)
    template = template_of(deployments)
    assert template["metadata"]["annotations"]["kuberos.io/tier"] == "edge"
    pod = check_pod(template, "kuberos-graph-check-x", "reg/bridge:1", ["fetch-1"], [{"name": "/a", "type": "t"}], 20, 3)
    spec, (container,) = pod["spec"], pod["spec"]["containers"]
    assert spec["nodeSelector"] == template["spec"]["template"]["spec"]["nodeSelector"]
    assert spec["restartPolicy"] == "Never" and spec["automountServiceAccountToken"] is False
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert env["ROS_DISCOVERY_SERVER"].startswith("$(KUBEROS_DISCOVERY_0_SERVICE_HOST)")
    assert env["ROS_SUPER_CLIENT"] == "TRUE" and env["KUBEROS_ROBOTS"] == "fetch-1" and env["ROS_DOMAIN_ID"] == "7"
    assert json.loads(env["KUBEROS_TOPICS"]) == [{"name": "/a", "type": "t"}]
    assert not {"KUBEROS_ROBOT_NAME", "KUBEROS_PARAMS_FILE", "KUBEROS_NODE_NAME"} & set(env), "the module's own variables"
    assert container["args"] == ["--topics", "--json", "--timeout", "20", "--window", "3"]
    assert container["securityContext"]["runAsNonRoot"] and container["securityContext"]["capabilities"] == {"drop": ["ALL"]}
    assert pod["metadata"]["labels"][CHECK_LABEL] == "pick-and-place"
    assert set(pod["metadata"]["labels"]) == {CHECK_LABEL, "fleet.kuberos.io/name"}, "status and the wait do not count it"
    modules = [d for d in deployments if d["metadata"]["labels"]["kuberos.io/component"] == "ros-module"]
    onboard = [d for d in modules if d["metadata"]["annotations"].get("kuberos.io/tier") == "onboard"]
    assert template_of(onboard)["metadata"]["name"] == min(d["metadata"]["name"] for d in onboard)
    assert template_of([]) is None


def test_the_verdict_is_read_from_the_probes_log():
    report = {"topics": [{"name": "/fetch_1/a"}], "problems": []}
    ok = read_verdict(json.dumps(report) + "\nros_graph_probe: 1 topic(s) on 1 robot(s) as declared, in 2.0 s\n", 0, 4.0)
    assert ok.ok and ok.summary == "1 topic(s) on 1 robot(s) as declared, in 2.0 s" and ok.report == report
    bad = {"topics": [], "problems": ["/fetch_1/a: nobody publishes it (p declares it)"]}
    failed = read_verdict(json.dumps(bad) + "\nros_graph_probe: /fetch_1/a: nobody publishes it (p declares it)\n", 1, 4.0)
    assert not failed.ok and failed.problems == bad["problems"]
    crashed = read_verdict("Traceback (most recent call last):\n  boom\n", 1, 1.0)
    assert not crashed.ok and crashed.problems[0].startswith("the probe exited 1: Traceback")
    assert read_verdict("ros_graph_probe: KUBEROS_TOPICS is empty\n", 2, 1.0).problems == ["KUBEROS_TOPICS is empty"]


def test_options_out_of_range_are_refused():
    assert graph_check_problem({}) == ""
    assert "graph_check_timeout" in graph_check_problem({"graph_check_timeout": 0})
    assert "graph_check_window" in graph_check_problem({"graph_check_window": 61})


class FakeKube:
    """The calls GraphCheck makes, answered as a cluster would: the pod ends with ``exit_code`` and ``log``."""

    def __init__(self, deployments, exit_code, log, waiting=None):
        self.deployments, self.exit_code, self.log_text, self.waiting = deployments, exit_code, log, waiting
        self.created, self.deleted = [], []
        self.node_annotations = {}
        record = {"metadata": {"name": "kuberos-record-pick-and-place", "uid": "u-1"}}
        self.configmaps = {"kuberos-record-pick-and-place": record}

    def list(self, kind, namespace="", selector=""):
        if kind == "Node":
            assert selector.startswith("device.kuberos.io/hostname=")
            return [{"metadata": {"name": selector.split("=")[1], "annotations": self.node_annotations}}]
        assert (kind, selector) == ("Deployment", "kuberos.io/deployment=pick-and-place")
        return self.deployments

    def create(self, obj):
        self.created.append(obj)
        return obj

    def get(self, kind, name, namespace):
        if kind == "ConfigMap":
            return self.configmaps.get(name)
        state = {"waiting": self.waiting} if self.waiting else {"terminated": {"exitCode": self.exit_code}}
        return {"status": {"containerStatuses": [{"state": state}]}}

    def apply(self, obj):
        self.configmaps[obj["metadata"]["name"]] = obj
        return obj

    def log(self, name, namespace, container=""):
        return self.log_text

    def delete(self, kind, name, namespace, grace_seconds=None):
        self.deleted.append((kind, name, namespace))
        return True


def test_a_check_creates_its_pod_reads_its_verdict_and_always_deletes_it(local_inventory):
    dep, deployments = _example(local_inventory)
    topic = {"name": "/fetch_1/execute", "robot": "fetch-1", "type": "t", "publishers": [], "rate": None,
             "subscribers": [{"node": "/fetch_1/controller"}]}  # fmt: skip
    report = {"topics": [topic], "problems": ["/fetch_1/execute: nobody publishes it"]}
    kube = FakeKube(deployments, 1, json.dumps(report) + "\n")
    verdict = GraphCheck(kube, "reg/bridge:1", timeout=5, window=1, poll=0.01).run(dep, "kuberos-test-fleet", ["fetch-1"])
    assert not verdict.ok and verdict.problems == ["/fetch_1/execute: nobody publishes it"]
    kept = kube.configmaps["kuberos-graph-pick-and-place"]
    assert kept["metadata"]["ownerReferences"][0]["uid"] == "u-1", "an undeploy removes it with the record"
    assert kept["metadata"]["labels"]["kuberos.io/graph"] == "true" and "kuberos.io/deployment" not in kept["metadata"]["labels"]
    graph = json.loads(kept["data"]["graph.json"])["robots"]["fetch-1"]
    assert graph["ok"] is False and graph["problems"] == report["problems"]
    assert graph["topics"] == [{"name": "/fetch_1/execute", "type": "t", "publishers": [], "subscribers": ["/fetch_1/controller"],
                                "rate": None}]  # fmt: skip
    (pod,) = kube.created
    assert kube.deleted == [("Pod", pod["metadata"]["name"], "kuberos-test-fleet")]
    wanted = json.loads(next(e["value"] for e in pod["spec"]["containers"][0]["env"] if e["name"] == "KUBEROS_TOPICS"))
    assert "/{robot}/plan/request" in {w["name"] for w in wanted}
    stuck = FakeKube(deployments, None, "", waiting={"reason": "ErrImagePull", "message": "no such image"})
    check = GraphCheck(stuck, "reg/bridge:1", timeout=0.1, window=0.1, start_timeout=0.2, poll=0.01)
    verdict = check.run(dep, "kuberos-test-fleet", ["fetch-1"])
    assert not verdict.ok and "did not finish within" in verdict.problems[0]
    assert "ErrImagePull: no such image" in verdict.problems[0]
    assert len(stuck.deleted) == 1
    kwok = FakeKube(deployments, 0, "")
    kwok.node_annotations = {"kwok.x-k8s.io/node": "fake"}
    verdict = GraphCheck(kwok, "reg/bridge:1", poll=0.01).run(dep, "kuberos-test-fleet", ["fetch-1"])
    assert verdict.ok and verdict.summary == "not checked: edge-1 is a kwok node, which runs no container" and not kwok.created


def test_the_controller_checks_each_declaring_deployment_on_its_robots_while_it_leads(local_inventory, monkeypatch):
    import threading
    from types import SimpleNamespace

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import graph_refresh

    dep, _deployments = _example(local_inventory)
    quiet = dataclasses.replace(dep, name="quiet", modules=tuple(dataclasses.replace(m, topics=()) for m in dep.modules))
    placement = place_modules([dep], local_inventory)
    records = {
        "a": SimpleNamespace(spec=dep, namespace="kuberos-test-fleet", deployment=dep.name, placement=placement),
        "b": SimpleNamespace(spec=quiet, namespace="kuberos-test-fleet", deployment="quiet", placement=placement),
    }

    def parse(configmap):
        if configmap["name"] == "broken":
            raise KuberosError("unreadable")
        return records[configmap["name"]]

    monkeypatch.setattr(graph_refresh, "parse_record", parse)
    runs = []

    class Check:
        def run(self, spec, namespace, robots):
            runs.append((spec.name, namespace, robots))
            if len(runs) == 1:
                raise RuntimeError("the fence refused")
            return SimpleNamespace(ok=True, summary="fine", problems=[])

    store = SimpleNamespace(snapshot=lambda: [{"name": "a"}, {"name": "b"}, {"name": "broken"}])
    controller = SimpleNamespace(records=store, leading=True, kube=None)
    refresh = graph_refresh.GraphRefresh(controller, "reg/bridge:1", 60, check=Check())
    stop = threading.Event()
    assert refresh.once(stop) == 0, "a refused check is tried again next round"
    assert refresh.once(stop) == 1
    assert runs == [("pick-and-place", "kuberos-test-fleet", ["fetch-1", "fetch-2"])] * 2, "only the declaring deployment"
    controller.leading = False
    assert refresh.once(stop) == 0 and len(runs) == 2, "a replica that does not lead checks nothing"
