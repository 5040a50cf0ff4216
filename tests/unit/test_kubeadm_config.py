"""kubeadm configuration from the inventory: documents per kind of host, validation, secrets, kubelet labels."""

from __future__ import annotations

import pytest
import yaml
from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.filter.kubeadm_config import kubeadm_config as kubeadm_config_filter
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import kubeadm_config as core

HARDWARE = {"kuberos_cpu": 4, "kuberos_memory": "8Gi"}
RAW = {
    "hosts": {
        "edge-1": dict(HARDWARE),
        "edge-2": dict(HARDWARE),
        "edge-3": {**HARDWARE, "kuberos_node_name": "edge-c", "kuberos_fleets": ["picking"]},
        "fetch-1": {**HARDWARE, "kuberos_fleet": "picking", "kuberos_devices": ["camera"]},
        "cloud-1": {**HARDWARE, "kuberos_gpu": 1},
    },
    "groups": {"robots": ["fetch-1"], "edge": ["edge-1", "edge-2", "edge-3"], "cloud": ["cloud-1"]},
}
HOSTVARS = {
    "edge-1": {"kuberos_address": "10.0.0.11"},
    "edge-2": {"kuberos_address": "10.0.0.12", "kuberos_vpn_address": "10.99.0.2"},
    "edge-3": {"ansible_host": "10.0.0.13"},
    "fetch-1": {"kuberos_address": "10.0.1.5"},
    "cloud-1": {"ansible_host": "203.0.113.7", "kuberos_vpn_address": "10.99.0.11"},
}
HA = ["edge-1", "edge-2", "edge-3"]
TOKEN = "k8sabc.0123456789qwerty"
CA_HASH = "sha256:" + "ab" * 32
JOIN_COMMAND = f"kubeadm join 10.0.0.10:6443 --token {TOKEN} --discovery-token-ca-cert-hash {CA_HASH} \n"
CERT_KEY = "cd" * 32
UPLOAD_CERTS = (
    f'[upload-certs] Storing the certificates in Secret "kubeadm-certs"\n[upload-certs] Using certificate key:\n{CERT_KEY}\n'
)


def render(host, control_planes=("edge-1",), hostvars=None, **options):
    return kubeadm_config_filter(RAW, hostvars or HOSTVARS, host, list(control_planes), **options)


def registration_args(result):
    return {a["name"]: a["value"] for a in result["documents"][0]["nodeRegistration"]["kubeletExtraArgs"]}


# host, control planes -> action, kinds, node name, node-ip, taints
INIT_KINDS = ["InitConfiguration", "ClusterConfiguration", "KubeletConfiguration"]
SHAPES = [
    ("edge-1", ["edge-1"], "init", INIT_KINDS, "edge-1", "10.0.0.11", []),
    ("edge-2", HA, "join-control-plane", ["JoinConfiguration"], "edge-2", "10.0.0.12", []),
    ("edge-3", HA, "join-control-plane", ["JoinConfiguration"], "edge-c", "10.0.0.13", []),
    ("edge-2", ["edge-1"], "join-worker", ["JoinConfiguration"], "edge-2", "10.0.0.12", []),
    (
        "fetch-1", HA, "join-worker", ["JoinConfiguration"], "fetch-1", "10.0.1.5",
        [{"key": "kuberos.io/robot", "value": "fetch-1", "effect": "NoSchedule"}],
    ),
    ("cloud-1", HA, "join-worker", ["JoinConfiguration"], "cloud-1", "10.99.0.11", []),
]  # fmt: skip


@pytest.mark.parametrize(("host", "planes", "action", "kinds", "node", "node_ip", "taints"), SHAPES)
def test_each_kind_of_host_gets_its_documents(host, planes, action, kinds, node, node_ip, taints):
    result = render(host, planes)
    assert result["action"] == action
    assert [d["kind"] for d in result["documents"]] == kinds
    assert all(d["apiVersion"] == core.API_VERSION for d in result["documents"] if d["kind"] != "KubeletConfiguration")
    registration = result["documents"][0]["nodeRegistration"]
    assert registration["name"] == node == result["node_name"]
    assert registration["taints"] == taints == result["taints"]
    assert registration_args(result)["node-ip"] == node_ip
    assert list(yaml.safe_load_all(result["content"])) == result["documents"]


def test_cluster_configuration_of_an_ha_control_plane():
    result = render("edge-1", HA, control_plane_endpoint="k8s.site.example:6443", kubernetes_version="v1.34.4")
    init, cluster, kubelet = result["documents"]
    assert init["localAPIEndpoint"] == {"advertiseAddress": "10.0.0.11", "bindPort": 6443}
    assert cluster["controlPlaneEndpoint"] == "k8s.site.example:6443"
    assert cluster["kubernetesVersion"] == "v1.34.4"
    assert cluster["networking"] == {"podSubnet": "10.244.0.0/16", "serviceSubnet": "10.96.0.0/12"}
    assert cluster["apiServer"]["certSANs"] == ["k8s.site.example", "10.0.0.11", "10.0.0.12", "10.99.0.2", "10.0.0.13"]
    assert cluster["etcd"] == {"local": {"dataDir": "/var/lib/etcd"}}
    assert kubelet == {"apiVersion": "kubelet.config.k8s.io/v1beta1", "kind": "KubeletConfiguration", "cgroupDriver": "systemd"}


@pytest.mark.parametrize(
    ("options", "endpoint"),
    [
        ({}, "10.0.0.11:6443"),  # the first control plane's address
        ({"control_plane_endpoint": "10.0.0.10:8443"}, "10.0.0.10:8443"),
        ({"control_plane_endpoint": "[fd00::10]:6443"}, "[fd00::10]:6443"),
    ],
)
def test_control_plane_endpoint_default_and_given(options, endpoint):
    assert render("fetch-1", HA, **options)["documents"][0]["discovery"]["bootstrapToken"]["apiServerEndpoint"] == endpoint
    assert render("edge-1", HA, **options)["documents"][1]["controlPlaneEndpoint"] == endpoint


def test_labels_are_the_kuberos_labels_through_the_kubelet():
    result = render("fetch-1", HA)
    labels = dict(pair.split("=") for pair in registration_args(result)["node-labels"].split(","))
    assert (
        labels
        == result["labels"]
        == {
            "device.kuberos.io/hostname": "fetch-1",
            "devices.kuberos.io/camera": "true",
            "fleet.kuberos.io/name": "picking",
            "kuberos.io/arch": "amd64",
            "kuberos.io/role": "robot",
            "resource-group.kuberos.io/name": "picking",
            "robot.kuberos.io/name": "fetch-1",
        }
    )
    assert result["labels_for_api"] == {}
    assert render("edge-3", HA)["labels"]["fleet-access.kuberos.io/picking"] == "true"


@pytest.mark.parametrize(
    ("key", "allowed"),
    [
        ("kuberos.io/role", True),
        ("example.com/rack", True),
        ("plain", True),
        ("kubernetes.io/hostname", True),
        ("topology.kubernetes.io/zone", True),
        ("node.kubernetes.io/instance-type", True),
        ("kubelet.kubernetes.io/anything", True),
        ("sub.node.kubernetes.io/anything", True),
        ("node-role.kubernetes.io/edge", False),
        ("kubernetes.io/role", False),
        ("k8s.io/anything", False),
        ("foo.k8s.io/anything", False),
    ],
)
def test_kubelet_self_labels_follow_node_restriction(key, allowed):
    kept, refused = core.kubelet_labels({key: "x"})
    assert (key in kept, key in refused) == (allowed, not allowed)


def test_refused_extra_labels_are_left_out_and_reported():
    result = render("edge-2", ["edge-1"], extra_labels={"node-role.kubernetes.io/edge": "", "example.com/rack": "r1"})
    assert "node-role.kubernetes.io/edge" not in registration_args(result)["node-labels"]
    assert "example.com/rack=r1" in registration_args(result)["node-labels"]
    assert list(result["labels_for_api"]) == ["node-role.kubernetes.io/edge"]
    assert "NodeRestriction" in result["labels_for_api"]["node-role.kubernetes.io/edge"]


def test_control_planes_can_keep_kubeadms_taint():
    assert render("edge-1", control_plane_schedulable=True)["taints"] == []
    assert render("edge-1", control_plane_schedulable=False)["taints"] == [
        {"key": "node-role.kubernetes.io/control-plane", "effect": "NoSchedule"}
    ]
    assert render("edge-2", ["edge-1"], control_plane_schedulable=False)["taints"] == []  # a worker


def test_join_secrets_placeholders_and_real():
    shown = render("edge-2", HA)
    assert shown["placeholders"] is True
    assert core.PLACEHOLDER_TOKEN in shown["content"] and core.PLACEHOLDER_CERTIFICATE_KEY in shown["content"]
    secret = render("edge-2", HA, join_command=JOIN_COMMAND, certificate_key=UPLOAD_CERTS)
    join = secret["documents"][0]
    assert secret["placeholders"] is False
    assert join["discovery"]["bootstrapToken"]["token"] == TOKEN
    assert join["discovery"]["bootstrapToken"]["caCertHashes"] == [CA_HASH]
    assert join["controlPlane"] == {
        "localAPIEndpoint": {"advertiseAddress": "10.0.0.12", "bindPort": 6443},
        "certificateKey": CERT_KEY,
    }
    worker = render("fetch-1", HA, join_command=JOIN_COMMAND)
    assert "controlPlane" not in worker["documents"][0] and CERT_KEY not in worker["content"]
    assert render("edge-1", HA, join_command=JOIN_COMMAND)["content"].count(TOKEN) == 0  # init never carries it


@pytest.mark.parametrize(
    ("join_command", "certificate_key", "expected"),
    [
        ("kubeadm join x:6443 --token nope", None, "found 0 bootstrap token(s) and 0 CA certificate hash(es)"),
        (f"kubeadm join x:6443 --token {TOKEN}", None, "found 1 bootstrap token(s) and 0 CA certificate hash(es)"),
        (None, "[upload-certs] Using certificate key:\nnot-a-key", "no certificate key found"),
    ],
)
def test_unreadable_secrets_are_named_without_repeating_them(join_command, certificate_key, expected):
    with pytest.raises(SpecError) as error:
        core.join_secrets(join_command, certificate_key)
    assert expected in str(error.value)
    assert TOKEN not in str(error.value) and "not-a-key" not in str(error.value)


BAD_SETTINGS = [
    ({"kubernetes_version": "1.34.4"}, "kuberos_kubernetes_version: '1.34.4' is not valid; expected a version such as v1.34.4"),
    ({"kubernetes_version": "v1.34"}, "kuberos_kubernetes_version: 'v1.34' is not valid"),
    ({"pod_cidr": "10.244.0.0/33"}, "kuberos_pod_cidr: '10.244.0.0/33' is not valid"),
    ({"pod_cidr": "10.244.0.1/16"}, "kuberos_pod_cidr: '10.244.0.1/16' is not valid; 10.244.0.1/16 has host bits set"),
    ({"pod_cidr": "10.244.0.0/28"}, "a /28 is smaller than one node's /24 of pods"),
    ({"pod_cidr": "10.0.0.0/7"}, "holds more than 2^16 node subnets"),
    ({"pod_cidr": "10.96.0.0/16"}, "kuberos_pod_cidr: '10.96.0.0/16' is not valid; overlaps kuberos_service_cidr 10.96.0.0/12"),
    ({"service_cidr": "10.0.0.0/8"}, "kuberos_service_cidr: '10.0.0.0/8' is not valid; too large for Kubernetes; use /12"),
    ({"service_cidr": "services"}, "kuberos_service_cidr: 'services' is not valid"),
    ({"control_plane_endpoint": "10.0.0.10"}, "kuberos_control_plane_endpoint: '10.0.0.10' is not valid; expected host:port"),
    ({"control_plane_endpoint": "k8s.example:70000"}, "port 70000 is out of range"),
    ({"control_plane_endpoint": "K8S_LB:6443"}, "'K8S_LB' is neither an IP address nor a DNS name"),
    (
        {"control_plane_endpoint": "https://k8s.example:6443"},
        "kuberos_control_plane_endpoint: 'https://k8s.example:6443' is not valid",
    ),
    ({"cri_socket": "containerd"}, "cri_socket: 'containerd' is not valid"),
    ({"cgroup_driver": "cgroupv2"}, "kuberos_cgroup_driver: 'cgroupv2' is not valid; expected systemd"),
    ({"image_repository": "https://mirror.example/k8s"}, "kuberos_kubeadm_image_repository: 'https://mirror.example/k8s'"),
    ({"image_repository": "Mirror.Example/k8s"}, "expected a registry path such as mirror.site.example:5000/k8s"),
    ({"etcd_image_tag": "3.5 35"}, "kuberos_etcd_image_tag: '3.5 35' is not valid; expected an image tag"),
    ({"coredns_image_tag": ":v1"}, "kuberos_coredns_image_tag: ':v1' is not valid"),
    ({"conntrack_max_per_core": -1}, "kuberos_kube_proxy_conntrack_max_per_core: -1 (int) is not valid; expected a whole number"),
    ({"eviction_hard": {"disk.free": "5%"}}, "kuberos_kubelet_eviction_hard.disk.free: '5%' is not valid; unknown signal"),
    ({"eviction_hard": {"nodefs.available": "plenty"}}, "kuberos_kubelet_eviction_hard.nodefs.available: 'plenty' is not valid"),
    ({"eviction_hard": {"memory.available": 100}}, "expected a quantity such as 500Mi or a share such as 5%"),
    ({"eviction_hard": ["nodefs.available<5%"]}, "kuberos_kubelet_eviction_hard: ['nodefs.available<5%'] (list) is not valid"),
]


@pytest.mark.parametrize(("options", "message"), BAD_SETTINGS)
def test_bad_settings_name_the_variable_the_value_and_the_reason(options, message):
    with pytest.raises(AnsibleFilterError) as error:
        render("edge-1", HA, **options)
    assert message in str(error.value)


def test_every_problem_is_reported_at_once():
    with pytest.raises(AnsibleFilterError) as error:
        render("edge-1", HA, kubernetes_version="latest", pod_cidr="x", control_plane_endpoint="lb")
    assert "(3 problems)" in str(error.value)


CLOUD_VPN = "hosts.cloud-1.kuberos_vpn_address"
BAD_INVENTORY = [
    ("cloud-1", HA, {"cloud-1": {"ansible_host": "203.0.113.7"}}, f"{CLOUD_VPN}: is required for a cloud host"),
    ("cloud-1", HA, {"cloud-1": {"kuberos_vpn_address": "vpn-1"}}, f"{CLOUD_VPN}: 'vpn-1' is not valid"),
    ("fetch-1", ["edge-1", "fetch-1"], {}, "groups.control_plane[1]: 'fetch-1' is not a host of the edge group"),
    ("fetch-1", [], {}, "groups.control_plane: is empty"),
    ("fetch-1", ["edge-1"], {"edge-1": {"kuberos_address": "edge-1.site.example"}}, "advertises its API server on an IP"),
    ("fetch-1", ["edge-1"], {"fetch-1": {"kuberos_address": "not an address"}}, "fetch-1.kuberos_address: 'not an"),
    ("nobody", ["edge-1"], {}, "hosts.nobody: is not a host of the groups robots, edge or cloud"),
]  # fmt: skip


@pytest.mark.parametrize(("host", "planes", "override", "message"), BAD_INVENTORY)
def test_bad_inventory_is_named_by_host_and_variable(host, planes, override, message):
    hostvars = {h: dict(v) for h, v in HOSTVARS.items()}
    for name, variables in override.items():
        hostvars[name] = variables
    with pytest.raises(AnsibleFilterError) as error:
        render(host, planes, hostvars=hostvars)
    assert message in str(error.value)


def test_bad_extra_labels_are_refused():
    with pytest.raises(AnsibleFilterError) as error:
        render("fetch-1", extra_labels={"bad key!": "x", "example.com/ok": "bad value!"})
    assert "'bad key!' is not valid; expected a label key" in str(error.value)
    assert "'bad value!' is not valid; expected a label value" in str(error.value)


def test_unknown_filter_option_is_named():
    with pytest.raises(AnsibleFilterError, match="pod_cdir: unknown option"):
        render("edge-1", pod_cdir="10.244.0.0/16")


def test_yaml_is_multi_document_and_keeps_order():
    text = core.to_yaml([{"b": 1, "a": 2}, {"kind": "X"}])
    assert text == "---\nb: 1\na: 2\n---\nkind: X\n"


def test_a_site_with_a_mirror_other_versions_and_the_cgroupfs_driver():
    """The settings of a site that runs its own mirror, another etcd and CoreDNS, and cgroupfs (the lab's machines)."""
    result = render(
        "edge-1", HA, image_repository="mirror.site.example:5000/k8s", etcd_image_tag="3.5.35-0",
        coredns_image_tag="v1.14.7", cgroup_driver="cgroupfs",
    )  # fmt: skip
    _init, cluster, kubelet = result["documents"]
    assert cluster["imageRepository"] == "mirror.site.example:5000/k8s"
    assert cluster["etcd"] == {"local": {"dataDir": "/var/lib/etcd", "imageTag": "3.5.35-0"}}
    assert cluster["dns"] == {"imageTag": "v1.14.7"}
    assert kubelet["cgroupDriver"] == "cgroupfs"
    # joins take the cluster's settings from it: their documents do not change
    assert render("edge-2", HA, cgroup_driver="cgroupfs", image_repository="mirror.site.example:5000/k8s") == render("edge-2", HA)
    # unset, kubeadm's defaults hold: no key at all
    assert "imageRepository" not in render("edge-1", HA)["documents"][1] and "dns" not in render("edge-1", HA)["documents"][1]


def test_the_kubelets_eviction_thresholds_are_the_sites_when_it_sets_them():
    thresholds = {"memory.available": "100Mi", "nodefs.available": "1%", "imagefs.available": "2.5Gi"}
    for host in ("edge-1", "edge-2"):  # kubeadm uploads the first control plane's; the others join with it
        documents = render(host, HA, eviction_hard=thresholds)["documents"]
        kubelet = [d for d in documents if d["kind"] == "KubeletConfiguration"]
        assert kubelet == ([{**kubelet[0], "evictionHard": thresholds}] if host == "edge-1" else [])
    unset = [d for d in render("edge-1", HA, eviction_hard={})["documents"] if d["kind"] == "KubeletConfiguration"]
    assert "evictionHard" not in unset[0]  # empty: the kubelet's own defaults


def test_kube_proxy_can_leave_the_hosts_conntrack_limit_alone():
    documents = render("edge-1", HA, conntrack_max_per_core="0")["documents"]
    assert documents[-1] == {
        "apiVersion": "kubeproxy.config.k8s.io/v1alpha1", "kind": "KubeProxyConfiguration", "conntrack": {"maxPerCore": 0},
    }  # fmt: skip
    assert [d["kind"] for d in render("edge-1", HA)["documents"]] == INIT_KINDS  # unset: kube-proxy's own default
