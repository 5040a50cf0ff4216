"""Cloud burst end to end on the real control plane: a scaled shared planner whose edge server has room for one
instance only. Its load asks for a second; the controller finds no node, writes what the fleet lacks, and runs
the provisioner (playbooks/cloud.yml with cloud_vms_burst, against moto's EC2 server started here); the VM becomes
a kwok node of the fleet, the controller places the second instance there, and after the peak it drains that
instance and has the idle VM released (terminated in the emulator, its node removed). The budget allows one VM.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time

import pytest
import yaml
from helpers import ROOT, MotoServer
from test_controller import wait_for
from test_scaling_on_cluster import watched_controller

FLEET = "burst-fleet"
NAMESPACE = f"kuberos-{FLEET}"
SITE = "burst"
FIRST, SECOND = "burst-planning-motion-planner-shared-0", "burst-planning-motion-planner-shared-1"
VM = f"{SITE}-{FLEET}-cloud-1"
SPEC = """\
metadata: {name: burst-planning, targetFleet: burst-fleet}
discovery: {servers: 1}
rosModules:
- name: motion-planner
  image: ghcr.io/kuberos/pnp-planner:0.2.0
  launch: [python3 -m kuberos_pnp.planner]
  preference: [edge, cloud]
  resources: {cpu: 600m, memory: 256Mi}
  strategy: shared
  robotsPerInstance: 2
  scaling: {maxInstances: 2, metric: kuberos_planner_queue_depth, target: 1, scaleDownWindow: 6s, drainTime: 3s}
"""
# Two robots of a fleet of their own (no onboard module: they need no node) and one edge server with room for the
# fleet's discovery server and one planner (1 CPU: 100m + 600m, and 600m more do not fit). No cloud VM at deploy.
INVENTORY = {
    "all": {
        "vars": {"kuberos_pin_images": False},  # kwok nodes: no registry serves the spec's images
        "children": {
            "robots": {
                "vars": {"kuberos_cpu": 4, "kuberos_memory": "8Gi"},
                "hosts": {"burst-1": {"kuberos_fleet": FLEET}, "burst-2": {"kuberos_fleet": FLEET}},
            },
            "edge": {
                "hosts": {
                    "edge-3": {"kuberos_fleets": [FLEET], "kuberos_cpu": 1, "kuberos_memory": "4Gi", "kuberos_latency_ms": 3}
                }
            },
        },
    }
}
REPORT_ENV = "KUBEROS_BURST_REPORT"
BUDGET = {"max_vms": 1, "instance_types": {"t3.large": {"cpu": 2, "memory": "8Gi", "hourly_price": 0.0832}}}


@pytest.fixture(scope="module")
def burst(cluster, tmp_path_factory):
    work = tmp_path_factory.mktemp("burst")
    site = work / "site"
    site.mkdir()
    (site / "hosts.yml").write_text(yaml.safe_dump(INVENTORY))
    spec = work / "burst-planning.yml"
    spec.write_text(SPEC)
    moto = MotoServer(work / "moto.log").start()
    moto.image_id = moto.ec2().describe_images()["Images"][0]["ImageId"]
    env = {
        **os.environ, "PYTHONPATH": os.path.join(ROOT, ".collections"), "AWS_ACCESS_KEY_ID": "AKIAKUBEROSBURSTTEST",
        "AWS_SECRET_ACCESS_KEY": "burst-secret-not-for-output", "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"),
    }  # fmt: skip
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN"):
        env.pop(name, None)
    deployed = subprocess.run(
        [os.path.join(os.path.dirname(sys.executable), "ansible-playbook"), "playbooks/deploy.yml", "-i", str(site),
         "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={work / 'render'}",
         "-e", f"kuberos_kubeconfig={cluster.kubeconfig}"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    settings = {
        "cloud_vms_burst": True, "cloud_vms_release_after": 5, "cloud_vms_site": SITE, "cloud_vms_budget": BUDGET,
        "cloud_vms_endpoint_url": moto.url, "cloud_vms_region": moto.REGION, "cloud_vms_image_id": moto.image_id,
        "cloud_vms_kubeconfig": cluster.kubeconfig, "cloud_vms_wait_timeout": 60, "cloud_vms_latency_ms": 30,
    }  # fmt: skip
    command = [os.path.join(os.path.dirname(sys.executable), "ansible-playbook"), os.path.join(ROOT, "playbooks", "cloud.yml"),
               "-i", str(site), "-e", json.dumps(settings)]  # fmt: skip
    core, apps, _ = cluster.clients()
    burst_args = ("--burst-command", shlex.join(command), "--burst-release-after", "5")
    try:
        with watched_controller(cluster, work, NAMESPACE, *burst_args, env=env) as (exporters, _prometheus, log):
            yield {"core": core, "apps": apps, "exporters": exporters, "moto": moto, "log": log, "site": site}
    finally:
        subprocess.run(
            [os.path.join(os.path.dirname(sys.executable), "ansible-playbook"), "playbooks/undeploy.yml", "-i", str(site),
             "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}"],
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=600, check=False,
        )  # fmt: skip
        for node in core.list_node(label_selector=f"fleet-access.kuberos.io/{FLEET}=true").items:
            if node.metadata.name != "edge-3":
                core.delete_node(node.metadata.name)
        moto.stop()


def _log(state) -> str:
    state["log"].seek(0)
    return state["log"].read()[-5000:]


def _vms(state, *states) -> dict[str, str]:
    """VM name -> state in the emulator."""
    found = {}
    for reservation in state["moto"].ec2().describe_instances()["Reservations"]:
        for item in reservation["Instances"]:
            tags = {t["Key"]: t["Value"] for t in item.get("Tags", [])}
            if not states or item["State"]["Name"] in states:
                found[tags.get("Name", item["InstanceId"])] = item["State"]["Name"]
    return found


def _planners(state) -> dict[str, str]:
    """instance -> the node its Deployment is pinned to."""
    items = state["apps"].list_namespaced_deployment(NAMESPACE, label_selector="kuberos.io/deployment=burst-planning").items
    return {d.metadata.name: d.spec.template.spec.node_selector.get("device.kuberos.io/hostname") for d in items}


def _sync(state) -> None:
    pods = state["core"].list_namespaced_pod(NAMESPACE, label_selector="kuberos.io/deployment=burst-planning").items
    running = {p.metadata.name: p.metadata.labels["kuberos.io/instance"] for p in pods if p.status.phase == "Running"}
    state["exporters"].publish(running)


def _demand(state) -> dict:
    data = state["core"].read_namespaced_config_map("kuberos-capacity", NAMESPACE).data
    return json.loads(data["demand.json"])


def test_a_peak_the_edge_cannot_hold_gets_a_cloud_vm_which_is_released_after(burst):
    state, exporters = burst, burst["exporters"]
    wait_for(lambda: _sync(state) or FIRST in exporters.servers, 60, "the first planner Running")
    assert _planners(state) == {FIRST: "edge-3"} and _vms(state) == {}
    marks = {"peak": time.monotonic()}
    exporters.values[FIRST] = 3.0  # three times the target: two instances wanted, the edge holds one

    wait_for(lambda: _vms(state, "running"), 120, "a VM launched for the fleet", lambda: _log(state))
    marks["vm_running"] = time.monotonic()
    assert list(_vms(state, "pending", "running")) == [VM], "the budget allows one VM"
    wait_for(lambda: _planners(state).get(SECOND) == VM, 120, "the second planner placed on the VM", lambda: _log(state))
    wait_for(lambda: _sync(state) or SECOND in exporters.servers, 60, "the second planner Running")
    marks["placed"] = time.monotonic()
    blocked = state["core"].list_namespaced_event(NAMESPACE, field_selector="reason=ModuleScaleBlocked").items
    assert blocked and "no node" in blocked[0].message
    assert _demand(state)["instances"] == 0, "once placed, the fleet lacks nothing"

    exporters.values[FIRST] = exporters.values[SECOND] = 0.0  # the peak is over
    marks["peak_over"] = time.monotonic()
    wait_for(lambda: SECOND not in _planners(state), 60, "the VM's planner drained and removed", lambda: _log(state))
    wait_for(lambda: _vms(state, "terminated") == {VM: "terminated"}, 120, "the idle VM released", lambda: _log(state))
    marks["released"] = time.monotonic()
    wait_for(lambda: not [n for n in state["core"].list_node().items if n.metadata.name == VM], 30, "its node removed")
    assert _planners(state) == {FIRST: "edge-3"}, "the edge planner stayed where it was"
    wait_for(lambda: f"released ['{VM}']" in _log(state), 60, "the provisioner's run reported", lambda: _log(state))
    text = _log(state)
    assert f"launched ['{VM}']" in text
    assert "burst-secret-not-for-output" not in text, "credentials never reach the controller's log"
    robots = state["core"].read_namespaced_config_map("burst-planning-motion-planner-robots", NAMESPACE).data
    assert robots == {FIRST: "burst-1,burst-2"}
    if os.environ.get(REPORT_ENV):  # the burst figures for bench/results/scaling.json (bench/RESULTS.md says how)
        figures = {
            "vms_provisioned": len(_vms(state)),
            "vms_released": len(_vms(state, "terminated")),
            "peak_to_vm_running_s": round(marks["vm_running"] - marks["peak"], 1),
            "peak_to_instance_running_s": round(marks["placed"] - marks["peak"], 1),
            "peak_over_to_vm_released_s": round(marks["released"] - marks["peak_over"], 1),
            "release_after_s": 5, "scale_down_window_s": 6, "drain_s": 3,
        }  # fmt: skip
        with open(os.environ[REPORT_ENV], "w", encoding="utf-8") as handle:
            json.dump(figures, handle, indent=1)
