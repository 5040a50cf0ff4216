"""Robots that are powered off are not failures (docs/cluster-setup.md): site.yml leaves them out of the plays that
touch machines and says so once, the CNI roles wait only for nodes whose kubelet reports
(``kuberos_cluster.cluster_nodes.agents_waiting``), and node labelling makes no Node for a host that never joined
(``not_joined``); edge servers and cloud VMs stay strict. The lab machines prove it end to end in the site chain."""

from __future__ import annotations

import os

import pytest
import yaml
from helpers import ROOT, inventory_raw

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import agents_waiting, not_joined


def _node(name: str, ready: str | None) -> dict:
    status = {"conditions": [{"type": "Ready", "status": ready}]} if ready else {}
    return {"metadata": {"name": name}, "status": status}


def _agent(node: str, ready: str, deleting: bool = False) -> dict:
    meta = {"name": f"cilium-{node}", **({"deletionTimestamp": "2026-12-06T00:00:00Z"} if deleting else {})}
    return {"metadata": meta, "spec": {"nodeName": node}, "status": {"conditions": [{"type": "Ready", "status": ready}]}}


def test_a_node_whose_kubelet_stopped_reporting_is_not_waited_for():
    nodes = [_node("edge-a", "True"), _node("robot-off", "Unknown"), _node("robot-new", "False"), _node("fresh", None)]
    pods = [_agent("edge-a", "True"), _agent("robot-off", "False"), _agent("robot-new", "False")]
    # the robot powered off is left; the robot that just joined (NotReady until its CNI runs) and a node with no
    # condition yet are waited for
    assert agents_waiting(pods, nodes) == ["fresh", "robot-new"]
    assert agents_waiting([*pods, _agent("robot-new", "True"), _agent("fresh", "True")], nodes) == []


def test_an_agent_being_deleted_does_not_count():
    nodes = [_node("edge-a", "True")]
    assert agents_waiting([_agent("edge-a", "True", deleting=True)], nodes) == ["edge-a"]
    assert agents_waiting([], []) == [] and agents_waiting(None, None) == []


def test_hosts_without_a_node_are_robots_to_leave_or_others_to_refuse():
    inventory = load_inventory(inventory_raw("inventories/sample"))
    robots = sorted(n.name for n in inventory.nodes.values() if n.tier == "onboard")
    others = sorted(n.name for n in inventory.nodes.values() if n.tier != "onboard")
    assert not_joined(inventory, [*robots, *others]) == {"robots": [], "others": []}
    assert not_joined(inventory, others) == {"robots": robots, "others": []}
    assert not_joined(inventory, robots[1:] + others[1:]) == {"robots": robots[:1], "others": others[:1]}


def _plays() -> list[dict]:
    with open(os.path.join(ROOT, "playbooks", "site.yml"), encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def test_site_yml_touches_robots_only_when_they_answered():
    plays = _plays()
    names = [p["name"] for p in plays]
    reach = names.index("Find the machines that answer")
    assert plays[reach]["hosts"] == "robots:edge:cloud" and plays[reach]["tags"] == ["always"]
    for play in plays[reach + 1 :]:
        hosts = str(play["hosts"])
        if "robots" in hosts.split(":"):
            assert "&kuberos_reached" in hosts.split(":"), (play["name"], hosts)
    assert plays[reach]["tasks"] == [
        {"name": "Find the machines that answer (kuberos_reached)", "ansible.builtin.import_tasks": "tasks/reach.yml"}
    ]
    with open(os.path.join(ROOT, "playbooks", "tasks", "reach.yml"), encoding="utf-8") as handle:
        waited = yaml.safe_load(handle)[0]  # shared with upgrade.yml
    assert waited["ansible.builtin.wait_for_connection"] and "robots" in waited["ignore_errors"], waited


@pytest.mark.parametrize("role", ["cilium", "calico"])
def test_the_cni_roles_wait_for_reporting_nodes_only(role):
    with open(os.path.join(ROOT, "roles", role, "tasks", "main.yml"), encoding="utf-8") as handle:
        tasks = yaml.safe_load(handle)
    daemonset_waits = [
        t["name"] for t in tasks
        if (t.get("kubernetes.core.k8s_info") or {}).get("kind") == "DaemonSet"
        or ((t.get("kubernetes.core.k8s") or {}).get("wait") and "others" in str(t["kubernetes.core.k8s"]["definition"]))
    ]  # fmt: skip
    assert not daemonset_waits, "a DaemonSet's rollout waits for every node, a powered-off robot's too"
    assert any("kuberos.platform.agents_waiting" in str(t.get("until", "")) for t in tasks)


def test_admin_conf_is_written_0600_and_never_shown():
    fetch = next(p for p in _plays() if p["name"].startswith("Fetch the administrator's kubeconfig"))
    modules = [next(k for k in t if k.startswith("ansible.builtin.")) for t in fetch["tasks"]]
    assert "ansible.builtin.fetch" not in modules  # fetch writes with the umask's mode (0644)
    touch = next(t for t in fetch["tasks"] if (t.get("ansible.builtin.file") or {}).get("state") == "touch")
    copy = next(t for t in fetch["tasks"] if "ansible.builtin.copy" in t)
    assert touch["ansible.builtin.file"]["mode"] == "0600" and copy["ansible.builtin.copy"]["mode"] == "0600"
    assert copy["no_log"] is True and copy["diff"] is False
    assert modules.index("ansible.builtin.file") < modules.index("ansible.builtin.copy")
