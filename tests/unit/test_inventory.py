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


def test_link_bandwidth_and_loss_are_read_and_reach_the_labs_links():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.link_delays import (
        link_losses,
        link_rates_bps,
    )

    def site(**robot_vars):
        robot = {"kuberos_fleet": "f", "kuberos_cpu": 2, "kuberos_memory": "4Gi", **robot_vars}
        return {
            "hosts": {"r1": robot, "e1": {"kuberos_cpu": 4, "kuberos_memory": "8Gi", "kuberos_link_bandwidth": "1 Gbit/s"}},
            "groups": {"robots": ["r1"], "edge": ["e1"], "cloud": []},
        }

    inventory = load_inventory(site(kuberos_link_bandwidth="20 Mbit/s", kuberos_link_loss="2%"))
    assert (inventory.nodes["r1"].link_bps, inventory.nodes["r1"].link_loss) == (20e6, 0.02)
    assert link_rates_bps(inventory, ["r1", "e1"]) == {"r1": 20e6, "e1": 1e9}
    assert link_losses(inventory, ["r1", "e1"]) == {"r1": 0.02}
    plain = load_inventory(site(kuberos_link_bandwidth=54, kuberos_link_loss=0.5))
    assert (plain.nodes["r1"].link_bps, plain.nodes["r1"].link_loss) == (54e6, 0.005)
    for var, value, expected in (
        ("kuberos_link_bandwidth", "fast", "expected a bandwidth above zero"),
        ("kuberos_link_bandwidth", 0, "expected a bandwidth above zero"),
        ("kuberos_link_loss", "100%", "from 0 to below 100"),
        ("kuberos_link_loss", -1, "from 0 to below 100"),
    ):
        try:
            load_inventory(site(**{var: value}))
        except SpecError as exc:
            assert [p.path for p in exc.problems] == [f"hosts.r1.{var}"], exc.problems
            assert expected in exc.problems[0].message
        else:
            raise AssertionError(f"{var}: {value!r} was accepted")
