"""Calico's rendered objects: the MTU table, settings validation, and the objects themselves
(Kubernetes 1.34 schema for the built-in kinds, the pod CIDR everywhere it belongs, robot taints tolerated)."""

from __future__ import annotations

import json
import re

import kubernetes_validate
import pytest

from ansible_collections.kuberos.platform.plugins.filter.calico_manifests import calico_manifests
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import (
    CALICO_KINDS,
    CalicoSettings,
    calico_objects,
    pod_mtu,
    settings_from,
    tolerates,
)

KUBERNETES_VERSION = "1.34"
REQUIRED_KINDS = {
    "BGPConfiguration", "BGPPeer", "BlockAffinity", "CalicoNodeStatus", "ClusterInformation", "FelixConfiguration",
    "GlobalNetworkPolicy", "GlobalNetworkSet", "HostEndpoint", "IPAMBlock", "IPAMConfig", "IPAMHandle", "IPPool",
    "IPReservation", "KubeControllersConfiguration", "NetworkPolicy", "NetworkSet",
}  # fmt: skip


@pytest.mark.parametrize(
    ("base", "encapsulation", "vpn", "ip_version", "expected"),
    [
        (1500, "none", False, 4, 1500),
        (1500, "ipip", False, 4, 1480),
        (1500, "vxlan", False, 4, 1450),
        (1500, "none", True, 4, 1420),
        (1500, "ipip", True, 4, 1400),
        (1500, "vxlan", True, 4, 1370),
        (9000, "vxlan", False, 4, 8950),
        (9000, "ipip", True, 4, 1400),  # the tunnel is the narrowest
        (1500, "vxlan", False, 6, 1430),
        (1500, "vxlan", True, 6, 1350),
        (1460, "vxlan", False, 4, 1410),  # a cloud network with a smaller MTU (GCE)
    ],
)
def test_pod_mtu(base, encapsulation, vpn, ip_version, expected):
    assert pod_mtu(base, encapsulation, vpn, ip_version) == expected


def by_kind(objects, kind):
    return [o for o in objects if o["kind"] == kind]


def one(objects, kind):
    found = by_kind(objects, kind)
    assert len(found) == 1, kind
    return found[0]


def env_of(daemonset):
    container = daemonset["spec"]["template"]["spec"]["containers"][0]
    return {e["name"]: e.get("value", e.get("valueFrom")) for e in container["env"]}


@pytest.mark.parametrize(
    ("settings", "veth_mtu"),
    [
        (CalicoSettings("10.244.0.0/16"), "1450"),
        (CalicoSettings("10.244.0.0/16", vpn=True), "1370"),
        (CalicoSettings("10.244.0.0/16", encapsulation="ipip", vpn=True), "1400"),
        (CalicoSettings("192.168.0.0/16", encapsulation="none", base_mtu=9000), "9000"),
    ],
)
def test_mtu_reaches_the_config_map(settings, veth_mtu):
    objects = calico_objects(settings)
    config = one(objects, "ConfigMap")
    assert config["data"]["veth_mtu"] == veth_mtu
    network = json.loads(config["data"]["cni_network_config"].replace("__CNI_MTU__", veth_mtu))
    assert network["plugins"][0]["mtu"] == int(veth_mtu)  # a number once install-cni substituted it
    env = env_of(one(objects, "DaemonSet"))
    assert env["FELIX_VXLANMTU"] == {"configMapKeyRef": {"name": "calico-config", "key": "veth_mtu"}}


@pytest.mark.parametrize(
    ("changes", "variable", "words"),
    [
        ({"pod_cidr": "10.244.0.1/16"}, "calico_pod_cidr", ["'10.244.0.1/16'", "host bits set", "'10.244.0.0/16'"]),
        ({"pod_cidr": "10.244.0.0/33"}, "calico_pod_cidr", ["'10.244.0.0/33'", "not an IPv4 or IPv6 network"]),
        ({"pod_cidr": "not-a-cidr/8"}, "calico_pod_cidr", ["'not-a-cidr/8'"]),
        ({"pod_cidr": "10.244.0.0"}, "calico_pod_cidr", ["no prefix length"]),
        ({"pod_cidr": 42}, "calico_pod_cidr", ["42 (int)", "CIDR notation"]),
        ({"block_size": 19}, "calico_block_size", ["19", "from 20 to 32"]),
        ({"block_size": 33}, "calico_block_size", ["33", "from 20 to 32"]),
        ({"block_size": "big"}, "calico_block_size", ["'big'", "from 20 to 32"]),
        ({"pod_cidr": "10.244.0.0/28", "block_size": 26}, "calico_block_size", ["larger than the pod CIDR", "at least 28"]),
        ({"pod_cidr": "fd00:10:244::/56", "block_size": 26}, "calico_block_size", ["IPv6", "from 116 to 128"]),
        ({"encapsulation": "vxlam"}, "calico_encapsulation", ["'vxlam'", "did you mean 'vxlan'"]),
        ({"encapsulation": "ipip", "pod_cidr": "fd00:10:244::/56"}, "calico_encapsulation", ["IPv4 only"]),
        ({"encapsulation_mode": "crosssubnet"}, "calico_encapsulation_mode", ["did you mean 'CrossSubnet'"]),
        ({"base_mtu": 70000}, "calico_base_mtu", ["70000", "from 576 to 9216"]),
        ({"base_mtu": True}, "calico_base_mtu", ["True (bool)"]),
        ({"base_mtu": 600, "vpn": True}, "calico_base_mtu", ["MTU of 550", "WireGuard", "minimum of 576"]),
        ({"vpn": "yes"}, "calico_vpn", ["'yes'", "not a boolean"]),
        ({"ip_autodetection_method": "iface=eth0"}, "calico_ip_autodetection_method", ["'iface=eth0'", "can-reach="]),
        ({"ip_autodetection_method": "cidr=10.0.0.0/33"}, "calico_ip_autodetection_method", ["'10.0.0.0/33'"]),
        ({"version": "3.31"}, "calico_version", ["'3.31'", "release tag"]),
        ({"image_registry": "Quay.io/"}, "calico_image_registry", ["'Quay.io/'"]),
        ({"namespace": "Kube_System"}, "calico_namespace", ["'Kube_System'", "DNS label"]),
    ],
)
def test_bad_settings_name_variable_value_and_reason(changes, variable, words):
    settings = {"pod_cidr": "10.244.0.0/16", **changes}
    with pytest.raises(KuberosError) as raised:
        calico_objects(CalicoSettings(**settings))
    message = str(raised.value)
    line = next((line for line in message.splitlines() if f"{variable}:" in line), None)
    assert line, message
    for word in words:
        assert word in line, message


def test_every_problem_is_reported_at_once():
    with pytest.raises(KuberosError) as raised:
        calico_objects(CalicoSettings("10.244.0.1/16", block_size=40, encapsulation="gre", vpn="no"))
    message = str(raised.value)
    assert "4 problems" in message
    for variable in ("calico_pod_cidr", "calico_block_size", "calico_encapsulation", "calico_vpn"):
        assert variable in message


def test_unknown_setting_suggests_the_known_one():
    with pytest.raises(KuberosError, match=r"calico_blocksize: unknown setting; did you mean 'block_size'"):
        settings_from("10.244.0.0/16", {"blocksize": 24})


def test_filter_turns_errors_into_ansible_filter_errors():
    from ansible.errors import AnsibleFilterError

    with pytest.raises(AnsibleFilterError, match=re.escape("calico_pod_cidr: '300.0.0.0/8'")):
        calico_manifests("300.0.0.0/8")
    assert calico_manifests("10.244.0.0/16", block_size="24")[0]["kind"] == "CustomResourceDefinition"


SETTINGS = [
    CalicoSettings("10.244.0.0/16"),
    CalicoSettings("10.244.0.0/16", encapsulation="ipip", encapsulation_mode="CrossSubnet", vpn=True),
    CalicoSettings("172.16.0.0/12", encapsulation="none", block_size=24, ip_autodetection_method="can-reach=10.0.0.1"),
    CalicoSettings("fd00:10:244::/56", encapsulation="vxlan", ip_autodetection_method="interface=eth.*"),
]


@pytest.mark.parametrize("settings", SETTINGS, ids=["vxlan", "ipip-vpn", "bgp", "ipv6"])
def test_objects_are_complete_and_ordered(settings):
    objects = calico_objects(settings)
    for obj in objects:
        assert obj["apiVersion"] and obj["kind"] and obj["metadata"]["name"], obj
    kinds = [o["kind"] for o in objects]
    crds = [i for i, k in enumerate(kinds) if k == "CustomResourceDefinition"]
    assert crds == list(range(len(crds))), "CRDs come first"
    keys = [(o["kind"], o["metadata"].get("namespace"), o["metadata"]["name"]) for o in objects]
    assert len(keys) == len(set(keys)), "no object twice"
    crd_kinds = {o["spec"]["names"]["kind"] for o in by_kind(objects, "CustomResourceDefinition")}
    assert crd_kinds >= REQUIRED_KINDS
    assert {k for k, _p, _n in CALICO_KINDS} <= crd_kinds
    for kind in ("ServiceAccount", "ClusterRole", "ClusterRoleBinding"):
        assert len(by_kind(objects, kind)) == 3
    assert one(objects, "DaemonSet")["metadata"]["namespace"] == settings.namespace


@pytest.mark.parametrize("settings", SETTINGS, ids=["vxlan", "ipip-vpn", "bgp", "ipv6"])
def test_built_in_kinds_pass_the_kubernetes_schema(settings):
    for obj in calico_objects(settings):
        if obj["apiVersion"].startswith(("crd.projectcalico.org/", "policy.networking.k8s.io/")):
            continue  # custom resources: checked against their CRD below and by the real API server
        kubernetes_validate.validate(obj, KUBERNETES_VERSION, strict=True)


def test_ippool_carries_the_pod_cidr_and_matches_its_crd_schema():
    import jsonschema

    objects = calico_objects(
        CalicoSettings("10.42.0.0/16", block_size=24, encapsulation="ipip", encapsulation_mode="CrossSubnet")
    )
    pool = one(objects, "IPPool")
    assert pool["apiVersion"] == "crd.projectcalico.org/v1"
    assert pool["spec"] == {
        "cidr": "10.42.0.0/16",
        "blockSize": 24,
        "ipipMode": "CrossSubnet",
        "vxlanMode": "Never",
        "natOutgoing": True,
        "nodeSelector": "all()",
        "disabled": False,
    }
    crd = next(o for o in objects if o["metadata"]["name"] == "ippools.crd.projectcalico.org")
    schema = crd["spec"]["versions"][0]["schema"]["openAPIV3Schema"]
    jsonschema.validate(pool, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**pool, "spec": {**pool["spec"], "ipipMode": "Sometimes"}}, schema)
    for other in by_kind(objects, "CustomResourceDefinition"):
        spec = other["spec"]["versions"][0]["schema"]["openAPIV3Schema"]["properties"]["spec"]
        if other is not crd:
            assert spec == {"type": "object", "x-kubernetes-preserve-unknown-fields": True}


@pytest.mark.parametrize(
    ("settings", "env"),
    [
        (
            CalicoSettings("10.244.0.0/16", vpn=True, ip_autodetection_method="interface=wg0"),
            {
                "CALICO_IPV4POOL_CIDR": "10.244.0.0/16",
                "CALICO_IPV4POOL_BLOCK_SIZE": "26",
                "CALICO_IPV4POOL_VXLAN": "Always",
                "CALICO_IPV4POOL_IPIP": "Never",
                "IP_AUTODETECTION_METHOD": "interface=wg0",
                "CLUSTER_TYPE": "k8s",
                "FELIX_IPV6SUPPORT": "false",
            },
        ),
        (
            CalicoSettings("10.244.0.0/16", encapsulation="ipip", encapsulation_mode="CrossSubnet"),
            {"CALICO_IPV4POOL_IPIP": "CrossSubnet", "CALICO_IPV4POOL_VXLAN": "Never", "CLUSTER_TYPE": "k8s,bgp"},
        ),
        (
            CalicoSettings("10.244.0.0/16", encapsulation="none", encapsulation_mode="CrossSubnet"),
            {"CALICO_IPV4POOL_IPIP": "Never", "CALICO_IPV4POOL_VXLAN": "Never"},
        ),
        (
            CalicoSettings("fd00:10:244::/56"),
            {"CALICO_IPV6POOL_CIDR": "fd00:10:244::/56", "CALICO_IPV6POOL_BLOCK_SIZE": "122", "IP": "none", "IP6": "autodetect"},
        ),
    ],
)
def test_calico_node_environment(settings, env):
    actual = env_of(one(calico_objects(settings), "DaemonSet"))
    assert {name: actual.get(name) for name in env} == env


def test_calico_node_runs_on_tainted_robots_and_the_controllers_do_not():
    objects = calico_objects(CalicoSettings("10.244.0.0/16"))
    node = one(objects, "DaemonSet")["spec"]["template"]["spec"]
    controllers = one(objects, "Deployment")["spec"]["template"]["spec"]
    robot = {"key": "kuberos.io/robot", "value": "fetch-1", "effect": "NoSchedule"}
    assert tolerates(node, robot)
    assert tolerates(node, {"key": "node.kubernetes.io/not-ready", "effect": "NoExecute"})
    assert tolerates(node, {"key": "node-role.kubernetes.io/control-plane", "effect": "NoSchedule"})
    assert not tolerates(controllers, robot)  # a robot's computer takes only what KubeROS placed there
    assert node["hostNetwork"] is True
    assert node["priorityClassName"] == "system-node-critical"


def test_config_change_rolls_calico_node():
    def annotations(settings):
        return one(calico_objects(settings), "DaemonSet")["spec"]["template"]["metadata"]["annotations"]

    assert annotations(CalicoSettings("10.244.0.0/16")) == annotations(CalicoSettings("10.244.0.0/16"))
    assert annotations(CalicoSettings("10.244.0.0/16")) != annotations(CalicoSettings("10.244.0.0/16", vpn=True))


def test_images_follow_version_and_registry():
    objects = calico_objects(CalicoSettings("10.244.0.0/16", version="v3.30.3", image_registry="registry.example.com/calico"))
    images = set()
    for workload in by_kind(objects, "DaemonSet") + by_kind(objects, "Deployment"):
        pod = workload["spec"]["template"]["spec"]
        images |= {c["image"] for c in pod.get("initContainers", []) + pod["containers"]}
    assert images == {
        "registry.example.com/calico/node:v3.30.3",
        "registry.example.com/calico/cni:v3.30.3",
        "registry.example.com/calico/kube-controllers:v3.30.3",
    }


def test_admin_network_policy_crds_can_be_left_out():
    def names(settings):
        return {o["metadata"]["name"] for o in by_kind(calico_objects(settings), "CustomResourceDefinition")}

    with_policy = names(CalicoSettings("10.244.0.0/16"))
    without = names(CalicoSettings("10.244.0.0/16", admin_network_policy_crds=False))
    assert with_policy - without == {
        "adminnetworkpolicies.policy.networking.k8s.io",
        "baselineadminnetworkpolicies.policy.networking.k8s.io",
    }


def test_manifest_yaml_reads_back_as_the_objects():
    import yaml

    from ansible_collections.kuberos.platform.plugins.filter.manifest_yaml import manifest_yaml

    objects = calico_objects(CalicoSettings("10.244.0.0/16"))
    text = manifest_yaml(objects)
    assert text.startswith("---\n") and text.count("\n---\n") == len(objects) - 1
    assert list(yaml.safe_load_all(text)) == objects
    assert "cni_network_config: |-" in text  # the embedded JSON stays readable


def test_kube_controllers_run_only_the_controllers_their_release_knows():
    """Calico 3.28 exits on the load-balancer controller, added in 3.29 (seen on the lab machines' real Calico)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.calico import _controllers

    assert _controllers("v3.31.3") == "node,loadbalancer"
    assert _controllers("v3.28.4-11-ga0db560f05") == "node"
