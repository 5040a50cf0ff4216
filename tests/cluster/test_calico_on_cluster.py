"""Calico's published release (its calico-vxlan.yaml, from Calico's Go module: scripts/calico-manifest.sh) through the
calico role on the real local API server: an unpinned download is refused; check mode writes nothing; the CRDs (Calico's
own schemas) are applied and Established, the other objects pass the server-side dry run and are applied (kwok runs
calico-node's pods, robots included); a second run changes nothing; a copy that does not match its checksum and a bad
CIDR fail naming the variable before anything is written. Calico's programs do not run here (docs/cluster-setup.md).
Everything is removed afterwards: the other tests share the cluster."""

from __future__ import annotations

import hashlib
import json

import pytest
import yaml
from helpers import CALICO_RELEASE as RELEASE
from helpers import calico_published_manifest, playbook, remove_objects

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import CalicoSettings, calico_objects

pytestmark = pytest.mark.cluster

POD_CIDR = "10.77.0.0/16"


def test_calico_release_check_apply_idempotent_and_refusals(cluster, tmp_path):
    from kubernetes import client, config, dynamic

    manifest = calico_published_manifest()
    with open(manifest, "rb") as handle:
        checksum = "sha256:" + hashlib.sha256(handle.read()).hexdigest()
    api = config.new_client_from_config(config_file=cluster.kubeconfig)
    dyn = dynamic.DynamicClient(api)
    core, apps = client.CoreV1Api(api), client.AppsV1Api(api)
    render_dir = tmp_path / "calico"
    pinned = {"calico_manifest_file": manifest, "calico_manifest_checksum": checksum}

    def run(*extra, **variables):
        variables = {
            "kuberos_kubeconfig": cluster.kubeconfig, "kuberos_pod_cidr": POD_CIDR, "calico_render_dir": str(render_dir),
            "calico_version": RELEASE, "calico_manifest_dir": str(tmp_path / "downloads"), **variables,
        }  # fmt: skip
        return playbook("calico.yml", "-e", json.dumps(variables), *extra, timeout=900)

    try:
        unpinned = run()  # the URL without a checksum: refused before any download
        assert unpinned.returncode != 0
        assert "calico_manifest_checksum" in unpinned.stdout and "does not pin" in unpinned.stdout, unpinned.stdout[-3000:]
        assert not (tmp_path / "downloads").exists()

        checked = run("--check", "--diff", **pinned)
        assert checked.returncode == 0, checked.stdout[-6000:]
        assert checked.changed >= 1
        assert not _crd_names(dyn, manifest), "check mode created CRDs"
        assert not render_dir.exists(), "check mode wrote files"
        assert "calico-node" in checked.stdout  # the diff names the objects

        applied = run(**pinned)
        assert applied.returncode == 0, applied.stdout[-6000:]
        assert applied.changed >= 1
        assert (render_dir / "01-crds.yaml").is_file() and (render_dir / "02-calico.yaml").is_file()
        crds = dyn.resources.get(api_version="apiextensions.k8s.io/v1", kind="CustomResourceDefinition")
        names = _crd_names(dyn, manifest, expected=True)
        assert len(names) >= 17
        for name in names:
            conditions = {c["type"]: c["status"] for c in crds.get(name=name).to_dict()["status"]["conditions"]}
            assert conditions.get("Established") == "True", name
        config_map = core.read_namespaced_config_map("calico-config", "kube-system")
        assert config_map.data["veth_mtu"] == "1370"  # the local inventory has cloud VMs: VXLAN over the VPN
        daemonset = apps.read_namespaced_daemon_set("calico-node", "kube-system")
        node = daemonset.spec.template.spec.containers[0]
        assert {e.name: e.value for e in node.env}["CALICO_IPV4POOL_CIDR"] == POD_CIDR
        assert node.image == f"quay.io/calico/node:{RELEASE}"
        # calico_wait waited for the rollout: kwok runs a calico-node pod on every node, tainted robots included.
        assert daemonset.status.number_ready == daemonset.status.desired_number_scheduled == len(core.list_node().items)
        pods = core.list_namespaced_pod("kube-system", label_selector="k8s-app=calico-node").items
        assert "fetch-1" in {p.spec.node_name for p in pods}

        again = run(**pinned)
        assert again.returncode == 0, again.stdout[-6000:]
        assert again.changed == 0, again.stdout[-6000:]
        rechecked = run("--check", "--diff", **pinned)
        assert rechecked.returncode == 0 and rechecked.changed == 0, rechecked.stdout[-6000:]

        tampered = run(**{**pinned, "calico_manifest_checksum": "sha256:" + "0" * 64})
        assert tampered.returncode != 0
        assert "does not match calico_manifest_checksum" in tampered.stdout, tampered.stdout[-3000:]
        bad = run("-e", "kuberos_pod_cidr=10.77.0.1/33", **pinned)
        assert bad.returncode != 0
        assert "calico_pod_cidr: '10.77.0.1/33'" in bad.stdout, bad.stdout[-4000:]
        env = {
            e.name: e.value
            for e in apps.read_namespaced_daemon_set("calico-node", "kube-system").spec.template.spec.containers[0].env
        }
        assert env["CALICO_IPV4POOL_CIDR"] == POD_CIDR  # nothing was written
    finally:
        remove_objects(dyn, core, _objects(manifest), "k8s-app in (calico-node, calico-kube-controllers)")


def _objects(manifest: str) -> list[dict]:
    with open(manifest, encoding="utf-8") as handle:
        return calico_objects(list(yaml.safe_load_all(handle)), CalicoSettings(POD_CIDR, version=RELEASE))


def _crd_names(dyn, manifest: str, expected=False):
    """Calico's CRD names that exist in the cluster (all of them when ``expected``)."""
    names = [o["metadata"]["name"] for o in _objects(manifest) if o["kind"] == "CustomResourceDefinition"]
    if expected:
        return names
    crds = dyn.resources.get(api_version="apiextensions.k8s.io/v1", kind="CustomResourceDefinition")
    present = {item["metadata"]["name"] for item in crds.get().to_dict()["items"]}
    return [name for name in names if name in present]
