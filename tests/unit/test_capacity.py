"""What a fleet lacks (``kuberos.capacity``), and nodes that joined after deploy (``labels.node_from_cluster``)."""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity, labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import Node


def test_demand_sums_per_fleet_and_advance_keeps_when_it_began_and_ended():
    items = [
        capacity.Shortfall("f", "app", "planner", 500, 2**28, 0, "no node"),
        capacity.Shortfall("f", "app", "planner", 500, 2**28, 0, "no node"),
        capacity.Shortfall("g", "other", "perception", 250, 2**27, 1, "stranded"),
    ]
    demand = capacity.demand(items)
    assert demand["f"] == {"instances": 2, "cpu_millis": 1000, "memory_bytes": 2**29, "gpu": 0, "modules": ["app/planner"]}
    assert demand["g"]["gpu"] == 1
    first = capacity.advance(None, demand["f"], "T1")
    assert first["since"] == "T1" and first["quiet_since"] == ""
    assert capacity.advance(first, demand["f"], "T2")["since"] == "T1"
    quiet = capacity.advance(first, None, "T3")
    assert quiet["instances"] == 0 and quiet["quiet_since"] == "T3"
    assert capacity.advance(quiet, None, "T4")["quiet_since"] == "T3"


def test_a_cluster_node_with_kuberos_labels_reads_back_as_the_node_it_was_made_from():
    node = Node("local-f-cloud-1", "cloud", 2000, 8 * 1024**3, 0, arch="amd64", fleets=("f",), shared=False,
                resource_group="cloud-eu", latency_ms=35.0)  # fmt: skip
    obj = {
        "metadata": {"name": node.name, "labels": labels.node_labels(node), "annotations": {labels.LATENCY_ANNOTATION: "35"}},
        "status": {"allocatable": {"cpu": "2", "memory": "8Gi", "pods": "110"}},
    }
    assert labels.node_from_cluster(obj, 50.0) == node
    obj["metadata"]["annotations"] = {}
    assert labels.node_from_cluster(obj, 50.0).latency_ms == 50.0
    robot = Node("r1", "onboard", 1000, 2**30, robot="r1", fleet="f")
    assert labels.node_from_cluster({"metadata": {"name": "r1", "labels": labels.node_labels(robot)}}, 5.0) is None
    assert labels.node_from_cluster({"metadata": {"name": "plain"}}, 5.0) is None
    obj["status"]["allocatable"]["cpu"] = "lots"
    assert labels.node_from_cluster(obj, 50.0) is None
