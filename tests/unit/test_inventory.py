"""The resource model of the embedded inventory, latency lookups and node labels."""

from __future__ import annotations

import math

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels


def test_local_inventory_has_the_documented_site(local_inventory):
    tiers = {}
    for node in local_inventory.nodes.values():
        tiers.setdefault(node.tier, []).append(node.name)
    assert tiers == {
        "onboard": ["fetch-1", "fetch-2", "tiago-1", "tiago-2"],
        "edge": ["edge-1", "edge-2", "edge-3"],
        "cloud": ["cloud-1", "cloud-2"],
    }
    assert local_inventory.fleets == {"test-fleet": ("fetch-1", "fetch-2"), "warehouse-fleet": ("tiago-1", "tiago-2")}
    assert all(local_inventory.nodes[n].gpu == 1 for n in ("cloud-1", "cloud-2"))


def test_latency_defaults_overrides_and_other_robots(local_inventory):
    inv = local_inventory
    assert inv.latency_ms("fetch-1", "fetch-1") == 0.0
    assert inv.latency_ms("fetch-1", "edge-1") == 5.0  # group default for edge
    assert inv.latency_ms("fetch-1", "edge-3") == 3.0  # host value
    assert inv.latency_ms("fetch-1", "cloud-1") == 40.0  # kuberos_default_latency_ms.cloud
    assert inv.latency_ms("fetch-1", "cloud-2") == 180.0  # per-link override on fetch-1
    assert inv.latency_ms("fetch-2", "cloud-2") == 60.0
    assert math.isinf(inv.latency_ms("fetch-1", "fetch-2"))


def test_fleet_access(local_inventory):
    edge3 = local_inventory.nodes["edge-3"]
    assert not edge3.shared and edge3.serves_fleet("warehouse-fleet") and not edge3.serves_fleet("test-fleet")
    assert [n.name for n in local_inventory.tier_nodes("edge", "test-fleet")] == ["edge-1", "edge-2"]


def test_node_labels_follow_the_scheme(local_inventory):
    assert labels.node_labels(local_inventory.nodes["fetch-1"]) == {
        "device.kuberos.io/hostname": "fetch-1",
        "devices.kuberos.io/camera": "true",
        "devices.kuberos.io/gripper": "true",
        "fleet.kuberos.io/name": "test-fleet",
        "kuberos.io/arch": "amd64",
        "kuberos.io/role": "robot",
        "resource-group.kuberos.io/name": "test-fleet",
        "robot.kuberos.io/name": "fetch-1",
    }
    assert labels.node_labels(local_inventory.nodes["edge-3"]) == {
        "device.kuberos.io/hostname": "edge-3",
        "fleet-access.kuberos.io/warehouse-fleet": "true",
        "kuberos.io/arch": "amd64",
        "kuberos.io/role": "edge",
        "kuberos.io/shared": "false",
        "resource-group.kuberos.io/name": "site-a",
    }
    assert labels.node_taints(local_inventory.nodes["fetch-1"]) == [
        {"key": "kuberos.io/robot", "value": "fetch-1", "effect": "NoSchedule"}
    ]
    assert labels.node_taints(local_inventory.nodes["cloud-1"]) == []


def test_sample_inventory_is_a_valid_site():
    from helpers import inventory_raw

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory

    inv = load_inventory(inventory_raw("inventories/sample"))
    assert inv.fleets == {"inventory": ("scanner-01",), "picking": ("fetch-01", "fetch-02")}
    assert sorted(n for n, node in inv.nodes.items() if node.tier == "edge") == ["edge-a", "edge-b", "edge-c", "edge-d"]
    assert inv.latency_ms("fetch-02", "gpu-vm-1") == 85.0 and inv.latency_ms("fetch-01", "gpu-vm-1") == 40.0
    assert inv.nodes["scanner-01.robots.example.internal"].arch == "arm64"
