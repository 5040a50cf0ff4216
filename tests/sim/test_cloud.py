"""The simulator's cloud (``kuberos_sim.cloud``) deciding on its own: launches within the budget, a VM still booting
counted as joining (no second launch for the same demand), a node made once the boot is over, release only after
the quiet period and only of a VM that runs nothing. The hosts side is a recorder here (the real runtime is in
test_scaler.py's burst test); the decisions are the role's own functions."""

from __future__ import annotations

import os
import sys
from types import SimpleNamespace

import pytest
from helpers import ROOT

sys.path[:0] = [os.path.join(ROOT, "sim")]

from kuberos_sim import cloud as sim_cloud  # noqa: E402

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory  # noqa: E402

# pure computation, no hosts nor processes: the api lane (tests/conftest.py), beside the host lane

BUDGET = {"max_vms": 2, "instance_types": {"t3.small": {"cpu": 1, "memory": "2Gi"}}}
SITE = {
    "hosts": {
        "r1": {"kuberos_fleet": "f", "kuberos_cpu": 1, "kuberos_memory": "1Gi"},
        "e1": {"kuberos_cpu": 1, "kuberos_memory": "1Gi"},
    },
    "groups": {"robots": ["r1"], "edge": ["e1"]},
}


class Hosts:
    """What SimCloud asks of the runtime: an inventory, hosts added and removed, the processes running."""

    def __init__(self):
        self.inventory = load_inventory(SITE)
        self.added, self.removed = [], []
        self.processes = {}

    def add_host(self, node, inventory):
        assert node in inventory.nodes and inventory.nodes[node].tier == "cloud"
        self.inventory = inventory
        self.added.append(node)

    def remove_host(self, node):
        self.removed.append(node)


def demand(instances: int, previous=None, at: float = 1000.0) -> dict:
    shortfalls = [capacity.Shortfall("f", "app", "planner", 1000, 2**28, 0, "no node")] * instances
    return capacity.advance(previous, capacity.demand(shortfalls).get("f"), capacity.stamp(at))


def test_launch_boot_node_and_release_after_the_quiet_period(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(sim_cloud.time, "monotonic", lambda: clock[0])
    hosts = Hosts()
    cloud = sim_cloud.SimCloud(hosts, "f", budget=BUDGET, boot_s=5.0, release_after_s=20.0).start()
    wanted = demand(1)
    assert cloud.reconcile(wanted, 1000.0)[0].startswith("launched: sim-f-cloud-1 t3.small")
    clock[0] = 2.0
    assert cloud.reconcile(wanted, 1002.0) == [] and len(cloud.vms) == 1, "booting: counted as joining, no second VM"
    assert cloud.nodes() == [] and hosts.added == []
    clock[0] = 5.0
    assert cloud.reconcile(wanted, 1005.0)[0].startswith("node: sim-f-cloud-1")
    (node,) = cloud.nodes()
    assert (node.name, node.tier, node.cpu_millis, node.fleets, node.latency_ms) == ("sim-f-cloud-1", "cloud", 1000, ("f",), 50.0)
    hosts.processes = {"planner": SimpleNamespace(host="sim-f-cloud-1", running=True)}
    quiet = demand(0, wanted, at=1010.0)
    assert cloud.reconcile(quiet, 1040.0) == [], "in use: kept however long the fleet is quiet"
    hosts.processes = {}
    assert cloud.reconcile(quiet, 1025.0) == [], "idle, but quiet for 15 of 20 s"
    assert cloud.reconcile(quiet, 1031.0)[0].startswith("released: sim-f-cloud-1")
    assert hosts.removed == ["sim-f-cloud-1"] and cloud.live() == []
    summary = cloud.summary()
    assert (summary["vms_provisioned"], summary["vms_released"], summary["vms_left_at_end"]) == (1, 1, 0)


def test_the_budget_caps_the_vms_and_says_why_once(monkeypatch):
    monkeypatch.setattr(sim_cloud.time, "monotonic", lambda: 0.0)
    cloud = sim_cloud.SimCloud(Hosts(), "f", budget=BUDGET, boot_s=5.0).start()
    first = cloud.reconcile(demand(5), 1000.0)  # 5 planners of 1 CPU: 5 VMs of 1 CPU wanted, 2 allowed
    assert [line.split(":")[0] for line in first] == ["launched", "launched", "refused"]
    assert "at most 2 VM(s)" in first[-1]
    assert cloud.reconcile(demand(5), 1001.0) == [], "the refusal is said once while it stands"
    assert len(cloud.vms) == 2
    assert [e["vm"] for e in cloud.log if e["event"] == "launched"] == ["sim-f-cloud-1", "sim-f-cloud-2"]


def test_a_vm_left_at_the_end_is_released_and_counted_apart(monkeypatch):
    monkeypatch.setattr(sim_cloud.time, "monotonic", lambda: 10.0)
    hosts = Hosts()
    cloud = sim_cloud.SimCloud(hosts, "f", budget=BUDGET, boot_s=0.0).start()
    cloud.reconcile(demand(1), 1000.0)
    cloud.reconcile(demand(1), 1001.0)  # a node now
    assert cloud.release_all() == ["released: sim-f-cloud-1 the run ended"] and hosts.removed == ["sim-f-cloud-1"]
    assert (cloud.summary()["vms_released"], cloud.summary()["vms_left_at_end"]) == (0, 1)


def test_a_bad_budget_is_named_by_field():
    with pytest.raises(SpecError, match=r"cloud_vms_budget.max_vms"):
        sim_cloud.SimCloud(Hosts(), "f", budget={"max_vms": -1, "instance_types": {"t3.small": {"cpu": 1, "memory": "1Gi"}}})
