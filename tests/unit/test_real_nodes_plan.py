"""Which hosts the local cluster runs as real nodes, and what each real node registers with (pure)."""

from __future__ import annotations

import os

import pytest
from helpers import inventory_raw

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import (
    cluster_nodes,
    real_node_names,
    real_nodes,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.link_delays import rtt_ms
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import delay_fabric


def test_the_real_pods_site_is_four_real_nodes_with_labels_taints_and_delays():
    raw = inventory_raw("inventories/real-pods")
    hostvars = {host: {"kuberos_local_node": "real"} for host in raw["hosts"]}
    names = real_node_names(raw, hostvars)
    assert names == ["cloud-1", "edge-1", "edge-2", "robot-1"]
    inventory = load_inventory(raw)
    plan = real_nodes(inventory, names)
    by_name = {node["name"]: node for node in plan["nodes"]}
    robot = by_name["robot-1"]
    assert robot["tier"] == "onboard"
    assert robot["labels"][labels.FLEET] == "test-fleet" and robot["labels"][labels.DEVICE_PREFIX + "gripper"] == "true"
    assert robot["taints"] == [{"key": labels.ROBOT_TAINT, "value": "robot-1", "effect": "NoSchedule"}]
    assert by_name["edge-1"]["taints"] == [] and by_name["cloud-1"]["labels"][labels.ROLE] == "cloud"
    delays = plan["delay_ms"]
    assert delays["robot-1"]["edge-1"] == 2.5 and delays["robot-1"]["cloud-1"] == 20.0  # half of 5 ms and 40 ms
    for a in names:
        assert a not in delays[a]
        for b in names:
            if a != b:
                assert delays[a][b] == delays[b][a] == rtt_ms(inventory, a, b) / 2


def test_hosts_are_simulated_unless_marked_real_and_kwok_leaves_the_real_ones_out():
    raw = inventory_raw()
    inventory = load_inventory(raw)
    assert real_node_names(raw, {}) == []
    names = real_node_names(raw, {"fetch-1": {"kuberos_local_node": "real"}, "edge-1": {"kuberos_local_node": "simulated"}})
    assert names == ["fetch-1"]
    kwok = [node["metadata"]["name"] for node in cluster_nodes(inventory, simulated=True, exclude=names)]
    assert "fetch-1" not in kwok and len(kwok) == len(inventory.nodes) - 1


def test_a_bad_local_node_kind_names_the_host_and_the_variable():
    raw = inventory_raw()
    with pytest.raises(SpecError) as error:
        real_node_names(raw, {"edge-2": {"kuberos_local_node": "yes"}}, source="inventories/local")
    assert "inventories/local: hosts.edge-2.kuberos_local_node: 'yes' is not valid; expected real or simulated" in str(
        error.value
    )


def test_the_fabric_routes_a_network_behind_a_host_with_that_hosts_delay():
    read_a, write_a = os.pipe()
    fabric = delay_fabric.Fabric({"hosts": [], "delay_ms": {"b": {"a": 20.0}}})
    fabric.by_address[bytes([10, 232, 0, 10])] = (write_a, "a")
    fabric.by_network.append((*delay_fabric.parse_network("10.233.0.0/24"), write_a, "a"))
    try:
        packet = bytes([0x45, 0, 0, 64]) + bytes(12) + bytes([10, 233, 0, 7]) + bytes(44)  # to a pod behind a
        fabric.receive("b", packet, now=10.0)
        fabric.receive("b", packet[:16] + bytes([10, 233, 1, 7]) + packet[20:], now=10.0)  # no host has 10.233.1.0/24
        fabric.deliver_due(10.019)
        assert fabric.stats.packets == 0
        fabric.deliver_due(10.020)
        assert os.read(read_a, 65536) == packet
        assert fabric.stats.drops["unknown_destination"] == 1
    finally:
        os.close(read_a)
        os.close(write_a)


def test_a_state_folder_too_deep_for_containerds_socket_is_named_before_anything_starts():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import SUN_PATH_MAX, RealNodes

    class Plane:
        def __init__(self, root):
            self.root = root

        def path(self, *parts):
            return os.path.join(self.root, *parts)

    nodes = [{"name": "partner-1", "labels": {}, "taints": []}]
    deep = RealNodes(Plane("/tmp/" + "d" * 60), nodes, {}, {})
    socket = deep.socket("partner-1") + ".ttrpc"
    assert len(socket) > SUN_PATH_MAX
    assert f"the state folder is too deep for containerd's sockets: {socket} has {len(socket)} characters" in " ".join(
        deep.problems()
    )
    shallow = RealNodes(Plane("/tmp/s"), nodes, {}, {})
    assert not any("too deep" in problem for problem in shallow.problems())


def test_a_real_nodes_configuration_is_rendered_from_its_names_and_paths_alone():
    """The pure half of the real nodes (kuberos_cluster.real_node_config): what each program is given."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import real_node_config as config

    net = config.NodeNet("robot-1", 2, "kt", 40)
    taint = {"key": "kuberos.io/robot", "value": "robot-1", "effect": "NoSchedule"}
    kubelet = config.kubelet_config(
        net, {"taints": [taint]}, ca_file="/p/ca.crt", dns="10.40.0.1", resolv_conf="/r", socket="/s.sock", pod_logs="/l"
    )
    assert (kubelet["address"], kubelet["podCIDR"], kubelet["registerWithTaints"]) == ("10.41.0.12", "10.42.2.0/24", [taint])
    assert kubelet["containerRuntimeEndpoint"] == "unix:///s.sock" and kubelet["cgroupRoot"] == "/kt-robot-1"
    assert 'address = "/s.sock"' in config.containerd_config("/d", "/s.sock", "/cni/bin", "/cni/conf")
    assert '"subnet": "10.42.2.0/24"' in config.cni_config(net, "/ipam")
    assert config.kube_proxy_config(net, "/kp", "10.42.0.0/16")["hostnameOverride"] == "robot-1"
    assert "bind 10.40.0.1" in config.corefile("10.40.0.1", "/c.kubeconfig") and config.host_address(40) == "10.40.0.1"
