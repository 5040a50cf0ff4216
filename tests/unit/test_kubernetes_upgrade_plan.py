"""The upgrade's plan (kuberos_cluster/upgrade.py): one minor at a time, robots offline left pending, refusals that
name both versions."""

from __future__ import annotations

import pytest

from ansible_collections.kuberos.platform.plugins.filter.kubernetes_upgrade_plan import kubernetes_upgrade_plan
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.upgrade import parse_version, upgrade_plan


def node(name: str, version: str) -> dict:
    return {"metadata": {"name": name}, "status": {"nodeInfo": {"kubeletVersion": version}}}


SITE = [("edge-a", "control_plane"), ("edge-b", "control_plane"), ("edge-c", "control_plane"), ("edge-d", "worker"),
        ("cloud-1", "worker"), ("fetch-01", "robot"), ("fetch-02", "robot")]  # fmt: skip


def hosts(offline=()):
    return [{"host": h, "node": h, "kind": k, "reached": h not in offline} for h, k in SITE]


def nodes(version="v1.33.7", **others):
    return [node(h, others.get(h.replace("-", "_"), version)) for h, _ in SITE]


def test_a_minor_upgrade_applies_on_the_first_control_plane_and_upgrades_every_node():
    plan = upgrade_plan("v1.34.4", "v1.33.7", nodes(), hosts())
    assert plan["refusal"] == "" and plan["apply"] and plan["apply_host"] == "edge-a"
    assert plan["upgrade"] == [h for h, _ in SITE] and not plan["pending"]
    assert plan["lines"][0] == "Kubernetes v1.33.7 -> v1.34.4"


def test_a_run_cut_off_half_way_is_finished_and_an_offline_robot_is_left_pending():
    plan = upgrade_plan("v1.34.4", "v1.34.4", nodes(edge_a="v1.34.4", edge_b="v1.34.4"), hosts(offline=("fetch-02",)))
    assert plan["refusal"] == "" and not plan["apply"]
    assert plan["done"] == ["edge-a", "edge-b"] and plan["pending"] == ["fetch-02"]
    assert plan["upgrade"] == ["edge-c", "edge-d", "cloud-1", "fetch-01"]
    assert plan["hosts"]["fetch-02"]["why"].startswith("does not answer")


def test_nothing_to_do_when_every_node_is_there():
    plan = upgrade_plan("v1.34.4", "v1.34.4", nodes("v1.34.4"), hosts())
    assert plan["refusal"] == "" and not plan["apply"] and not plan["upgrade"] and plan["lines"][-1] == "nothing to do"


@pytest.mark.parametrize(
    "target, cluster, expected",
    [
        ("v1.35.4", "v1.33.7", "kuberos_kubernetes_version v1.35.4 is 2 minor versions above the cluster's v1.33.7: "
         "upgrade one minor version at a time (first to a v1.34 release)"),
        ("v1.33.1", "v1.33.7", "kuberos_kubernetes_version v1.33.1 is older than the cluster's v1.33.7"),
        ("1.34.4", "v1.33.7", "kuberos_kubernetes_version: '1.34.4' is not a Kubernetes version such as v1.34.4"),
        ("v1.34.4-rc.1", "v1.33.7", "is not a Kubernetes version"),
        ("v2.0.0", "v1.33.7", "changes the major version"),
        ("v1.34.4", "", "the cluster's version (kubeadm-config's kubernetesVersion) is ''"),
    ],
)  # fmt: skip
def test_refusals_name_both_versions(target, cluster, expected):
    plan = upgrade_plan(target, cluster, nodes(), hosts())
    assert expected in plan["refusal"], plan["refusal"]
    assert not plan["upgrade"] and not plan["apply"]


def test_a_control_plane_or_worker_that_does_not_answer_refuses_the_run():
    plan = upgrade_plan("v1.34.4", "v1.33.7", nodes(), hosts(offline=("edge-b", "cloud-1")))
    assert "edge-b (a control plane) does not answer" in plan["refusal"]
    assert "cloud-1 (a worker) does not answer" in plan["refusal"]


def test_a_node_newer_than_the_target_refuses_the_run():
    plan = upgrade_plan("v1.34.4", "v1.34.4", nodes("v1.34.4", fetch_01="v1.35.0"), hosts())
    assert plan["refusal"] == "fetch-01 (node fetch-01) runs kubelet v1.35.0, newer than kuberos_kubernetes_version v1.34.4"


def test_a_robot_two_minors_behind_is_left_behind_and_one_too_far_behind_refuses():
    plan = upgrade_plan("v1.34.4", "v1.33.7", nodes(fetch_01="v1.32.3"), hosts())
    assert plan["refusal"] == "" and plan["behind"] == ["fetch-01"]
    assert "with a v1.33 release first" in plan["hosts"]["fetch-01"]["why"]
    plan = upgrade_plan("v1.34.4", "v1.33.7", nodes(fetch_02="v1.30.0"), hosts(offline=("fetch-02",)))
    assert "would stay at kubelet v1.30.0, more than 3 minor versions below v1.34.4" in plan["refusal"]


def test_a_host_that_never_joined_is_left_to_site_yml():
    plan = upgrade_plan("v1.34.4", "v1.33.7", [n for n in nodes() if n["metadata"]["name"] != "fetch-02"], hosts())
    assert plan["not_joined"] == ["fetch-02"] and "fetch-02" not in plan["upgrade"]


def test_hostile_input_is_a_refusal_not_a_crash():
    plan = upgrade_plan("v1.34.4", "v1.33.7", [None, "x", {"metadata": None}, node("edge-a", "banana")], hosts())
    assert "its kubelet's version 'banana' is not a version" in plan["refusal"]
    plan = upgrade_plan("v1.34.4", "v1.33.7", nodes(), [{"host": "x", "kind": "printer", "reached": True}])
    assert "kind 'printer' is not one of control_plane, worker, robot" in plan["refusal"]
    assert parse_version("v1.2.3\n") == (1, 2, 3) and parse_version(None) is None and parse_version("v1.2") is None


def test_the_filter_gives_the_same_plan():
    assert kubernetes_upgrade_plan("v1.34.4", "v1.33.7", nodes(), hosts()) == upgrade_plan("v1.34.4", "v1.33.7", nodes(), hosts())
