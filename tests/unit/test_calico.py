"""Calico from its published release: the MTU table, settings validation, and the adaptation of Calico's own
``calico-vxlan.yaml`` to a site (images from the site's registry, the pod CIDR, the MTU, nothing else changed).

A small manifest in the published one's shape checks each rule; Calico's real published manifest (taken from its Go
module by scripts/calico-manifest.sh, which ``make test`` runs) is adapted whole and validated against the Kubernetes
1.34 schema."""

from __future__ import annotations

import copy
import re

import kubernetes_validate
import pytest
import yaml
from helpers import CALICO_RELEASE, calico_published_manifest

from ansible_collections.kuberos.platform.plugins.filter.calico_manifests import calico_manifests
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import (
    CONFIG_HASH_ANNOTATION,
    CalicoSettings,
    calico_objects,
    pod_mtu,
    settings_from,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cni import tolerates

KUBERNETES_VERSION = "1.34"
RELEASE = CALICO_RELEASE  # the release whose manifest the Go module proxy serves
ROBOT_TAINT = {"key": "kuberos.io/robot", "value": "fetch-1", "effect": "NoSchedule"}


def published(tag: str = RELEASE) -> list[dict]:
    """The objects of a manifest in the shape of Calico's calico-vxlan.yaml (the parts the role touches)."""
    env = [
        {"name": "DATASTORE_TYPE", "value": "kubernetes"},
        {"name": "CALICO_IPV4POOL_IPIP", "value": "Never"},
        {"name": "CALICO_IPV4POOL_VXLAN", "value": "Always"},
        {"name": "FELIX_VXLANMTU", "valueFrom": {"configMapKeyRef": {"name": "calico-config", "key": "veth_mtu"}}},
    ]
    node = {
        "initContainers": [{"name": "install-cni", "image": f"docker.io/calico/cni:{tag}"}],
        "containers": [{"name": "calico-node", "image": f"docker.io/calico/node:{tag}", "env": env,
                        "resources": {"requests": {"cpu": "250m"}}}],
        "tolerations": [{"effect": "NoSchedule", "operator": "Exists"}, {"operator": "Exists", "effect": "NoExecute"}],
    }  # fmt: skip
    controllers = {"containers": [{"name": "calico-kube-controllers", "image": f"docker.io/calico/kube-controllers:{tag}"}]}
    return [
        {"apiVersion": "policy/v1", "kind": "PodDisruptionBudget", "metadata": {"name": "calico-kube-controllers"}},
        {"apiVersion": "v1", "kind": "ConfigMap", "metadata": {"name": "calico-config", "namespace": "kube-system"},
         "data": {"veth_mtu": "0", "calico_backend": "vxlan"}},
        {"apiVersion": "apiextensions.k8s.io/v1", "kind": "CustomResourceDefinition",
         "metadata": {"name": "ippools.crd.projectcalico.org"}},
        {"apiVersion": "apps/v1", "kind": "DaemonSet", "metadata": {"name": "calico-node", "namespace": "kube-system"},
         "spec": {"template": {"spec": node}}},
        {"apiVersion": "apps/v1", "kind": "Deployment", "metadata": {"name": "calico-kube-controllers"},
         "spec": {"template": {"spec": controllers}}},
        None,  # an empty YAML document, as the published file has
    ]  # fmt: skip


def one(objects, kind):
    found = [o for o in objects if o["kind"] == kind]
    assert len(found) == 1, kind
    return found[0]


def node_container(objects):
    return one(objects, "DaemonSet")["spec"]["template"]["spec"]["containers"][0]


def env_of(objects):
    return {e["name"]: e.get("value", e.get("valueFrom")) for e in node_container(objects)["env"]}


@pytest.mark.parametrize(
    ("base", "vpn", "expected"),
    [(1500, False, 1450), (1500, True, 1370), (9000, False, 8950), (9000, True, 1370), (1460, False, 1410)],
)
def test_pod_mtu(base, vpn, expected):
    assert pod_mtu(base, vpn) == expected


@pytest.mark.parametrize(("settings", "veth_mtu"), [({}, "1450"), ({"vpn": True}, "1370"), ({"base_mtu": 9000}, "8950")])
def test_the_mtu_goes_to_the_config_map_and_rolls_calico_node(settings, veth_mtu):
    objects = calico_objects(published(), CalicoSettings("10.244.0.0/16", version=RELEASE, **settings))
    assert one(objects, "ConfigMap")["data"]["veth_mtu"] == veth_mtu
    # Felix's VXLAN MTU still reads it from the ConfigMap, as published
    assert env_of(objects)["FELIX_VXLANMTU"] == {"configMapKeyRef": {"name": "calico-config", "key": "veth_mtu"}}
    hashes = {
        one(calico_objects(published(), CalicoSettings("10.244.0.0/16", version=RELEASE, vpn=vpn)), "DaemonSet")["spec"][
            "template"
        ]["metadata"]["annotations"][CONFIG_HASH_ANNOTATION]
        for vpn in (False, True)
    }
    assert len(hashes) == 2


def test_the_pool_and_the_node_settings_reach_calico_node():
    settings = CalicoSettings(
        "10.77.0.0/16", version=RELEASE, block_size=24, encapsulation_mode="CrossSubnet", nat_outgoing=False,
        ip_autodetection_method="kubernetes-internal-ip", node_cpu_request="0",
    )  # fmt: skip
    objects = calico_objects(published(), settings)
    env = env_of(objects)
    assert env["CALICO_IPV4POOL_CIDR"] == "10.77.0.0/16" and env["CALICO_IPV4POOL_BLOCK_SIZE"] == "24"
    assert env["CALICO_IPV4POOL_VXLAN"] == "CrossSubnet" and env["CALICO_IPV4POOL_IPIP"] == "Never"
    assert env["CALICO_IPV4POOL_NAT_OUTGOING"] == "false" and env["IP_AUTODETECTION_METHOD"] == "kubernetes-internal-ip"
    assert "cpu" not in node_container(objects)["resources"]["requests"]
    assert [e["name"] for e in node_container(objects)["env"]].count("CALICO_IPV4POOL_VXLAN") == 1  # set in place


def test_images_come_from_the_sites_registry_and_nothing_else_changes():
    before = published()
    objects = calico_objects(before, CalicoSettings("10.244.0.0/16", version=RELEASE, image_registry="mirror.site:5000/calico"))
    images = {
        c["image"]
        for o in objects
        if o["kind"] in ("DaemonSet", "Deployment")
        for c in o["spec"]["template"]["spec"].get("initContainers", []) + o["spec"]["template"]["spec"]["containers"]
    }
    assert images == {f"mirror.site:5000/calico/{name}:{RELEASE}" for name in ("node", "cni", "kube-controllers")}
    assert before == published(), "the published objects given in are not changed"
    assert [o["kind"] for o in objects] == [
        "CustomResourceDefinition", "PodDisruptionBudget", "ConfigMap", "DaemonSet", "Deployment",
    ]  # fmt: skip
    assert one(objects, "PodDisruptionBudget") == published()[0]


def test_calico_node_keeps_its_published_tolerations_robots_included():
    objects = calico_objects(published(), CalicoSettings("10.244.0.0/16", version=RELEASE))
    assert tolerates(one(objects, "DaemonSet")["spec"]["template"]["spec"], ROBOT_TAINT)


@pytest.mark.parametrize(
    ("manifest", "words"),
    [
        ([], ["holds no Kubernetes objects"]),
        ([o for o in published() if o and o["kind"] != "ConfigMap"], ["no ConfigMap calico-config"]),
        ([o for o in published() if o and o["kind"] != "DaemonSet"], ["no DaemonSet calico-node"]),
        (published("v3.30.0"), ["is Calico v3.30.0's manifest, not v3.28.5's (calico_version)"]),
    ],
)
def test_a_manifest_that_is_not_the_releases_is_refused_naming_it(manifest, words):
    with pytest.raises(KuberosError) as raised:
        calico_objects(manifest, CalicoSettings("10.244.0.0/16", version=RELEASE), source="/tmp/calico-vxlan.yaml")
    message = str(raised.value)
    assert "/tmp/calico-vxlan.yaml" in message
    for word in words:
        assert word in message, message


@pytest.mark.parametrize(
    ("changes", "variable", "words"),
    [
        ({"pod_cidr": "10.244.0.1/16"}, "calico_pod_cidr", ["'10.244.0.1/16'", "host bits set", "'10.244.0.0/16'"]),
        ({"pod_cidr": "10.244.0.0/33"}, "calico_pod_cidr", ["'10.244.0.0/33'", "not an IPv4 or IPv6 network"]),
        ({"pod_cidr": "10.244.0.0"}, "calico_pod_cidr", ["no prefix length"]),
        ({"pod_cidr": 42}, "calico_pod_cidr", ["42 (int)", "CIDR notation"]),
        ({"pod_cidr": "fd00:10:244::/56"}, "calico_pod_cidr", ["IPv6", "IPv4 pool"]),
        ({"block_size": 19}, "calico_block_size", ["19", "from 20 to 32"]),
        ({"block_size": "big"}, "calico_block_size", ["'big'", "from 20 to 32"]),
        ({"pod_cidr": "10.244.0.0/28", "block_size": 26}, "calico_block_size", ["larger than the pod CIDR", "at least 28"]),
        ({"encapsulation_mode": "crosssubnet"}, "calico_encapsulation_mode", ["did you mean 'CrossSubnet'"]),
        ({"base_mtu": 70000}, "calico_base_mtu", ["70000", "from 576 to 9216"]),
        ({"base_mtu": True}, "calico_base_mtu", ["True (bool)"]),
        ({"base_mtu": 600, "vpn": True}, "calico_base_mtu", ["MTU of 550", "WireGuard", "minimum of 576"]),
        ({"vpn_mtu": 100}, "calico_vpn_mtu", ["100", "from 1280 to 9000"]),
        ({"vpn": "yes"}, "calico_vpn", ["'yes'", "not a boolean"]),
        ({"ip_autodetection_method": "iface=eth0"}, "calico_ip_autodetection_method", ["'iface=eth0'", "can-reach="]),
        ({"ip_autodetection_method": "cidr=10.0.0.0/33"}, "calico_ip_autodetection_method", ["'10.0.0.0/33'"]),
        ({"version": "3.31"}, "calico_version", ["'3.31'", "release tag"]),
        ({"image_registry": "Quay.io/"}, "calico_image_registry", ["'Quay.io/'"]),
        ({"node_cpu_request": "lots"}, "calico_node_cpu_request", ["'lots'", "CPU quantity"]),
    ],
)
def test_bad_settings_name_variable_value_and_reason(changes, variable, words):
    settings = {"pod_cidr": "10.244.0.0/16", "version": RELEASE, **changes}
    with pytest.raises(KuberosError) as raised:
        calico_objects(published(), CalicoSettings(**settings))
    message = str(raised.value)
    line = next((line for line in message.splitlines() if f"{variable}:" in line), None)
    assert line, message
    for word in words:
        assert word in line, message


def test_every_problem_is_reported_at_once_and_unknown_settings_get_a_suggestion():
    with pytest.raises(KuberosError) as raised:
        calico_objects(published(), CalicoSettings("10.244.0.1/16", block_size=40, encapsulation_mode="gre", vpn="no"))
    message = str(raised.value)
    assert "4 problems" in message
    for variable in ("calico_pod_cidr", "calico_block_size", "calico_encapsulation_mode", "calico_vpn"):
        assert variable in message
    with pytest.raises(KuberosError, match=r"calico_blocksize: unknown setting; did you mean 'block_size'"):
        settings_from("10.244.0.0/16", {"blocksize": 24})


def test_filter_turns_errors_into_ansible_filter_errors():
    from ansible.errors import AnsibleFilterError

    with pytest.raises(AnsibleFilterError, match=re.escape("calico_pod_cidr: '300.0.0.0/8'")):
        calico_manifests(published(), pod_cidr="300.0.0.0/8", version=RELEASE)


def test_the_published_release_adapts_whole_and_passes_the_kubernetes_schema():
    path = calico_published_manifest()
    with open(path, encoding="utf-8") as handle:
        release = [o for o in yaml.safe_load_all(handle) if o]
    objects = calico_objects(copy.deepcopy(release), CalicoSettings("10.244.0.0/16", version=RELEASE, vpn=True), source=path)
    assert len(objects) == len(release)
    kinds = [o["kind"] for o in objects]
    assert (
        kinds.count("CustomResourceDefinition") >= 17 and kinds.index("ConfigMap") > kinds.count("CustomResourceDefinition") - 1
    )
    assert one(objects, "ConfigMap")["data"]["veth_mtu"] == "1370"
    assert env_of(objects)["CALICO_IPV4POOL_CIDR"] == "10.244.0.0/16"
    assert tolerates(one(objects, "DaemonSet")["spec"]["template"]["spec"], ROBOT_TAINT)
    for obj in objects:
        if obj["kind"] != "CustomResourceDefinition":  # Calico's CRDs are checked by the API server (tests/cluster)
            kubernetes_validate.validate(obj, KUBERNETES_VERSION, strict=True)
    # only the site's places changed: every object of the release is there, by kind and name
    assert sorted((o["kind"], o["metadata"]["name"]) for o in objects) == sorted(
        (o["kind"], o["metadata"]["name"]) for o in release
    )
