"""Calico's rendered manifests on the real local API server: check mode writes nothing, the CRDs are
applied and Established, the other objects pass the server-side dry run and are applied (kwok runs
calico-node's pods, robots included), a second run changes nothing, a bad CIDR fails naming the variable.
Everything is removed afterwards: the other tests share the cluster."""

from __future__ import annotations

import json
import time

import pytest
from helpers import playbook

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import CalicoSettings, calico_objects

pytestmark = pytest.mark.cluster

POD_CIDR = "10.77.0.0/16"


def test_calico_check_apply_idempotent_and_bad_cidr(cluster, tmp_path):
    from kubernetes import client, config, dynamic

    api = config.new_client_from_config(config_file=cluster.kubeconfig)
    dyn = dynamic.DynamicClient(api)
    core, apps = client.CoreV1Api(api), client.AppsV1Api(api)
    render_dir = tmp_path / "calico"

    def run(*extra):
        variables = {"kuberos_kubeconfig": cluster.kubeconfig, "kuberos_pod_cidr": POD_CIDR, "calico_render_dir": str(render_dir)}
        return playbook("calico.yml", "-e", json.dumps(variables), *extra, timeout=900)

    try:
        checked = run("--check", "--diff")
        assert checked.returncode == 0, checked.stdout[-6000:]
        assert checked.changed >= 1
        assert not _crd_names(dyn), "check mode created CRDs"
        assert not render_dir.exists(), "check mode wrote files"
        assert "calico-node" in checked.stdout  # the diff names the objects

        applied = run()
        assert applied.returncode == 0, applied.stdout[-6000:]
        assert applied.changed >= 1
        assert (render_dir / "01-crds.yaml").is_file() and (render_dir / "02-calico.yaml").is_file()
        crds = dyn.resources.get(api_version="apiextensions.k8s.io/v1", kind="CustomResourceDefinition")
        for name in _crd_names(dyn, expected=True):
            conditions = {c["type"]: c["status"] for c in crds.get(name=name).to_dict()["status"]["conditions"]}
            assert conditions.get("Established") == "True", name
        pools = dyn.resources.get(api_version="crd.projectcalico.org/v1", kind="IPPool")
        pool = pools.get(name="default-ipv4-ippool").to_dict()
        assert pool["spec"]["cidr"] == POD_CIDR and pool["spec"]["vxlanMode"] == "Always"
        config_map = core.read_namespaced_config_map("calico-config", "kube-system")
        assert config_map.data["veth_mtu"] == "1370"  # the local inventory has cloud VMs: VXLAN over the VPN
        daemonset = apps.read_namespaced_daemon_set("calico-node", "kube-system")
        env = {e.name: e.value for e in daemonset.spec.template.spec.containers[0].env}
        assert env["CALICO_IPV4POOL_CIDR"] == POD_CIDR
        # calico_wait waited for the rollout: kwok runs a calico-node pod on every node, tainted robots included.
        assert daemonset.status.number_ready == daemonset.status.desired_number_scheduled == len(core.list_node().items)
        pods = core.list_namespaced_pod("kube-system", label_selector="k8s-app=calico-node").items
        assert "fetch-1" in {p.spec.node_name for p in pods}

        again = run()
        assert again.returncode == 0, again.stdout[-6000:]
        assert again.changed == 0, again.stdout[-6000:]
        rechecked = run("--check", "--diff")
        assert rechecked.returncode == 0 and rechecked.changed == 0, rechecked.stdout[-6000:]

        bad = run("-e", "kuberos_pod_cidr=10.77.0.1/33")
        assert bad.returncode != 0
        assert "calico_pod_cidr: '10.77.0.1/33'" in bad.stdout, bad.stdout[-4000:]
        assert pools.get(name="default-ipv4-ippool").to_dict()["spec"]["cidr"] == POD_CIDR  # nothing was written
    finally:
        _remove_calico(dyn, core)


def _crd_names(dyn, expected=False):
    """Calico's CRD names that exist in the cluster (all of them when ``expected``)."""
    names = [o["metadata"]["name"] for o in calico_objects(CalicoSettings(POD_CIDR)) if o["kind"] == "CustomResourceDefinition"]
    if expected:
        return names
    crds = dyn.resources.get(api_version="apiextensions.k8s.io/v1", kind="CustomResourceDefinition")
    present = {item["metadata"]["name"] for item in crds.get().to_dict()["items"]}
    return [name for name in names if name in present]


def _remove_calico(dyn, core):
    """Delete every object the role creates, newest first, and wait until calico's pods are gone."""
    from kubernetes.dynamic.exceptions import NotFoundError, ResourceNotFoundError

    for obj in reversed(calico_objects(CalicoSettings(POD_CIDR))):
        try:
            resource = dyn.resources.get(api_version=obj["apiVersion"], kind=obj["kind"])
            resource.delete(name=obj["metadata"]["name"], namespace=obj["metadata"].get("namespace"))
        except (NotFoundError, ResourceNotFoundError):
            pass
    deadline = time.monotonic() + 120
    selector = "k8s-app in (calico-node, calico-kube-controllers)"
    while core.list_namespaced_pod("kube-system", label_selector=selector).items and time.monotonic() < deadline:
        time.sleep(1)
    for pod in core.list_namespaced_pod("kube-system", label_selector=selector).items:
        core.delete_namespaced_pod(pod.metadata.name, "kube-system", grace_period_seconds=0)
