"""Calico, the cluster's CNI, as Kubernetes objects: a manifest install with the Kubernetes datastore.

``calico_objects`` returns, in apply order: the CustomResourceDefinitions calico-node and
calico-kube-controllers read and write, the default IPPool with the site's pod CIDR, the ServiceAccounts,
least-privilege ClusterRoles and their bindings, the ``calico-config`` ConfigMap (MTU and CNI network
configuration), the calico-node DaemonSet (on every node, tainted robot nodes included), the
calico-kube-controllers Deployment and its PodDisruptionBudget.

The CRDs carry a real schema for the fields this collection sets (the IPPool's); every other field of
every kind is kept as it is written (``x-kubernetes-preserve-unknown-fields``). Calico's own, complete
schemas are not shipped.

The pod MTU is the network's MTU minus the encapsulation overhead, minus the WireGuard overhead when pod
traffic crosses the site VPN (``pod_mtu``).
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe, did_you_mean
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cni import (  # noqa: F401 (tolerates: the tests')
    BASE_MTU_RANGE,
    DEFAULT_VPN_MTU,
    MIN_POD_MTU,
    RBAC_API,
    _integer,
    _rule,
    settings_of,
    tolerates,
)

GROUP = "crd.projectcalico.org"
CRD_API = "apiextensions.k8s.io/v1"
NODE = "calico-node"
CNI_PLUGIN = "calico-cni-plugin"
KUBE_CONTROLLERS = "calico-kube-controllers"
CONFIG = "calico-config"
ROBOT_TAINT = "kuberos.io/robot"
CONFIG_HASH_ANNOTATION = "kuberos.io/calico-config-hash"

ENCAPSULATIONS = ("ipip", "vxlan", "none")
ENCAPSULATION_MODES = ("Always", "CrossSubnet")
# Bytes each packet loses to the encapsulation (outer header), by pod address family.
ENCAPSULATION_OVERHEAD = {
    ("ipip", 4): 20,  # an outer IPv4 header
    ("vxlan", 4): 50,  # outer IPv4 + UDP + VXLAN headers and the inner Ethernet header
    ("vxlan", 6): 70,  # the same over an IPv6 outer header
    ("none", 4): 0,
    ("none", 6): 0,
}
# WireGuard over an IPv4 underlay: outer IPv4 (20) + UDP (8) + WireGuard header and tag (32).
BLOCK_SIZE_RANGE = {4: (20, 32), 6: (116, 128)}
AUTODETECTION_VALUES = ("first-found", "kubernetes-internal-ip")
AUTODETECTION_PREFIXES = ("can-reach=", "interface=", "skip-interface=", "cidr=")

# (kind, plural, namespaced) of every crd.projectcalico.org/v1 kind calico-node, the CNI plugin and
# calico-kube-controllers of Calico 3.30 and 3.31 use with the Kubernetes datastore.
CALICO_KINDS = (
    ("BGPConfiguration", "bgpconfigurations", False),
    ("BGPFilter", "bgpfilters", False),
    ("BGPPeer", "bgppeers", False),
    ("BlockAffinity", "blockaffinities", False),
    ("CalicoNodeStatus", "caliconodestatuses", False),
    ("ClusterInformation", "clusterinformations", False),
    ("FelixConfiguration", "felixconfigurations", False),
    ("GlobalNetworkPolicy", "globalnetworkpolicies", False),
    ("GlobalNetworkSet", "globalnetworksets", False),
    ("HostEndpoint", "hostendpoints", False),
    ("IPAMBlock", "ipamblocks", False),
    ("IPAMConfig", "ipamconfigs", False),
    ("IPAMHandle", "ipamhandles", False),
    ("IPPool", "ippools", False),
    ("IPReservation", "ipreservations", False),
    ("KubeControllersConfiguration", "kubecontrollersconfigurations", False),
    ("NetworkPolicy", "networkpolicies", True),
    ("NetworkSet", "networksets", True),
    ("StagedGlobalNetworkPolicy", "stagedglobalnetworkpolicies", False),
    ("StagedKubernetesNetworkPolicy", "stagedkubernetesnetworkpolicies", True),
    ("StagedNetworkPolicy", "stagednetworkpolicies", True),
    ("Tier", "tiers", False),
)
# Kubernetes SIG Network's admin network policy API, which calico-node watches since Calico 3.29.
POLICY_GROUP = "policy.networking.k8s.io"
POLICY_KINDS = (
    ("AdminNetworkPolicy", "adminnetworkpolicies"),
    ("BaselineAdminNetworkPolicy", "baselineadminnetworkpolicies"),
)
# CRDs of a *.k8s.io group need the API review's approval; this is the one of the network-policy-api project.
POLICY_API_APPROVAL = "https://github.com/kubernetes-sigs/network-policy-api/pull/30"

# calico-node reads every Calico kind but its IPAM bookkeeping and kube-controllers' configuration.
_CALICO_READS = sorted(
    plural for _kind, plural, _ns in CALICO_KINDS if plural not in ("ipamconfigs", "ipamhandles", "kubecontrollersconfigurations")
)
_IPAM = ["blockaffinities", "ipamblocks", "ipamhandles"]
_READ = ["get", "list", "watch"]
_WRITE = ["get", "list", "create", "update", "delete"]


@dataclass(frozen=True)
class CalicoSettings:
    """What a site chooses about Calico; ``calico_objects`` validates it first."""

    pod_cidr: str
    version: str = "v3.31.3"
    image_registry: str = "quay.io/calico"
    block_size: int | None = None  # 26 for an IPv4 pod CIDR, 122 for an IPv6 one
    encapsulation: str = "vxlan"
    encapsulation_mode: str = "Always"
    base_mtu: int = 1500
    vpn: bool = False
    vpn_mtu: int = DEFAULT_VPN_MTU  # the WireGuard interface's MTU, which the VPN's traffic must fit
    ip_autodetection_method: str = "first-found"
    nat_outgoing: bool = True
    admin_network_policy_crds: bool = True
    namespace: str = "kube-system"
    node_cpu_request: str = "250m"  # calico-node's CPU request, upstream's; "0" for none


def settings_from(pod_cidr, options: dict, prefix: str = "calico_") -> CalicoSettings:
    """Settings from keyword options, an unknown one reported with the closest known name."""
    return settings_of(CalicoSettings, "calico", pod_cidr, options, prefix)


@dataclass(frozen=True)
class _Checked:
    """Settings after validation: parsed network, integer sizes."""

    settings: CalicoSettings
    network: ipaddress.IPv4Network | ipaddress.IPv6Network
    block_size: int
    base_mtu: int
    veth_mtu: int

    @property
    def family(self) -> int:
        return self.network.version


def pod_mtu(base_mtu: int, encapsulation: str, vpn: bool, ip_version: int = 4, vpn_mtu: int = DEFAULT_VPN_MTU) -> int:
    """MTU of the pods' interfaces and Calico's tunnel: the smallest MTU on the way (the network's, or the WireGuard
    interface's when pod traffic crosses the VPN) less the encapsulation's headers."""
    overhead = ENCAPSULATION_OVERHEAD[(encapsulation, ip_version)]
    return (min(base_mtu, vpn_mtu) if vpn else base_mtu) - overhead


def check_settings(settings: CalicoSettings, prefix: str = "calico_") -> _Checked:
    """Every problem with the settings at once, each naming the variable (``prefix`` + field), value and reason."""
    problems: list[Problem] = []

    def problem(field: str, message: str) -> None:
        problems.append(Problem("calico", prefix + field, message))

    s = settings
    if not isinstance(s.version, str) or not re.fullmatch(r"v\d+\.\d+\.\d+(-[0-9A-Za-z.-]+)?", s.version):
        problem("version", f"{describe(s.version)} is not a Calico release tag such as 'v3.31.3'")
    if not isinstance(s.image_registry, str) or not re.fullmatch(r"[a-z0-9]([a-z0-9._:/-]*[a-z0-9])?", s.image_registry or ""):
        problem("image_registry", f"{describe(s.image_registry)} is not an image registry path such as 'quay.io/calico'")

    network = None
    if not isinstance(s.pod_cidr, str):
        problem("pod_cidr", f"{describe(s.pod_cidr)} is not a network in CIDR notation such as '10.244.0.0/16'")
    elif "/" not in s.pod_cidr:
        problem("pod_cidr", f"{s.pod_cidr!r} has no prefix length; write a network such as '10.244.0.0/16'")
    else:
        try:
            network = ipaddress.ip_network(s.pod_cidr.strip(), strict=True)
        except ValueError as exc:
            hint = ""
            try:
                hint = f"; did you mean '{ipaddress.ip_network(s.pod_cidr.strip(), strict=False)}'?"
            except ValueError:
                pass
            problem("pod_cidr", f"{s.pod_cidr!r} is not an IPv4 or IPv6 network: {exc}{hint}")

    family = network.version if network else 4
    block_size = _integer(s.block_size if s.block_size is not None else (26 if family == 4 else 122))
    low, high = BLOCK_SIZE_RANGE[family]
    if block_size is None or not low <= block_size <= high:
        problem("block_size", f"{describe(s.block_size)} is not a block size for IPv{family}: an integer from {low} to {high}")
        block_size = None
    elif network is not None and block_size < network.prefixlen:
        problem(
            "block_size",
            f"{block_size} makes blocks larger than the pod CIDR {network} (/{network.prefixlen}); "
            f"use a block size of at least {network.prefixlen}",
        )

    if s.encapsulation not in ENCAPSULATIONS:
        problem(
            "encapsulation",
            f"{describe(s.encapsulation)} is not one of {', '.join(ENCAPSULATIONS)}"
            f"{did_you_mean(s.encapsulation, ENCAPSULATIONS)}",
        )
    elif s.encapsulation == "ipip" and family == 6:
        problem("encapsulation", "'ipip' carries IPv4 only; an IPv6 pod CIDR takes 'vxlan' or 'none'")
    if s.encapsulation_mode not in ENCAPSULATION_MODES:
        problem(
            "encapsulation_mode",
            f"{describe(s.encapsulation_mode)} is not one of {', '.join(ENCAPSULATION_MODES)}"
            f"{did_you_mean(s.encapsulation_mode, ENCAPSULATION_MODES)}",
        )

    base_mtu = _integer(s.base_mtu)
    veth_mtu = 0
    if base_mtu is None or not BASE_MTU_RANGE[0] <= base_mtu <= BASE_MTU_RANGE[1]:
        problem("base_mtu", f"{describe(s.base_mtu)} is not an MTU: an integer from {BASE_MTU_RANGE[0]} to {BASE_MTU_RANGE[1]}")
    elif s.encapsulation in ENCAPSULATIONS and (s.encapsulation, family) in ENCAPSULATION_OVERHEAD and isinstance(s.vpn, bool):
        vpn_mtu = _integer(s.vpn_mtu)
        if vpn_mtu is None or not 1280 <= vpn_mtu <= 9000:
            problem("vpn_mtu", f"{describe(s.vpn_mtu)} is not the VPN interface's MTU: an integer from 1280 to 9000")
            vpn_mtu = DEFAULT_VPN_MTU
        veth_mtu = pod_mtu(base_mtu, s.encapsulation, s.vpn, family, vpn_mtu)
        if veth_mtu < MIN_POD_MTU[family]:
            problem(
                "base_mtu",
                f"{base_mtu} leaves pods an MTU of {veth_mtu} after {s.encapsulation} encapsulation"
                f"{' and the WireGuard VPN' if s.vpn else ''}, below IPv{family}'s minimum of {MIN_POD_MTU[family]}",
            )

    for field in ("vpn", "nat_outgoing", "admin_network_policy_crds"):
        if not isinstance(getattr(s, field), bool):
            problem(field, f"{describe(getattr(s, field))} is not a boolean (true or false)")

    _check_autodetection(s.ip_autodetection_method, problem)
    if not isinstance(s.namespace, str) or not re.fullmatch(r"[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?", s.namespace):
        problem("namespace", f"{describe(s.namespace)} is not a namespace name (a DNS label)")

    if not isinstance(s.node_cpu_request, str) or not re.fullmatch(r"(0|[1-9][0-9]*m|[0-9]+(\.[0-9]+)?)", s.node_cpu_request):
        problem("node_cpu_request", f"{describe(s.node_cpu_request)} is not a CPU quantity such as 250m, 1 or 0")

    if problems:
        raise SpecError(problems, title="invalid Calico settings")
    return _Checked(settings, network, block_size, base_mtu, veth_mtu)


def _check_autodetection(method, problem) -> None:
    known = (
        "first-found, kubernetes-internal-ip, can-reach=<address or name>, interface=<regex>, skip-interface=<regex>, cidr=<cidr>"
    )
    if not isinstance(method, str) or not method:
        problem("ip_autodetection_method", f"{describe(method)} is not an IP autodetection method ({known})")
        return
    if method in AUTODETECTION_VALUES:
        return
    prefix = next((p for p in AUTODETECTION_PREFIXES if method.startswith(p)), None)
    if prefix is None or not method[len(prefix) :].strip():
        problem("ip_autodetection_method", f"{method!r} is not an IP autodetection method ({known})")
        return
    if prefix == "cidr=":
        for part in method[len(prefix) :].split(","):
            try:
                ipaddress.ip_network(part.strip(), strict=False)
            except ValueError as exc:
                problem("ip_autodetection_method", f"{method!r}: {part.strip()!r} is not a network: {exc}")


def calico_objects(settings: CalicoSettings, prefix: str = "calico_") -> list[dict]:
    """The Kubernetes objects of a Calico install, in apply order (CRDs first, then the IPPool that needs them)."""
    checked = check_settings(settings, prefix)
    s = settings
    labels = {MANAGED_BY: "kuberos", "app.kubernetes.io/part-of": "calico"}
    config = _config_map(checked, labels)
    objects = [_crd(kind, plural, namespaced, labels) for kind, plural, namespaced in CALICO_KINDS]
    if s.admin_network_policy_crds:
        objects.extend(_policy_crd(kind, plural, labels) for kind, plural in POLICY_KINDS)
    objects.append(_ip_pool(checked, labels))
    for name in (KUBE_CONTROLLERS, NODE, CNI_PLUGIN):
        objects.append(
            {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": {"name": name, "namespace": s.namespace, "labels": labels}}
        )
    objects.append(config)
    for name, rules in ((KUBE_CONTROLLERS, _kube_controllers_rules()), (NODE, _node_rules()), (CNI_PLUGIN, _cni_rules())):
        objects.append(
            {"apiVersion": RBAC_API, "kind": "ClusterRole", "metadata": {"name": name, "labels": labels}, "rules": rules}
        )
        objects.append(
            {
                "apiVersion": RBAC_API,
                "kind": "ClusterRoleBinding",
                "metadata": {"name": name, "labels": labels},
                "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": name},
                "subjects": [{"kind": "ServiceAccount", "name": name, "namespace": s.namespace}],
            }
        )
    objects.append(_node_daemonset(checked, labels, config))
    objects.append(_kube_controllers_deployment(checked, labels))
    objects.append(
        {
            "apiVersion": "policy/v1",
            "kind": "PodDisruptionBudget",
            "metadata": {"name": KUBE_CONTROLLERS, "namespace": s.namespace, "labels": labels},
            "spec": {"maxUnavailable": 1, "selector": {"matchLabels": {"k8s-app": KUBE_CONTROLLERS}}},
        }
    )
    return objects


# --- CustomResourceDefinitions ------------------------------------------------------------------------

_OPEN_OBJECT = {"type": "object", "x-kubernetes-preserve-unknown-fields": True}
_MODE = {"type": "string", "enum": ["", "Never", "Always", "CrossSubnet"]}
# The IPPool fields this collection writes, typed; Calico's other IPPool fields are kept as written.
IPPOOL_SPEC_SCHEMA = {
    "type": "object",
    "required": ["cidr"],
    "properties": {
        "cidr": {"type": "string", "description": "The pool's network, in CIDR notation."},
        "blockSize": {
            "type": "integer",
            "minimum": 20,
            "maximum": 128,
            "description": "Prefix length of each node's address block.",
        },
        "ipipMode": {**_MODE, "description": "When to encapsulate pod traffic in IP-in-IP."},
        "vxlanMode": {**_MODE, "description": "When to encapsulate pod traffic in VXLAN."},
        "natOutgoing": {"type": "boolean", "description": "Masquerade traffic from pods to destinations outside every pool."},
        "nodeSelector": {"type": "string", "description": "Calico selector of the nodes that take addresses from the pool."},
        "disabled": {"type": "boolean", "description": "Assign no new addresses from the pool."},
    },
    "x-kubernetes-preserve-unknown-fields": True,
}


def _schema(spec: dict) -> dict:
    return {
        "type": "object",
        "properties": {
            "apiVersion": {"type": "string"},
            "kind": {"type": "string"},
            "metadata": {"type": "object"},
            "spec": spec,
            "status": _OPEN_OBJECT,
        },
    }


def _crd(kind: str, plural: str, namespaced: bool, labels: dict) -> dict:
    spec_schema = IPPOOL_SPEC_SCHEMA if kind == "IPPool" else _OPEN_OBJECT
    return {
        "apiVersion": CRD_API,
        "kind": "CustomResourceDefinition",
        "metadata": {"name": f"{plural}.{GROUP}", "labels": labels},
        "spec": {
            "group": GROUP,
            "names": {"kind": kind, "listKind": f"{kind}List", "plural": plural, "singular": kind.lower()},
            "scope": "Namespaced" if namespaced else "Cluster",
            "versions": [{"name": "v1", "served": True, "storage": True, "schema": {"openAPIV3Schema": _schema(spec_schema)}}],
        },
    }


def _policy_crd(kind: str, plural: str, labels: dict) -> dict:
    return {
        "apiVersion": CRD_API,
        "kind": "CustomResourceDefinition",
        "metadata": {
            "name": f"{plural}.{POLICY_GROUP}",
            "labels": labels,
            "annotations": {"api-approved.kubernetes.io": POLICY_API_APPROVAL},
        },
        "spec": {
            "group": POLICY_GROUP,
            "names": {"kind": kind, "listKind": f"{kind}List", "plural": plural, "singular": kind.lower()},
            "scope": "Cluster",
            "versions": [
                {
                    "name": "v1alpha1",
                    "served": True,
                    "storage": True,
                    "schema": {"openAPIV3Schema": _schema(_OPEN_OBJECT)},
                    "subresources": {"status": {}},
                }
            ],
        },
    }


def _ip_pool(checked: _Checked, labels: dict) -> dict:
    s = checked.settings
    encapsulated = "Never" if s.encapsulation == "none" else s.encapsulation_mode
    return {
        "apiVersion": f"{GROUP}/v1",
        "kind": "IPPool",
        "metadata": {"name": f"default-ipv{checked.family}-ippool", "labels": labels},
        "spec": {
            "cidr": str(checked.network),
            "blockSize": checked.block_size,
            "ipipMode": encapsulated if s.encapsulation == "ipip" else "Never",
            "vxlanMode": encapsulated if s.encapsulation == "vxlan" else "Never",
            "natOutgoing": s.nat_outgoing,
            "nodeSelector": "all()",
            "disabled": False,
        },
    }


# --- RBAC ---------------------------------------------------------------------------------------------


def _node_rules() -> list[dict]:
    """calico-node: Felix, BIRD/confd and the node's start-up; the CNI plugin's token."""
    return [
        _rule("", ["serviceaccounts/token"], ["create"], [CNI_PLUGIN]),
        _rule("", ["pods", "nodes", "namespaces", "serviceaccounts", "endpoints", "services"], _READ),
        _rule("", ["configmaps"], ["get"]),  # kubeadm's pod CIDR
        _rule("", ["nodes/status"], ["patch", "update"]),  # NetworkUnavailable and Calico's node annotations
        _rule("", ["pods/status"], ["patch"]),
        _rule("discovery.k8s.io", ["endpointslices"], ["list", "watch"]),
        _rule("networking.k8s.io", ["networkpolicies"], ["list", "watch"]),
        _rule(POLICY_GROUP, [p for _k, p in POLICY_KINDS] + ["clusternetworkpolicies"], ["list", "watch"]),
        _rule(GROUP, _CALICO_READS, _READ),
        # Kinds of Calico's old datastore, which calico-node's start-up reads to know whether to migrate (there are no
        # such CRDs, so it finds none; without the permission, releases up to 3.28 at least refuse to start).
        _rule(GROUP, ["globalfelixconfigs", "globalbgpconfigs"], _READ),
        _rule(
            GROUP,
            ["ippools", "felixconfigurations", "bgpconfigurations", "bgppeers", "clusterinformations"],
            ["create", "update"],
        ),
        _rule(GROUP, ["tiers"], ["create"]),
        _rule(GROUP, ["caliconodestatuses"], ["update"]),
        _rule(GROUP, _IPAM, _WRITE),
        _rule(GROUP, ["ipamconfigs"], ["get", "create"]),
        _rule("apps", ["daemonsets"], ["get"]),
    ]


def _cni_rules() -> list[dict]:
    """The CNI plugin, with the token calico-node mints for it: pod addresses from Calico IPAM."""
    return [
        _rule("", ["pods", "nodes", "namespaces"], ["get"]),
        _rule("", ["pods/status"], ["patch"]),
        _rule(GROUP, [*_IPAM, "clusterinformations", "ippools", "ipreservations", "ipamconfigs"], _WRITE),
    ]


def _controllers(version: str) -> str:
    """kube-controllers' controllers: the node controller (IPAM garbage collection), and the load-balancer IPAM
    controller from Calico 3.29 on (3.28 and older exit on a controller they do not know)."""
    major, minor = (int(part) for part in re.match(r"v(\d+)\.(\d+)", version).groups())
    return "node,loadbalancer" if (major, minor) >= (3, 29) else "node"


def _kube_controllers_rules() -> list[dict]:
    """calico-kube-controllers: IPAM garbage collection, node and load-balancer controllers."""
    return [
        _rule("", ["nodes", "pods", "namespaces"], _READ),
        _rule("", ["services", "services/status"], ["get", "list", "watch", "update"]),
        _rule(GROUP, ["ipreservations"], ["list"]),
        _rule(GROUP, [*_IPAM, "ipamconfigs", "tiers", "hostendpoints"], [*_WRITE, "watch"]),
        _rule(GROUP, ["ippools"], ["list", "watch"]),
        _rule(GROUP, ["clusterinformations", "kubecontrollersconfigurations"], ["get", "list", "watch", "create", "update"]),
        _rule(GROUP, ["kubecontrollersconfigurations/status"], ["get", "update"]),
        _rule(
            GROUP,
            ["networkpolicies", "stagednetworkpolicies", "globalnetworkpolicies", "stagedglobalnetworkpolicies"],
            [*_WRITE, "watch"],
        ),
        _rule("apps", ["daemonsets"], ["get"], [NODE]),
    ]


# --- configuration and workloads ----------------------------------------------------------------------


def _backend(settings: CalicoSettings) -> str:
    """BIRD (BGP) routes IP-in-IP and unencapsulated pools; a VXLAN pool needs no BGP."""
    return "vxlan" if settings.encapsulation == "vxlan" else "bird"


def _config_map(checked: _Checked, labels: dict) -> dict:
    ipam = {"type": "calico-ipam"}
    if checked.family == 6:
        ipam.update({"assign_ipv4": "false", "assign_ipv6": "true"})
    network = {
        "name": "k8s-pod-network",
        "cniVersion": "0.3.1",
        "plugins": [
            {
                "type": "calico",
                "log_level": "info",
                "log_file_path": "/var/log/calico/cni/cni.log",
                "datastore_type": "kubernetes",
                "nodename": "__KUBERNETES_NODE_NAME__",
                "mtu": "__CNI_MTU__",
                "ipam": ipam,
                "policy": {"type": "k8s"},
                "kubernetes": {"kubeconfig": "__KUBECONFIG_FILEPATH__"},
            },
            {"type": "portmap", "snat": True, "capabilities": {"portMappings": True}},
        ],
    }
    # install-cni substitutes the placeholders; the MTU is a number in the installed file.
    text = json.dumps(network, indent=2).replace('"__CNI_MTU__"', "__CNI_MTU__")
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": CONFIG, "namespace": checked.settings.namespace, "labels": labels},
        "data": {
            "typha_service_name": "none",
            "calico_backend": _backend(checked.settings),
            "veth_mtu": str(checked.veth_mtu),
            "cni_network_config": text,
        },
    }


def _from_config(name: str, key: str) -> dict:
    return {"name": name, "valueFrom": {"configMapKeyRef": {"name": CONFIG, "key": key}}}


def _env(name: str, value) -> dict:
    return {"name": name, "value": str(value)}


def _node_env(checked: _Checked) -> list[dict]:
    s = checked.settings
    family = checked.family
    pool = f"CALICO_IPV{family}POOL"
    mode = "Never" if s.encapsulation == "none" else s.encapsulation_mode
    env = [
        _env("DATASTORE_TYPE", "kubernetes"),
        _env("WAIT_FOR_DATASTORE", "true"),
        {"name": "NODENAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}},
        _from_config("CALICO_NETWORKING_BACKEND", "calico_backend"),
        _env("CLUSTER_TYPE", "k8s,bgp" if _backend(s) == "bird" else "k8s"),
        _env("IP", "autodetect" if family == 4 else "none"),
        _env("IP_AUTODETECTION_METHOD", s.ip_autodetection_method),
    ]
    if family == 6:
        env += [_env("IP6", "autodetect"), _env("IP6_AUTODETECTION_METHOD", s.ip_autodetection_method)]
    env += [
        # The pool calico-node would create if none existed; the role applies the same pool first.
        _env(f"{pool}_CIDR", checked.network),
        _env(f"{pool}_BLOCK_SIZE", checked.block_size),
        _env(f"{pool}_NAT_OUTGOING", "true" if s.nat_outgoing else "false"),
    ]
    if family == 4:
        env.append(_env("CALICO_IPV4POOL_IPIP", mode if s.encapsulation == "ipip" else "Never"))
    env += [
        _env(f"{pool}_VXLAN", mode if s.encapsulation == "vxlan" else "Never"),
        # The tunnel devices take the pods' MTU (veth_mtu), set for the encapsulation and the VPN.
        _from_config("FELIX_IPINIPMTU", "veth_mtu"),
        _from_config("FELIX_VXLANMTU", "veth_mtu"),
        _from_config("FELIX_VXLANMTUV6", "veth_mtu"),
        _env("CALICO_DISABLE_FILE_LOGGING", "true"),
        _env("FELIX_DEFAULTENDPOINTTOHOSTACTION", "ACCEPT"),
        _env("FELIX_IPV6SUPPORT", "true" if family == 6 else "false"),
        _env("FELIX_HEALTHENABLED", "true"),
    ]
    return env


def _host_path(name: str, path: str, kind: str | None = None) -> dict:
    host_path = {"path": path}
    if kind:
        host_path["type"] = kind
    return {"name": name, "hostPath": host_path}


def _node_daemonset(checked: _Checked, labels: dict, config: dict) -> dict:
    s = checked.settings
    probes = ["-felix-live"] if _backend(s) == "vxlan" else ["-felix-live", "-bird-live"]
    ready = ["-felix-ready"] if _backend(s) == "vxlan" else ["-felix-ready", "-bird-ready"]
    # Pods read the ConfigMap at start only: its hash in the template rolls them when it changes.
    config_hash = hashlib.sha256(json.dumps(config["data"], sort_keys=True).encode()).hexdigest()[:16]
    install_cni = {
        "name": "install-cni",
        "image": f"{s.image_registry}/cni:{s.version}",
        "imagePullPolicy": "IfNotPresent",
        "command": ["/opt/cni/bin/install"],
        "env": [
            _env("CNI_CONF_NAME", "10-calico.conflist"),
            _from_config("CNI_NETWORK_CONFIG", "cni_network_config"),
            {"name": "KUBERNETES_NODE_NAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}},
            _from_config("CNI_MTU", "veth_mtu"),
            _env("SLEEP", "false"),
        ],
        "volumeMounts": [
            {"name": "cni-bin-dir", "mountPath": "/host/opt/cni/bin"},
            {"name": "cni-net-dir", "mountPath": "/host/etc/cni/net.d"},
        ],
        "securityContext": {"privileged": True},
    }
    node = {
        "name": NODE,
        "image": f"{s.image_registry}/node:{s.version}",
        "imagePullPolicy": "IfNotPresent",
        "env": _node_env(checked),
        "securityContext": {"privileged": True},
        "resources": {"requests": {"cpu": s.node_cpu_request}} if s.node_cpu_request != "0" else {},
        "lifecycle": {"preStop": {"exec": {"command": ["/bin/calico-node", "-shutdown"]}}},
        "livenessProbe": {
            "exec": {"command": ["/bin/calico-node", *probes]},
            "periodSeconds": 10,
            "initialDelaySeconds": 10,
            "failureThreshold": 6,
            "timeoutSeconds": 10,
        },
        "readinessProbe": {"exec": {"command": ["/bin/calico-node", *ready]}, "periodSeconds": 10, "timeoutSeconds": 10},
        "volumeMounts": [
            {"name": "cni-net-dir", "mountPath": "/host/etc/cni/net.d"},
            {"name": "lib-modules", "mountPath": "/lib/modules", "readOnly": True},
            {"name": "xtables-lock", "mountPath": "/run/xtables.lock"},
            {"name": "var-run-calico", "mountPath": "/var/run/calico"},
            {"name": "var-lib-calico", "mountPath": "/var/lib/calico"},
            {"name": "policysync", "mountPath": "/var/run/nodeagent"},
            {"name": "cni-log-dir", "mountPath": "/var/log/calico/cni", "readOnly": True},
        ],
    }
    selector = {"k8s-app": NODE}
    return {
        "apiVersion": "apps/v1",
        "kind": "DaemonSet",
        "metadata": {"name": NODE, "namespace": s.namespace, "labels": {**labels, **selector}},
        "spec": {
            "selector": {"matchLabels": selector},
            "updateStrategy": {"type": "RollingUpdate", "rollingUpdate": {"maxUnavailable": 1}},
            "template": {
                "metadata": {"labels": selector, "annotations": {CONFIG_HASH_ANNOTATION: config_hash}},
                "spec": {
                    "nodeSelector": {"kubernetes.io/os": "linux"},
                    "hostNetwork": True,
                    # Every node needs the CNI, robots included: their taint kuberos.io/robot=<robot>:NoSchedule
                    # (and any other NoSchedule or NoExecute taint) is tolerated.
                    "tolerations": [
                        {"key": ROBOT_TAINT, "operator": "Exists", "effect": "NoSchedule"},
                        {"operator": "Exists", "effect": "NoSchedule"},
                        {"operator": "Exists", "effect": "NoExecute"},
                        {"key": "CriticalAddonsOnly", "operator": "Exists"},
                    ],
                    "serviceAccountName": NODE,
                    "securityContext": {"seccompProfile": {"type": "RuntimeDefault"}},
                    "terminationGracePeriodSeconds": 0,
                    "priorityClassName": "system-node-critical",
                    "initContainers": [install_cni],
                    "containers": [node],
                    "volumes": [
                        _host_path("lib-modules", "/lib/modules"),
                        _host_path("var-run-calico", "/var/run/calico", "DirectoryOrCreate"),
                        _host_path("var-lib-calico", "/var/lib/calico", "DirectoryOrCreate"),
                        _host_path("xtables-lock", "/run/xtables.lock", "FileOrCreate"),
                        _host_path("cni-bin-dir", "/opt/cni/bin", "DirectoryOrCreate"),
                        _host_path("cni-net-dir", "/etc/cni/net.d"),
                        _host_path("cni-log-dir", "/var/log/calico/cni"),
                        _host_path("policysync", "/var/run/nodeagent", "DirectoryOrCreate"),
                    ],
                },
            },
        },
    }


def _kube_controllers_deployment(checked: _Checked, labels: dict) -> dict:
    s = checked.settings
    selector = {"k8s-app": KUBE_CONTROLLERS}
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {"name": KUBE_CONTROLLERS, "namespace": s.namespace, "labels": {**labels, **selector}},
        "spec": {
            "replicas": 1,  # one active instance only
            "selector": {"matchLabels": selector},
            "strategy": {"type": "Recreate"},
            "template": {
                "metadata": {"labels": selector},
                "spec": {
                    "nodeSelector": {"kubernetes.io/os": "linux"},
                    "tolerations": [
                        {"key": "CriticalAddonsOnly", "operator": "Exists"},
                        {"key": "node-role.kubernetes.io/control-plane", "operator": "Exists", "effect": "NoSchedule"},
                    ],
                    "serviceAccountName": KUBE_CONTROLLERS,
                    "securityContext": {"seccompProfile": {"type": "RuntimeDefault"}},
                    "priorityClassName": "system-cluster-critical",
                    "containers": [
                        {
                            "name": KUBE_CONTROLLERS,
                            "image": f"{s.image_registry}/kube-controllers:{s.version}",
                            "imagePullPolicy": "IfNotPresent",
                            "env": [_env("ENABLED_CONTROLLERS", _controllers(s.version)), _env("DATASTORE_TYPE", "kubernetes")],
                            "livenessProbe": {
                                "exec": {"command": ["/usr/bin/check-status", "-l"]},
                                "periodSeconds": 10,
                                "initialDelaySeconds": 10,
                                "failureThreshold": 6,
                                "timeoutSeconds": 10,
                            },
                            "readinessProbe": {"exec": {"command": ["/usr/bin/check-status", "-r"]}, "periodSeconds": 10},
                            "securityContext": {"runAsNonRoot": True},
                        }
                    ],
                },
            },
        },
    }
