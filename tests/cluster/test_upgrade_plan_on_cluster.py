"""playbooks/upgrade.yml's plan on a real API server: the cluster's version from kubeadm-config, each Node's kubelet,
the machines that answer; check mode says what would happen and stops, a skipped minor is refused by name.

The API server is the local control plane of this folder (not kubeadm's): the test writes kubeadm-config's
ClusterConfiguration and three Nodes of its own (no kubelet behind them: their status is written through the API, as a
kubelet would), and removes them after. The inventory's machines are this machine (local connection) and a robot
whose SSH port on loopback does not answer (powered off).
"""

from __future__ import annotations

import pytest
import yaml
from helpers import playbook
from kubernetes.client.rest import ApiException

pytestmark = pytest.mark.cluster

NODES = {"upgrade-cp-1": "v1.33.7", "upgrade-edge-1": "v1.33.7", "upgrade-robot-1": "v1.33.7", "upgrade-robot-2": "v1.33.7"}


@pytest.fixture()
def kubeadm_site(cluster, tmp_path):
    core = cluster.clients()[0]
    config = {"apiVersion": "kubeadm.k8s.io/v1beta4", "kind": "ClusterConfiguration", "kubernetesVersion": "v1.33.7"}
    core.create_namespaced_config_map(
        "kube-system", {"metadata": {"name": "kubeadm-config"}, "data": {"ClusterConfiguration": yaml.safe_dump(config)}}
    )
    for name, version in NODES.items():
        core.create_node({"metadata": {"name": name, "labels": {"kuberos.io/test": "upgrade-plan"}}})
        core.patch_node_status(name, {"status": {"nodeInfo": {"kubeletVersion": version}}})
    inventory = tmp_path / "inventory.yml"
    local = {"ansible_connection": "local", "ansible_python_interpreter": "{{ ansible_playbook_python }}"}
    inventory.write_text(yaml.safe_dump({"all": {
        "vars": {"kuberos_kubeconfig": str(cluster.kubeconfig), "kuberos_robot_reach_timeout": 3},
        "children": {
            "control_plane": {"hosts": {"upgrade-cp-1": local}},
            "edge": {"hosts": {"upgrade-cp-1": local, "upgrade-edge-1": local}},
            "robots": {"hosts": {
                "upgrade-robot-1": local,
                # a robot that is off: nothing listens on this loopback port
                "upgrade-robot-2": {"ansible_host": "127.0.0.1", "ansible_port": 9, "ansible_user": "nobody"},
            }},
        },
    }}))  # fmt: skip
    yield inventory
    for name in NODES:
        try:
            core.delete_node(name)
        except ApiException:
            pass
    core.delete_namespaced_config_map("kubeadm-config", "kube-system")


def _run(inventory, target, *extra):
    done = playbook("upgrade.yml", "-e", f"kuberos_kubernetes_version={target}", *extra, inventory=inventory, timeout=300)
    done.said = " ".join(done.stdout.split())  # the YAML callback folds long messages at its width
    return done


def test_check_mode_says_what_the_upgrade_does_and_changes_nothing(cluster, kubeadm_site):
    done = _run(kubeadm_site, "v1.34.4", "--check")
    out = done.said
    assert done.returncode == 0, out[-4000:] + done.stderr[-2000:]
    assert "Kubernetes v1.33.7 -> v1.34.4" in out
    assert "kubeadm upgrade apply v1.34.4 on upgrade-cp-1" in out
    assert (
        "to upgrade, one at a time (control planes, workers; robots in place): upgrade-cp-1, upgrade-edge-1, upgrade-robot-1"
        in out
    )
    assert "left pending (offline): upgrade-robot-2" in out
    # check mode stops at the plan: no node's play ran
    assert "Upgrade this control plane" not in out and "Install kubeadm at the new version" not in out
    core = cluster.clients()[0]
    assert {core.read_node(n).status.node_info.kubelet_version for n in NODES} == {"v1.33.7"}


def test_a_skipped_minor_and_a_downgrade_are_refused_naming_both_versions(cluster, kubeadm_site):
    skipped = _run(kubeadm_site, "v1.35.4")
    assert skipped.returncode != 0
    assert ("Nothing was changed: kuberos_kubernetes_version v1.35.4 is 2 minor versions above the cluster's v1.33.7: "
            "upgrade one minor version at a time (first to a v1.34 release)") in skipped.said  # fmt: skip
    older = _run(kubeadm_site, "v1.32.9")
    assert older.returncode != 0 and "v1.32.9 is older than the cluster's v1.33.7" in older.said
    core = cluster.clients()[0]
    assert {core.read_node(n).status.node_info.kubelet_version for n in NODES} == {"v1.33.7"}
