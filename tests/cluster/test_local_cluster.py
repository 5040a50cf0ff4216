"""The local control plane itself: secure, idempotent, and with the inventory's nodes."""

from __future__ import annotations

import ssl
import urllib.error
import urllib.request

import pytest
from helpers import TEST_PORTS

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cluster_nodes import cluster_nodes

pytestmark = pytest.mark.cluster


def test_every_inventory_node_is_a_ready_node_with_labels_taints_and_capacity(cluster, local_inventory):
    core, _apps, _discovery = cluster.clients()
    nodes = {n.metadata.name: n for n in core.list_node().items}
    expected = cluster_nodes(local_inventory, simulated=True)
    assert sorted(nodes) == sorted(n["metadata"]["name"] for n in expected)
    for want in expected:
        node = nodes[want["metadata"]["name"]]
        for key, value in want["metadata"]["labels"].items():
            assert node.metadata.labels.get(key) == value, (node.metadata.name, key)
        assert any(c.type == "Ready" and c.status == "True" for c in node.status.conditions)
        for resource, amount in want["status"]["capacity"].items():
            assert node.status.allocatable[resource] == amount, (node.metadata.name, resource)
        taints = [(t.key, t.value, t.effect) for t in node.spec.taints or []]
        if want["metadata"]["labels"][labels.ROLE] == "robot":
            assert (labels.ROBOT_TAINT, want["metadata"]["labels"][labels.ROBOT], "NoSchedule") in taints


def test_starting_twice_changes_nothing(cluster):
    assert cluster.first_start.changed >= 1
    again = cluster.start()
    assert again.returncode == 0, again.stdout[-3000:]
    assert again.changed == 0, again.stdout[-3000:]


def test_anonymous_access_is_refused(cluster):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_control_plane import LocalControlPlane

    plane = LocalControlPlane(cluster.state_dir, {})
    context = ssl.create_default_context(cafile=plane.path("pki", "ca.crt"))
    server = plane.server.replace("16443", str(TEST_PORTS["apiserver"]))
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(server + "/api/v1/namespaces", context=context, timeout=5)
    assert refused.value.code == 401
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"http://127.0.0.1:{TEST_PORTS['apiserver']}/version", timeout=5)
