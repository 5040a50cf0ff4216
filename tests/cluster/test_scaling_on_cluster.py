"""Scaling a shared module on the real control plane (kwok nodes): the controller reads the module's own load
gauge from a real Prometheus, which scrapes real exporters standing for the instances' pods (kwok pods run no
process; each exporter is labelled with its pod's namespace and name through file-based discovery, as a PodMonitor
labels a real pod's series), and scales between 1 and 2 instances: up at once, never down while the load flaps
within the window, and down with a drain: the robots move to the instance that stays before the other stops.
"""

from __future__ import annotations

import contextlib
import http.server
import json
import os
import subprocess
import sys
import threading
import time

import pytest
from helpers import ROOT
from test_controller import wait_for
from test_dashboard import Prometheus

NAMESPACE = "kuberos-test-fleet"
METRIC = "kuberos_planner_queue_depth"
SPEC = """\
metadata: {name: scaled-planning, targetFleet: test-fleet}
rosModules:
- name: motion-planner
  image: ghcr.io/kuberos/pnp-planner:0.2.0
  launch: [python3 -m kuberos_pnp.planner]
  preference: edge
  resources: {cpu: 500m, memory: 256Mi}
  strategy: shared
  robotsPerInstance: 2
  scaling: {minInstances: 1, maxInstances: 2, metric: kuberos_planner_queue_depth, target: 2,
            scaleDownWindow: 8s, drainTime: 4s}
"""
ROBOTS_MAP = "scaled-planning-motion-planner-robots"
FIRST, SECOND = "scaled-planning-motion-planner-shared-0", "scaled-planning-motion-planner-shared-1"


class Exporters:
    """One HTTP exporter per instance, its gauge set by the test; Prometheus finds them through a targets file."""

    def __init__(self, targets_file: str, namespace: str = NAMESPACE):
        self.targets_file = targets_file
        self.namespace = namespace
        self.values: dict[str, float] = {}
        self.servers: dict[str, http.server.ThreadingHTTPServer] = {}
        self.publish({})

    def _server(self, instance: str) -> int:
        if instance not in self.servers:
            values = self.values

            class Handler(http.server.BaseHTTPRequestHandler):
                def do_GET(self):
                    body = f"# TYPE {METRIC} gauge\n{METRIC} {values.get(instance, 0.0)}\n".encode()
                    self.send_response(200)
                    self.send_header("Content-Type", "text/plain; version=0.0.4")
                    self.end_headers()
                    self.wfile.write(body)

                def log_message(self, *args):
                    pass

            server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
            threading.Thread(target=server.serve_forever, daemon=True).start()
            self.servers[instance] = server
        return self.servers[instance].server_address[1]

    def publish(self, pods: dict[str, str]) -> None:
        """pods: pod name -> instance. Written atomically: Prometheus watches the file."""
        groups = [
            {"targets": [f"127.0.0.1:{self._server(inst)}"], "labels": {"namespace": self.namespace, "pod": pod}}
            for pod, inst in sorted(pods.items())
        ]
        with open(self.targets_file + ".tmp", "w", encoding="utf-8") as handle:
            json.dump(groups, handle)
        os.replace(self.targets_file + ".tmp", self.targets_file)

    def close(self):
        for server in self.servers.values():
            server.shutdown()
            server.server_close()


@contextlib.contextmanager
def watched_controller(cluster, work, namespace: str, *extra: str, env=None):
    """A controller process (no leader election, 1 s resync) that reads module gauges from a real Prometheus, which
    scrapes one exporter per instance pod (``Exporters``); yields (exporters, prometheus, the controller's log)."""
    exporters = Exporters(str(work / "targets.json"), namespace=namespace)
    discovery = [{"files": [exporters.targets_file], "refresh_interval": "1s"}]
    prometheus = Prometheus(str(work), {}, [{"job_name": "modules", "file_sd_configs": discovery}])
    log = open(work / "controller.log", "w+", encoding="utf-8")
    controller = subprocess.Popen(
        [sys.executable, "-m", "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller",
         "--kubeconfig", cluster.kubeconfig, "--grace", "2", "--resync", "1", "--no-leader-elect", "--dashboard-port", "0",
         "--prometheus-url", f"http://127.0.0.1:{prometheus.port}", *extra],
        stdout=log, stderr=subprocess.STDOUT, env=env or {**os.environ, "PYTHONPATH": os.path.join(ROOT, ".collections")},
        cwd=ROOT,
    )  # fmt: skip
    try:
        yield exporters, prometheus, log
    finally:
        controller.terminate()
        try:
            controller.wait(15)
        except subprocess.TimeoutExpired:
            controller.kill()
        prometheus.close()
        exporters.close()
        log.close()


@pytest.fixture(scope="module")
def scaled(cluster, tmp_path_factory):
    work = tmp_path_factory.mktemp("scaling")
    spec = work / "scaled-planning.yml"
    spec.write_text(SPEC)
    deployed = cluster.deploy(str(spec), work / "render")
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    core, apps, _ = cluster.clients()
    with watched_controller(cluster, work, NAMESPACE) as (exporters, prometheus, log):
        yield {"core": core, "apps": apps, "exporters": exporters, "prometheus": prometheus, "log": log, "spec": str(spec)}
    undeployed = cluster.undeploy(str(spec))  # after the controller stopped: nothing re-creates what is removed
    assert undeployed.returncode == 0, undeployed.stdout[-3000:]
    left = apps.list_namespaced_deployment(NAMESPACE, label_selector="kuberos.io/deployment=scaled-planning").items
    assert [d.metadata.name for d in left] == [], "undeploy removes the instances scaling added too"


def _controller_log(state) -> str:
    state["log"].seek(0)
    return state["log"].read()[-4000:]


def _pods(state) -> dict[str, tuple[str, str]]:
    """instance -> (pod name, uid) of its Running pod."""
    found = {}
    for pod in state["core"].list_namespaced_pod(NAMESPACE, label_selector="kuberos.io/deployment=scaled-planning").items:
        if pod.status.phase == "Running" and not pod.metadata.deletion_timestamp:
            found[pod.metadata.labels["kuberos.io/instance"]] = (pod.metadata.name, pod.metadata.uid)
    return found


def _sync_targets(state) -> dict[str, tuple[str, str]]:
    pods = _pods(state)
    state["exporters"].publish({name: inst for inst, (name, _uid) in pods.items()})
    return pods


def _instances(state) -> list[str]:
    items = state["apps"].list_namespaced_deployment(NAMESPACE, label_selector="kuberos.io/deployment=scaled-planning").items
    return sorted(d.metadata.name for d in items if "motion-planner" in d.metadata.name)


def _robots(state) -> dict[str, str]:
    return state["core"].read_namespaced_config_map(ROBOTS_MAP, NAMESPACE).data or {}


def _events(state, reason: str) -> list[str]:
    items = state["core"].list_namespaced_event(NAMESPACE, field_selector=f"reason={reason}").items
    return [e.message for e in items if "motion-planner" in (e.message or "")]


def test_a_shared_module_scales_up_holds_through_flapping_and_drains_on_the_way_down(scaled):
    state, exporters = scaled, scaled["exporters"]
    wait_for(lambda: FIRST in _sync_targets(state), 60, "the first instance Running")
    assert _instances(state) == [FIRST] and _robots(state) == {FIRST: "fetch-1,fetch-2"}
    first_pod = _pods(state)[FIRST]
    exporters.values[FIRST] = 1.0  # half the target: one instance is enough, and it is the minimum
    state["prometheus"].wait(f"sum({METRIC})", lambda v: v == 1.0, "the first instance's gauge in Prometheus")
    time.sleep(3)
    assert _instances(state) == [FIRST]

    # Up: 5 waiting requests against a target of 2 asks for 3 instances; the policy allows 2.
    exporters.values[FIRST] = 5.0
    wait_for(lambda: _instances(state) == [FIRST, SECOND], 20, "a second instance", lambda: _controller_log(state))
    wait_for(lambda: SECOND in _sync_targets(state), 60, "the second instance Running")
    wait_for(lambda: _robots(state) == {FIRST: "fetch-1", SECOND: "fetch-2"}, 20, "fetch-2 handed over once Ready",
             lambda: f"{_robots(state)}\n{_controller_log(state)}")  # fmt: skip
    assert _pods(state)[FIRST] == first_pod, "the instance that stays keeps its pod (its robots come from a file)"
    (up,) = _events(state, "ModuleScaledUp")
    assert "1 -> 2 instances" in up and "fetch-2 to " + SECOND in up
    status = json.loads(state["core"].read_namespaced_config_map("kuberos-status-scaled-planning", NAMESPACE).data["status.json"])
    assert status["scaling"][0]["instances"] == 2 and status["scaling"][0]["metric"] == METRIC

    # Flapping: the load swings between none and a lot every 2 s for 14 s; an 8 s window never sees only "low".
    exporters.values[SECOND] = 1.0
    deadline = time.monotonic() + 14
    high = True
    while time.monotonic() < deadline:
        exporters.values[FIRST] = exporters.values[SECOND] = 6.0 if high else 0.0
        high = not high
        time.sleep(2)
        assert _instances(state) == [FIRST, SECOND], "no scale-down while the load flaps within the window"
    assert _events(state, "ModuleScaledDown") == []

    # Down: no load. After the 8 s window the newest instance's robot moves back first; the instance stops after 4 s.
    exporters.values[FIRST] = exporters.values[SECOND] = 0.0
    wait_for(lambda: _robots(state) == {FIRST: "fetch-1,fetch-2", SECOND: ""}, 30, "fetch-2 moved back",
             lambda: f"{_robots(state)}\n{_controller_log(state)}")  # fmt: skip
    moved_at = time.monotonic()
    assert SECOND in _instances(state), "the drained instance still runs right after its robot moved away"
    wait_for(lambda: _instances(state) == [FIRST], 20, "the drained instance removed", lambda: _controller_log(state))
    assert time.monotonic() - moved_at >= 2.5, "it ran on for about its drain time (4 s) after its robots left"
    assert _pods(state)[FIRST] == first_pod, "the instance that stays never restarted"
    (down,) = _events(state, "ModuleScaledDown")
    assert "2 -> 1 instances" in down and SECOND + " drains for 4 s" in down
    assert _events(state, "ModuleInstanceStopped")
    assert _robots(state) == {FIRST: "fetch-1,fetch-2"}
