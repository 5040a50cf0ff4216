"""The resource manager labels cluster nodes from the inventory: idempotent, with check and diff."""

from __future__ import annotations

import pytest
from helpers import playbook

pytestmark = pytest.mark.cluster


def test_labels_restored_idempotently_with_check_and_diff(cluster):
    core, _apps, _discovery = cluster.clients()

    def run(*extra):
        return playbook("label_nodes.yml", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", *extra)

    assert run().returncode == 0  # takes ownership of the labels the local cluster created
    assert run().changed == 0
    robot_taints = core.read_node("fetch-1").spec.taints
    # Somebody removes a label and a taint by hand.
    core.patch_node("edge-2", {"metadata": {"labels": {"kuberos.io/role": None}}})
    core.patch_node("fetch-1", {"spec": {"taints": [{"key": "example.com/other", "effect": "NoSchedule"}]}})
    try:
        _check_and_fix(core, run)
    finally:  # the foreign taint goes again: later tests place modules on fetch-1
        core.patch_node("fetch-1", {"spec": {"taints": [core.api_client.sanitize_for_serialization(t) for t in robot_taints]}})


def _check_and_fix(core, run):
    checked = run("--check", "--diff")
    assert checked.returncode == 0 and checked.changed >= 1, checked.stdout[-4000:]
    assert "kuberos.io/role" in checked.stdout
    assert "kuberos.io/role" not in (core.read_node("edge-2").metadata.labels or {})  # check mode changed nothing
    fixed = run()
    assert fixed.returncode == 0 and fixed.changed >= 1, fixed.stdout[-4000:]
    assert core.read_node("edge-2").metadata.labels["kuberos.io/role"] == "edge"
    taints = {(t.key, t.effect) for t in core.read_node("fetch-1").spec.taints}
    assert taints == {("kuberos.io/robot", "NoSchedule"), ("example.com/other", "NoSchedule")}  # merged, not replaced
    assert run().changed == 0
