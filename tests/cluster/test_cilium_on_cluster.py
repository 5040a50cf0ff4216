"""Cilium's rendered manifests on the real local API server: check mode writes nothing, the objects pass the
server-side dry run and are applied (kwok runs the agent's pods on every node, robots included, and the operator),
a second run changes nothing, a bad CIDR fails naming the variable before anything is written. Everything is
removed afterwards: the other tests share the cluster."""

from __future__ import annotations

import json

import pytest
from helpers import playbook, remove_objects

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cilium import CiliumSettings, cilium_objects

pytestmark = pytest.mark.cluster

POD_CIDR = "10.78.0.0/16"


def test_cilium_check_apply_idempotent_and_bad_cidr(cluster, tmp_path):
    from kubernetes import client, config, dynamic

    api = config.new_client_from_config(config_file=cluster.kubeconfig)
    dyn = dynamic.DynamicClient(api)
    core, apps = client.CoreV1Api(api), client.AppsV1Api(api)
    render_dir = tmp_path / "cilium"

    def run(*extra):
        variables = {"kuberos_kubeconfig": cluster.kubeconfig, "kuberos_pod_cidr": POD_CIDR, "cilium_render_dir": str(render_dir)}
        return playbook("cilium.yml", "-e", json.dumps(variables), *extra, timeout=900)

    try:
        checked = run("--check", "--diff")
        assert checked.returncode == 0, checked.stdout[-6000:]
        assert checked.changed >= 1
        assert not render_dir.exists(), "check mode wrote files"
        assert "cilium-operator" in checked.stdout  # the diff names the objects
        assert not apps.list_namespaced_daemon_set("kube-system", field_selector="metadata.name=cilium").items

        applied = run()
        assert applied.returncode == 0, applied.stdout[-6000:]
        assert applied.changed >= 1
        assert (render_dir / "cilium.yaml").is_file()
        config_map = core.read_namespaced_config_map("cilium-config", "kube-system")
        assert config_map.data["mtu"] == "1420"  # the local inventory has cloud VMs: the VPN is the narrowest link
        assert config_map.data["ipam"] == "kubernetes" and config_map.data["tunnel-protocol"] == "vxlan"
        # cilium_wait waited for the rollout: kwok runs an agent pod on every node, tainted robots included.
        daemonset = apps.read_namespaced_daemon_set("cilium", "kube-system")
        assert daemonset.status.number_ready == daemonset.status.desired_number_scheduled == len(core.list_node().items)
        pods = core.list_namespaced_pod("kube-system", label_selector="k8s-app=cilium").items
        assert "fetch-1" in {p.spec.node_name for p in pods}
        assert apps.read_namespaced_deployment("cilium-operator", "kube-system").status.available_replicas == 1

        again = run()
        assert again.returncode == 0, again.stdout[-6000:]
        assert again.changed == 0, again.stdout[-6000:]
        rechecked = run("--check", "--diff")
        assert rechecked.returncode == 0 and rechecked.changed == 0, rechecked.stdout[-6000:]

        bad = run("-e", "kuberos_pod_cidr=10.78.0.1/33")
        assert bad.returncode != 0
        assert "cilium_pod_cidr: '10.78.0.1/33'" in bad.stdout, bad.stdout[-4000:]
        assert core.read_namespaced_config_map("cilium-config", "kube-system").data["cluster-pool-ipv4-cidr"] == POD_CIDR
    finally:
        remove_objects(dyn, core, cilium_objects(CiliumSettings(POD_CIDR)), "k8s-app in (cilium, cilium-operator)")
