"""The live graph check: after a deploy's wait and after each rollout wave, do the modules' declared topics really
connect?

The check runs where the modules' ROS 2 traffic is: a short-lived pod in the fleet's namespace, on the node of one of
the deployment's modules (an edge or cloud one first: its ROS_DISCOVERY_SERVER lists the fleet's servers), with that
module's ROS environment. Its program is the ROS probe (``ros_graph_probe --topics``) from the collection's image
(the bridge's, which has rclpy and the collection); it joins the graph as a Fast DDS super client, so the Ansible
host needs neither rclpy nor a route to the pods. The pod is deleted when it has ended (``kuberos.topics`` judges
what the probe saw; this module only starts it and reads its verdict back).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import dns_label
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import record_name
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import by_robot, expectations
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, message

PROBE_MODULE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe"
CHECK_LABEL = "kuberos.io/graph-check"  # the deployment a check pod is for
CONTAINER = "graph-check"
# The module's environment the probe keeps: how it reaches the graph (the rest is the module's own).
ROS_ENV = ("ROS_DISCOVERY_SERVER", "RMW_IMPLEMENTATION", "ROS_DOMAIN_ID", "FASTDDS_BUILTIN_TRANSPORTS", "ROS_HOME",
           "ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE")  # fmt: skip
TIER_ORDER = {"edge": 0, "cloud": 1, "onboard": 2}
# The options of the graph check (documented by the kuberos.platform.graph_check fragment).
GRAPH_CHECK_ARGS = {
    "graph_check": {"type": "bool", "default": True},
    "graph_check_timeout": {"type": "float", "default": 30.0},
    "graph_check_window": {"type": "float", "default": 3.0},
}
FINAL_WAITING = ("ErrImagePull", "ImagePullBackOff", "InvalidImageName", "CreateContainerConfigError")
START_TIMEOUT = 180.0  # seconds for the check pod to start (its image may need a pull)


@dataclass
class Verdict:
    """What a check found: ``ok``, one line per problem, the probe's report (topics, endpoints, rates), seconds."""

    ok: bool
    problems: list[str] = field(default_factory=list)
    report: dict | None = None
    seconds: float = 0.0
    summary: str = ""

    def to_dict(self) -> dict:
        data = {"ok": self.ok, "problems": self.problems, "seconds": round(self.seconds, 2), "summary": self.summary}
        if self.report:
            data["topics"] = len(self.report.get("topics") or [])
        return data


def graph_configmap_name(deployment: str) -> str:
    return dns_label("kuberos-graph", deployment)


def declares_topics(dep) -> bool:
    return any(module.topics for module in dep.modules)


def template_of(deployments: list[dict]) -> dict | None:
    """The module Deployment whose pod the check copies: edge first, then cloud, then onboard; by name."""
    modules = [d for d in deployments if (d["metadata"].get("labels") or {}).get(labels.COMPONENT) == "ros-module"]

    def order(dep):
        tier = (dep["metadata"].get("annotations") or {}).get(labels.TIER_ANNOTATION, "onboard")
        return TIER_ORDER.get(tier, 3), dep["metadata"]["name"]

    return min(modules, key=order) if modules else None


def check_pod(template: dict, name: str, image: str, robots: list[str], wanted: list[dict], timeout: float,
              window: float) -> dict:  # fmt: skip
    """The check pod: the template module's node, tolerations and ROS environment, the probe as its program."""
    pod = template["spec"]["template"]["spec"]
    module = pod["containers"][0]
    env = [e for e in module.get("env") or () if e["name"] in ROS_ENV]
    env += [
        {"name": "ROS_SUPER_CLIENT", "value": "TRUE"},
        {"name": "KUBEROS_ROBOTS", "value": ",".join(robots)},
        {"name": "KUBEROS_TOPICS", "value": json.dumps(wanted, separators=(",", ":"), allow_nan=False)},
    ]
    if not any(e["name"] == "ROS_HOME" for e in env):
        env.append({"name": "ROS_HOME", "value": "/tmp/.ros"})
    meta = template["metadata"]
    spec = {
        "restartPolicy": "Never",
        "automountServiceAccountToken": False,
        "securityContext": pod.get("securityContext") or {"seccompProfile": {"type": "RuntimeDefault"}},
        "containers": [
            {
                "name": CONTAINER,
                "image": image,
                "command": ["python3", "-m", PROBE_MODULE],
                "args": ["--topics", "--json", "--timeout", f"{timeout:g}", "--window", f"{window:g}"],
                "env": env,
                "resources": {"requests": {"cpu": "100m", "memory": "128Mi"}, "limits": {"memory": "512Mi"}},
                "securityContext": {
                    "runAsNonRoot": True,
                    "runAsUser": 65532,
                    "runAsGroup": 65532,
                    "allowPrivilegeEscalation": False,
                    "capabilities": {"drop": ["ALL"]},
                },
            }
        ],
    }
    for key in ("nodeSelector", "tolerations", "imagePullSecrets"):
        if pod.get(key):
            spec[key] = pod[key]
    template_labels = meta.get("labels") or {}
    # Not the deployment's or KubeROS's managed labels: status, the wait and the controller count those pods as modules.
    pod_labels = {CHECK_LABEL: template_labels.get(labels.DEPLOYMENT, "")}
    if labels.FLEET in template_labels:
        pod_labels[labels.FLEET] = template_labels[labels.FLEET]
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {"name": name, "namespace": meta["namespace"], "labels": pod_labels},
        "spec": spec,
    }


def read_verdict(log: str, exit_code: int | None, seconds: float) -> Verdict:
    """The probe's verdict from its pod's log: its JSON report line and its ``ros_graph_probe:`` lines."""
    report, lines = None, []
    for line in log.splitlines():
        text = line.strip()
        if text.startswith("{") and report is None:
            try:
                report = json.loads(text)
            except ValueError:
                pass
        elif text.startswith("ros_graph_probe: "):
            lines.append(text[len("ros_graph_probe: ") :])
    if exit_code == 0:
        return Verdict(True, [], report, seconds, lines[-1] if lines else "")
    problems = (report or {}).get("problems") or lines or [f"the probe exited {exit_code}: {log.strip()[-300:] or 'no output'}"]
    return Verdict(False, list(problems), report, seconds)


def graph_check_problem(params: dict) -> str:
    """Why the graph check options are not usable, or ''."""
    if not 0 < float(params.get("graph_check_timeout", 30.0)) <= 600:
        return "graph_check_timeout must be more than 0 and at most 600 seconds"
    if not 0 < float(params.get("graph_check_window", 3.0)) <= 60:
        return "graph_check_window must be more than 0 and at most 60 seconds"
    return ""


class GraphCheck:
    """Runs the check for one deployment of one fleet namespace, on the robots given."""

    @classmethod
    def from_params(cls, kube: Kube, params: dict, progress=None) -> GraphCheck:
        return cls(kube, params["bridge_image"], float(params.get("graph_check_timeout", 30.0)),
                   float(params.get("graph_check_window", 3.0)), progress=progress)  # fmt: skip

    def __init__(self, kube: Kube, image: str, timeout: float = 30.0, window: float = 3.0,
                 start_timeout: float = START_TIMEOUT, poll: float = 0.5, progress=None):  # fmt: skip
        self.kube = kube
        self.image = image
        self.timeout = timeout
        self.window = window
        self.start_timeout = start_timeout
        self.poll = poll
        self.progress = progress or (lambda line: None)

    def run(self, dep, namespace: str, robots: list[str]) -> Verdict:
        started = time.monotonic()
        wanted = [e.to_dict() for e in expectations(dep.modules)]
        if dep.rmw != "fastdds":
            return Verdict(True, [], None, 0.0, f"not checked: the live check joins Fast DDS discovery servers ({dep.rmw})")
        selector = f"{labels.DEPLOYMENT}={dep.name}"
        template = template_of(self.kube.list("Deployment", namespace, selector=selector))
        if template is None:
            return Verdict(False, [f"no module Deployment of {dep.name} in {namespace} to run the check beside"])
        simulated = self._simulated(template)
        if simulated:
            return Verdict(True, [], None, 0.0, f"not checked: {simulated} is a kwok node, which runs no container")
        name = dns_label("kuberos-graph-check", dep.name, f"{int(time.time() * 1000) % 100000:05d}")
        pod = check_pod(template, name, self.image, robots, wanted, self.timeout, self.window)
        self.progress(f"checking the ROS graph of {dep.name}: {len(wanted)} declared topic(s) on {len(robots)} robot(s)")
        self.kube.create(pod)
        try:
            exit_code, why = self._wait(name, namespace)
            if exit_code is None:
                return Verdict(False, [why], None, time.monotonic() - started)
            log = self.kube.log(name, namespace, container=CONTAINER)
            verdict = read_verdict(log, exit_code, time.monotonic() - started)
            self.keep(dep, namespace, robots, verdict)
            return verdict
        except Exception as exc:  # the API server's refusal or an unreachable cluster: the check did not run
            return Verdict(False, [f"the check pod {name} could not be read: {message(exc)}"], None, time.monotonic() - started)
        finally:
            try:
                self.kube.delete("Pod", name, namespace, grace_seconds=0)
            except Exception:  # pylint: disable=broad-except
                pass  # a pod left behind ends on its own (restartPolicy Never); the next check has another name

    def keep(self, dep, namespace: str, robots: list[str], verdict: Verdict) -> None:
        """Write what the check saw, per robot, into the deployment's graph ConfigMap (the robots not checked now keep
        their last picture); owned by the deployment's record, so that an undeploy removes it with the record."""
        record = self.kube.get("ConfigMap", record_name(dep.name), namespace)
        name = graph_configmap_name(dep.name)
        found = self.kube.get("ConfigMap", name, namespace)
        try:
            kept = json.loads(((found or {}).get("data") or {}).get("graph.json", "{}"))
        except ValueError:
            kept = {}
        robots_seen = kept.get("robots") if isinstance(kept.get("robots"), dict) else {}
        at = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        topics = (verdict.report or {}).get("topics") or []
        for robot, part in by_robot(topics, verdict.problems, robots).items():
            robots_seen[robot] = {"at": at, **part}
        data = {"deployment": dep.name, "robots": robots_seen}
        obj = {
            "apiVersion": "v1",
            "kind": "ConfigMap",
            "metadata": {
                "name": name,
                "namespace": namespace,
                "labels": {labels.MANAGED_BY: "kuberos", labels.GRAPH: "true", labels.FLEET: dep.fleet},
                "annotations": {labels.DEPLOYMENT: dep.name},
            },
            "data": {"graph.json": json.dumps(data, separators=(",", ":"))},
        }
        if record is not None:
            obj["metadata"]["ownerReferences"] = [
                {"apiVersion": "v1", "kind": "ConfigMap", "name": record["metadata"]["name"], "uid": record["metadata"]["uid"]}
            ]
        self.kube.apply(obj)

    def _simulated(self, template: dict) -> str:
        """The node the check would run on when kwok simulates it (no container runs there), else ''."""
        where = (template["spec"]["template"]["spec"].get("nodeSelector") or {}).get(labels.HOSTNAME, "")
        nodes = self.kube.list("Node", selector=f"{labels.HOSTNAME}={where}") if where else []
        return where if nodes and all(labels.KWOK_NODE in (n["metadata"].get("annotations") or {}) for n in nodes) else ""

    def _wait(self, name: str, namespace: str) -> tuple[int | None, str]:
        """The probe's exit code once its container ended, or None and why it did not run."""
        deadline = time.monotonic() + self.start_timeout + self.timeout + self.window
        why = "it was not scheduled"
        while time.monotonic() < deadline:
            pod = self.kube.get("Pod", name, namespace) or {}
            status = pod.get("status") or {}
            for container in status.get("containerStatuses") or ():
                state = container.get("state") or {}
                if state.get("terminated"):
                    return int(state["terminated"].get("exitCode", 1)), ""
                waiting = state.get("waiting") or {}
                if waiting.get("reason") in FINAL_WAITING:
                    why = f"{waiting['reason']}: {waiting.get('message', '')}".strip()
                elif waiting.get("reason"):
                    why = waiting["reason"]
            for condition in status.get("conditions") or ():
                if condition.get("type") == "PodScheduled" and condition.get("status") == "False":
                    why = f"not scheduled: {condition.get('message', '')}"
            time.sleep(self.poll)
        return None, f"the check pod {name} did not finish within {self.start_timeout + self.timeout + self.window:g} s ({why})"
