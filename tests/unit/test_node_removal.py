"""Removing a node (playbooks/remove_node.yml): which deployments need a pass first, what a pass without the host
places, and the playbooks' order of work (pass, drain, delete; the host reset after; the inventory's change last)."""

from __future__ import annotations

import copy
import os

import pytest
import yaml
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.filter.fleet_inventory import fleet_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import RECORD_LABEL, build_records
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.node_removal import removal_plan

EXAMPLE = os.path.join(ROOT, "examples", "pick-and-place.yml")


def _groups_and_hostvars(raw: dict) -> tuple[dict, dict]:
    """Ansible's ``groups`` and ``hostvars`` for a plain-data inventory (what the filter is given)."""
    groups = {name: list(hosts) for name, hosts in raw["groups"].items()}
    return groups, copy.deepcopy(raw["hosts"])


class FakeKube:
    """The reads removal_plan makes: record ConfigMaps, the Node, the pods on it."""

    def __init__(self, configmaps, node=None, pods=()):
        self.configmaps, self.node, self.pods = configmaps, node, list(pods)

    def list(self, kind, namespace="", selector="", field_selector=""):
        if kind == "ConfigMap":
            assert selector == f"{RECORD_LABEL}=true" and namespace == ""
            return self.configmaps
        assert kind == "Pod" and field_selector.startswith("spec.nodeName=")
        return [p for p in self.pods if p["spec"]["nodeName"] == field_selector.split("=", 1)[1]]

    def get(self, kind, name, namespace=""):
        assert kind == "Node"
        return self.node if self.node and self.node["metadata"]["name"] == name else None


@pytest.fixture(scope="module")
def deployed(local_raw):
    with open(EXAMPLE, encoding="utf-8") as handle:
        text = handle.read()
    inventory = load_inventory(local_raw)
    deployments = load_rosdeployments(text, EXAMPLE)
    placement = place_modules(deployments, inventory)
    objects = build_records(text, EXAMPLE, deployments, placement, local_raw, RenderOptions(), "kuberos", {})
    records = [o for o in objects if RECORD_LABEL in o["metadata"]["labels"]]
    return {"text": text, "deployments": deployments, "placement": placement, "records": records}


def test_a_robot_with_modules_needs_its_deployments_pass_and_a_node_with_nothing_none(deployed):
    placement = deployed["placement"]
    robot_node = next(i.node for i in placement.instances if i.tier == "onboard")
    plan = removal_plan(FakeKube(deployed["records"]), robot_node)
    assert plan["node"] == {"name": robot_node, "exists": False, "ready": False, "unschedulable": False}
    assert [p["deployment"] for p in plan["passes"]] == sorted(
        {i.deployment for i in placement.instances if i.node == robot_node}
    )
    assert all(p["revision"] == 1 and p["on_node"] for p in plan["passes"]), plan["passes"]
    used = {i.node for i in placement.instances} | {s.node for servers in placement.discovery.values() for s in servers}
    idle = next(n for n in ("edge-1", "edge-2", "edge-3", "cloud-1", "cloud-2") if n not in used)
    assert removal_plan(FakeKube(deployed["records"]), idle)["passes"] == []


def test_a_fleets_discovery_server_on_the_node_passes_every_deployment_of_the_fleet(deployed):
    server = next(s for servers in deployed["placement"].discovery.values() for s in servers)
    plan = removal_plan(FakeKube(deployed["records"]), server.node)
    assert any(server.name in p["on_node"] for p in plan["passes"]), plan["passes"]


def test_an_unreadable_record_is_named_and_the_drain_only_counts_what_it_evicts(deployed):
    broken = copy.deepcopy(deployed["records"][0])
    broken["binaryData"] = {}
    node = {"metadata": {"name": "edge-1"}, "spec": {"unschedulable": True},
            "status": {"conditions": [{"type": "Ready", "status": "True"}]}}  # fmt: skip
    pods = [
        {"metadata": {"namespace": "kube-system", "name": "cilium-x", "ownerReferences": [{"kind": "DaemonSet"}]},
         "spec": {"nodeName": "edge-1"}},
        {"metadata": {"namespace": "kube-system", "name": "etcd-edge-1", "annotations": {"kubernetes.io/config.mirror": "x"}},
         "spec": {"nodeName": "edge-1"}},
        {"metadata": {"namespace": "kuberos-picking", "name": "planner-abc", "ownerReferences": [{"kind": "ReplicaSet"}]},
         "spec": {"nodeName": "edge-1"}},
    ]  # fmt: skip
    plan = removal_plan(FakeKube([broken], node, pods), "edge-1")
    assert plan["node"] == {"name": "edge-1", "exists": True, "ready": True, "unschedulable": True}
    assert plan["pods"] == ["kuberos-picking/planner-abc"] and plan["passes"] == []
    assert len(plan["unreadable"]) == 1 and broken["metadata"]["name"] in plan["unreadable"][0], plan["unreadable"]


def test_the_pass_without_the_host_places_nothing_there_and_keeps_the_other_robots(deployed, local_raw):
    placement = deployed["placement"]
    robot_node = next(i.node for i in placement.instances if i.tier == "onboard")
    groups, hostvars = _groups_and_hostvars(local_raw)
    host = next(h for h, v in local_raw["hosts"].items() if v.get("kuberos_node_name", h) == robot_node)
    without = fleet_inventory(groups, hostvars, without=[host])
    assert host not in without["hosts"] and all(host not in members for members in without["groups"].values())
    again = place_modules(deployed["deployments"], load_inventory(without), previous=placement)
    assert again.on_node(robot_node) == []
    kept = {i.name: i.node for i in placement.instances if robot_node not in (i.node, *i.robots)}
    assert {i.name: i.node for i in again.instances if i.name in kept} == kept


def _tasks(path: str) -> list[str]:
    with open(os.path.join(ROOT, path), encoding="utf-8") as handle:
        plays = yaml.safe_load(handle)
    return [f"{play['name']} / {task['name']}" for play in plays for task in play.get("tasks") or []]


def test_remove_node_passes_before_it_drains_deletes_then_resets_the_host_and_says_what_the_inventory_needs():
    names = _tasks("playbooks/remove_node.yml")
    order = ["Cordon the node", "Pass the deployments, or give the node back", "Drain the node", "Delete the Node",
             "Reset it (kubeadm reset", "Say it"]  # fmt: skip
    found = [next(i for i, name in enumerate(names) if step in name) for step in order]
    assert found == sorted(found), list(zip(order, found, strict=True))


def test_reset_yml_asks_for_the_sites_first_control_plane_and_resets_workers_before_control_planes():
    with open(os.path.join(ROOT, "playbooks/reset.yml"), encoding="utf-8") as handle:
        plays = yaml.safe_load(handle)
    assert "reset_site" in plays[0]["tasks"][0]["ansible.builtin.assert"]["that"]
    hosts = [play["hosts"] for play in plays]
    workers = hosts.index("robots:edge:cloud:&kuberos_reached:!control_plane")
    control_planes = hosts.index("control_plane:&kuberos_reached")
    assert workers < control_planes
    roles = plays[control_planes]["roles"]
    reset = next(r for r in roles if r["role"] == "kuberos.platform.node_reset")
    assert reset["vars"] == {"node_reset_control_plane": True, "node_reset_skip_phases": ["remove-etcd-member"]}
