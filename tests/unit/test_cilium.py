"""Cilium's rendered objects: the MTU, settings validation, and the objects themselves (Kubernetes 1.34 schema,
the pod CIDR and the overlay in the agent's configuration, every node's taints tolerated, the images)."""

from __future__ import annotations

import re

import kubernetes_validate
import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.filter.cilium_manifests import cilium_manifests
from ansible_collections.kuberos.platform.plugins.filter.manifest_yaml import manifest_yaml
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cilium import (
    CONFIG_HASH_ANNOTATION,
    CiliumSettings,
    cilium_objects,
    pod_mtu,
    settings_from,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cni import tolerates

KUBERNETES_VERSION = "1.34"
ROBOT_TAINT = {"key": "kuberos.io/robot", "value": "true", "effect": "NoSchedule"}


def one(objects, kind, name=None):
    found = [o for o in objects if o["kind"] == kind and (name is None or o["metadata"]["name"] == name)]
    assert len(found) == 1, (kind, name)
    return found[0]


@pytest.mark.parametrize(
    ("base", "vpn", "vpn_mtu", "expected"),
    [(1500, False, 1420, 1450), (1500, True, 1420, 1370), (9000, False, 1420, 8950), (9000, True, 1420, 1370),
     (1460, False, 1420, 1410), (1400, True, 1420, 1350)],
)  # fmt: skip
def test_pod_mtu_is_the_narrowest_link_less_the_tunnel(base, vpn, vpn_mtu, expected):
    assert pod_mtu(base, "vxlan", vpn, vpn_mtu) == expected


@pytest.mark.parametrize(
    ("settings", "mtu"), [(CiliumSettings("10.244.0.0/16"), "1500"), (CiliumSettings("10.244.0.0/16", vpn=True), "1420")]
)
def test_the_agent_is_told_the_networks_mtu(settings, mtu):
    config = one(cilium_objects(settings), "ConfigMap")["data"]
    assert config["mtu"] == mtu
    assert config["routing-mode"] == "tunnel" and config["tunnel-protocol"] == "vxlan"
    assert config["ipam"] == "kubernetes" and config["cluster-pool-ipv4-cidr"] == "10.244.0.0/16"
    assert config["kube-proxy-replacement"] == "false" and config["enable-policy"] == "default"


@pytest.mark.parametrize(
    "settings", [CiliumSettings("10.244.0.0/16"), CiliumSettings("192.168.0.0/16", vpn=True, agent_cpu_request="0")]
)
def test_built_in_kinds_pass_the_kubernetes_schema(settings):
    objects = cilium_objects(settings)
    assert [o["kind"] for o in objects][-2:] == ["Deployment", "DaemonSet"]
    for obj in objects:
        kubernetes_validate.validate(obj, KUBERNETES_VERSION, strict=True)


def test_the_agent_runs_on_every_node_and_the_operator_prefers_control_planes():
    objects = cilium_objects(CiliumSettings("10.244.0.0/16"))
    agent = one(objects, "DaemonSet")["spec"]["template"]["spec"]
    for taint in (ROBOT_TAINT, {"key": "node-role.kubernetes.io/control-plane", "effect": "NoSchedule"},
                  {"key": "node.kubernetes.io/not-ready", "effect": "NoExecute"}):  # fmt: skip
        assert tolerates(agent, taint), taint
    assert agent["hostNetwork"] and agent["priorityClassName"] == "system-node-critical"
    operator = one(objects, "Deployment")["spec"]["template"]["spec"]
    assert operator["hostNetwork"]
    preferred = operator["affinity"]["nodeAffinity"]["preferredDuringSchedulingIgnoredDuringExecution"][0]
    assert preferred["preference"]["matchExpressions"][0]["key"] == "node-role.kubernetes.io/control-plane"


def test_the_bpf_filesystem_is_mounted_for_the_node_and_seen_by_the_agent():
    agent = one(cilium_objects(CiliumSettings("10.244.0.0/16")), "DaemonSet")["spec"]["template"]["spec"]
    mount = one_mount(agent["initContainers"][0], "bpf-maps")
    assert mount["mountPropagation"] == "Bidirectional"
    assert one_mount(agent["containers"][0], "bpf-maps")["mountPropagation"] == "HostToContainer"
    assert agent["initContainers"][1]["command"] == ["/install-plugin.sh"]


def one_mount(container, name):
    return next(m for m in container["volumeMounts"] if m["name"] == name)


def test_cpu_request_zero_requests_none():
    default = one(cilium_objects(CiliumSettings("10.244.0.0/16")), "DaemonSet")
    assert default["spec"]["template"]["spec"]["containers"][0]["resources"]["requests"]["cpu"] == "100m"
    none = one(cilium_objects(CiliumSettings("10.244.0.0/16", agent_cpu_request="0")), "DaemonSet")
    assert "cpu" not in none["spec"]["template"]["spec"]["containers"][0]["resources"]["requests"]


def test_a_config_change_rolls_the_agent_and_the_same_settings_do_not():
    def annotation(settings):
        template = one(cilium_objects(settings), "DaemonSet")["spec"]["template"]
        return template["metadata"]["annotations"][CONFIG_HASH_ANNOTATION]

    assert annotation(CiliumSettings("10.244.0.0/16")) == annotation(CiliumSettings("10.244.0.0/16"))
    assert annotation(CiliumSettings("10.244.0.0/16")) != annotation(CiliumSettings("10.244.0.0/16", vpn=True))


def test_images_follow_version_and_registry():
    objects = cilium_objects(CiliumSettings("10.244.0.0/16", version="v1.15.6", image_registry="mirror.site:5000/cilium"))
    agent = one(objects, "DaemonSet")["spec"]["template"]["spec"]
    images = {c["image"] for c in agent["containers"] + agent["initContainers"]}
    assert images == {"mirror.site:5000/cilium/cilium:v1.15.6"}
    operator = one(objects, "Deployment")["spec"]["template"]["spec"]["containers"][0]
    assert operator["image"] == "mirror.site:5000/cilium/operator-generic:v1.15.6"


def test_rbac_binds_each_service_account_to_its_role():
    objects = cilium_objects(CiliumSettings("10.244.0.0/16", namespace="cni"))
    for name in ("cilium", "cilium-operator"):
        binding = one(objects, "ClusterRoleBinding", name)
        assert binding["roleRef"]["name"] == name and binding["subjects"] == [
            {"kind": "ServiceAccount", "name": name, "namespace": "cni"}
        ]
        rules = one(objects, "ClusterRole", name)["rules"]
        assert not any("*" in rule["verbs"] or "*" in rule["resources"] for rule in rules), name
    agent_rules = one(objects, "ClusterRole", "cilium")["rules"]
    assert any(r["apiGroups"] == ["networking.k8s.io"] and "networkpolicies" in r["resources"] for r in agent_rules)


@pytest.mark.parametrize(
    ("changes", "variable", "words"),
    [
        ({"pod_cidr": "10.244.0.1/16"}, "cilium_pod_cidr", ["'10.244.0.1/16'", "host bits set"]),
        ({"pod_cidr": "10.244.0.0"}, "cilium_pod_cidr", ["CIDR notation"]),
        ({"pod_cidr": 42}, "cilium_pod_cidr", ["42 (int)"]),
        ({"pod_cidr": "fd00:10:244::/56"}, "cilium_pod_cidr", ["IPv6"]),
        ({"tunnel_protocol": "vxlam"}, "cilium_tunnel_protocol", ["'vxlam'", "did you mean 'vxlan'"]),
        ({"base_mtu": 70000}, "cilium_base_mtu", ["70000", "from 576 to 9216"]),
        ({"base_mtu": True}, "cilium_base_mtu", ["True (bool)"]),
        ({"base_mtu": 600}, "cilium_base_mtu", ["MTU of 550", "minimum of 576"]),
        ({"vpn_mtu": 100, "vpn": True}, "cilium_vpn_mtu", ["100", "from 1280 to 9000"]),
        ({"vpn": "yes"}, "cilium_vpn", ["'yes'", "not a boolean"]),
        ({"version": "1.15"}, "cilium_version", ["'1.15'", "release tag"]),
        ({"image_registry": "Quay.io/"}, "cilium_image_registry", ["'Quay.io/'"]),
        ({"namespace": "Kube_System"}, "cilium_namespace", ["'Kube_System'", "DNS label"]),
        ({"agent_cpu_request": "lots"}, "cilium_agent_cpu_request", ["'lots'", "CPU quantity"]),
        ({"operator_replicas": 0}, "cilium_operator_replicas", ["0", "from 1 to 5"]),
    ],
)
def test_bad_settings_name_variable_value_and_reason(changes, variable, words):
    with pytest.raises(KuberosError) as raised:
        cilium_objects(CiliumSettings(**{"pod_cidr": "10.244.0.0/16", **changes}))
    message = str(raised.value)
    line = next((line for line in message.splitlines() if f"{variable}:" in line), None)
    assert line, message
    for word in words:
        assert word in line, message


def test_every_problem_is_reported_at_once_and_unknown_settings_get_a_suggestion():
    with pytest.raises(KuberosError) as raised:
        cilium_objects(CiliumSettings("10.244.0.1/16", tunnel_protocol="gre", vpn="no"))
    assert "3 problems" in str(raised.value)
    with pytest.raises(KuberosError, match=r"cilium_tunnel_protocoll: unknown setting; did you mean 'tunnel_protocol'"):
        settings_from("10.244.0.0/16", {"tunnel_protocoll": "vxlan"})


def test_filter_turns_errors_into_ansible_filter_errors_and_renders_yaml():
    from ansible.errors import AnsibleFilterError

    with pytest.raises(AnsibleFilterError, match=re.escape("cilium_pod_cidr: '300.0.0.0/8'")):
        cilium_manifests("300.0.0.0/8")
    objects = cilium_manifests("10.244.0.0/16", vpn=True)
    assert list(yaml.safe_load_all(manifest_yaml(objects))) == objects
