"""Cilium, the cluster's CNI, as Kubernetes objects: the agent on every node and the generic operator.

``cilium_objects`` returns, in apply order: the ServiceAccounts, least-privilege ClusterRoles and their bindings of
the agent and the operator, the ``cilium-config`` ConfigMap, the ``cilium-operator`` Deployment and the ``cilium``
DaemonSet (on every node, tainted robot nodes and not-ready nodes included). Cilium's CustomResourceDefinitions are
not among them: the operator registers its release's own when it starts, and the agents wait for them.

The choices are a site's usual ones beside kubeadm's kube-proxy: a VXLAN (or Geneve) overlay between nodes, so that a
robot, an edge server and a cloud VM behind the VPN reach each other's pods over whatever routes their node
addresses; IPAM from the nodes' ``podCIDR`` (kubeadm's controller manager gives every node a slice of the pod
network); Kubernetes NetworkPolicy enforced in the agents' eBPF datapath; pods masqueraded when they leave the pod
network; no kube-proxy replacement, no L7 proxy, no Hubble.

The MTU the agent takes for the network (``mtu``) is the network's, or the WireGuard interface's when pod traffic
crosses the site's VPN; the agent subtracts the tunnel's own overhead from it for the pods (``pod_mtu``).
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe, did_you_mean
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cni import (
    BASE_MTU_RANGE,
    DEFAULT_VPN_MTU,
    MIN_POD_MTU,
    RBAC_API,
    _integer,
    _rule,
    check_cpu_request,
    check_image_registry,
    settings_of,
)

AGENT = "cilium"
OPERATOR = "cilium-operator"
CONFIG = "cilium-config"
CONFIG_HASH_ANNOTATION = "kuberos.io/cilium-config-hash"
GROUP = "cilium.io"
TUNNEL_PROTOCOLS = ("vxlan", "geneve")
# Bytes each packet loses to the tunnel: outer IPv4 + UDP + VXLAN (or Geneve without options) + inner Ethernet.
TUNNEL_OVERHEAD = {"vxlan": 50, "geneve": 50}
HEALTH_PORT = 9879  # the agent's /healthz (upstream's default)
OPERATOR_HEALTH_PORT = 9234  # the operator's API (/healthz)
_READ = ["get", "list", "watch"]

# Every cilium.io kind the 1.15 agent lists and watches.
AGENT_WATCHES = [
    "ciliumloadbalancerippools",
    "ciliumbgppeeringpolicies",
    "ciliumbgpnodeconfigs",
    "ciliumbgpadvertisements",
    "ciliumbgppeerconfigs",
    "ciliumclusterwideenvoyconfigs",
    "ciliumclusterwidenetworkpolicies",
    "ciliumegressgatewaypolicies",
    "ciliumendpoints",
    "ciliumendpointslices",
    "ciliumenvoyconfigs",
    "ciliumidentities",
    "ciliumlocalredirectpolicies",
    "ciliumnetworkpolicies",
    "ciliumnodes",
    "ciliumnodeconfigs",
    "ciliumcidrgroups",
    "ciliuml2announcementpolicies",
    "ciliumpodippools",
]
# The CRDs the 1.15 operator registers (and may update).
OPERATOR_CRDS = [
    f"{plural}.{GROUP}"
    for plural in (
        "ciliumloadbalancerippools",
        "ciliumbgppeeringpolicies",
        "ciliumbgpclusterconfigs",
        "ciliumbgppeerconfigs",
        "ciliumbgpadvertisements",
        "ciliumbgpnodeconfigs",
        "ciliumbgpnodeconfigoverrides",
        "ciliumclusterwideenvoyconfigs",
        "ciliumclusterwidenetworkpolicies",
        "ciliumegressgatewaypolicies",
        "ciliumendpoints",
        "ciliumendpointslices",
        "ciliumenvoyconfigs",
        "ciliumexternalworkloads",
        "ciliumidentities",
        "ciliumlocalredirectpolicies",
        "ciliumnetworkpolicies",
        "ciliumnodes",
        "ciliumnodeconfigs",
        "ciliumcidrgroups",
        "ciliuml2announcementpolicies",
        "ciliumpodippools",
    )
]


@dataclass(frozen=True)
class CiliumSettings:
    """What a site chooses about Cilium; ``cilium_objects`` validates it first."""

    pod_cidr: str
    version: str = "v1.15.19"
    image_registry: str = "quay.io/cilium"
    tunnel_protocol: str = "vxlan"
    base_mtu: int = 1500
    vpn: bool = False
    vpn_mtu: int = DEFAULT_VPN_MTU  # the WireGuard interface's MTU, which the VPN's traffic must fit
    masquerade: bool = True
    namespace: str = "kube-system"
    agent_cpu_request: str = "100m"  # the agent's CPU request; "0" for none
    operator_replicas: int = 1


def settings_from(pod_cidr, options: dict, prefix: str = "cilium_") -> CiliumSettings:
    """Settings from keyword options, an unknown one reported with the closest known name."""
    return settings_of(CiliumSettings, "cilium", pod_cidr, options, prefix)


def network_mtu(base_mtu: int, vpn: bool, vpn_mtu: int = DEFAULT_VPN_MTU) -> int:
    """The MTU the agent is told the nodes' network has: the smallest on the way between nodes."""
    return min(base_mtu, vpn_mtu) if vpn else base_mtu


def pod_mtu(base_mtu: int, tunnel_protocol: str, vpn: bool, vpn_mtu: int = DEFAULT_VPN_MTU) -> int:
    """MTU of the pods' routes: the network's (or the VPN's) less the tunnel's headers, as the agent computes it."""
    return network_mtu(base_mtu, vpn, vpn_mtu) - TUNNEL_OVERHEAD[tunnel_protocol]


def check_settings(settings: CiliumSettings, prefix: str = "cilium_") -> dict:
    """Every problem with the settings at once, each naming the variable (``prefix`` + field), value and reason.
    Returns the derived values: ``network`` (the pod CIDR), ``mtu`` (the network's) and ``replicas``."""
    problems: list[Problem] = []

    def problem(field: str, message: str) -> None:
        problems.append(Problem("cilium", prefix + field, message))

    s = settings
    if not isinstance(s.version, str) or not re.fullmatch(r"v1\.\d+\.\d+(-[0-9A-Za-z.-]+)?", s.version):
        problem("version", f"{describe(s.version)} is not a Cilium release tag such as 'v1.15.19'")
    check_image_registry(s.image_registry, "quay.io/cilium", problem)
    network = None
    if not isinstance(s.pod_cidr, str) or "/" not in s.pod_cidr:
        problem("pod_cidr", f"{describe(s.pod_cidr)} is not a network in CIDR notation such as '10.244.0.0/16'")
    else:
        try:
            network = ipaddress.ip_network(s.pod_cidr.strip(), strict=True)
        except ValueError as exc:
            problem("pod_cidr", f"{s.pod_cidr!r} is not an IPv4 or IPv6 network: {exc}")
    if network is not None and network.version != 4:
        problem("pod_cidr", f"{network} is IPv6: the collection's Cilium settings carry an IPv4 pod network")
    if s.tunnel_protocol not in TUNNEL_PROTOCOLS:
        problem(
            "tunnel_protocol",
            f"{describe(s.tunnel_protocol)} is not one of {', '.join(TUNNEL_PROTOCOLS)}"
            f"{did_you_mean(s.tunnel_protocol, TUNNEL_PROTOCOLS)}",
        )
    for field in ("vpn", "masquerade"):
        if not isinstance(getattr(s, field), bool):
            problem(field, f"{describe(getattr(s, field))} is not a boolean (true or false)")
    base_mtu, vpn_mtu, mtu = _integer(s.base_mtu), _integer(s.vpn_mtu), 0
    if base_mtu is None or not BASE_MTU_RANGE[0] <= base_mtu <= BASE_MTU_RANGE[1]:
        problem("base_mtu", f"{describe(s.base_mtu)} is not an MTU: an integer from {BASE_MTU_RANGE[0]} to {BASE_MTU_RANGE[1]}")
    elif vpn_mtu is None or not 1280 <= vpn_mtu <= 9000:
        problem("vpn_mtu", f"{describe(s.vpn_mtu)} is not the VPN interface's MTU: an integer from 1280 to 9000")
    elif isinstance(s.vpn, bool) and s.tunnel_protocol in TUNNEL_PROTOCOLS:
        mtu = network_mtu(base_mtu, s.vpn, vpn_mtu)
        pods = pod_mtu(base_mtu, s.tunnel_protocol, s.vpn, vpn_mtu)
        if pods < MIN_POD_MTU[4]:
            problem(
                "base_mtu",
                f"{base_mtu} leaves pods an MTU of {pods} after {s.tunnel_protocol}"
                f"{' and the WireGuard VPN' if s.vpn else ''}, below IPv4's minimum of {MIN_POD_MTU[4]}",
            )
    if not isinstance(s.namespace, str) or not re.fullmatch(r"[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?", s.namespace):
        problem("namespace", f"{describe(s.namespace)} is not a namespace name (a DNS label)")
    check_cpu_request("agent_cpu_request", s.agent_cpu_request, "100m", problem)
    replicas = _integer(s.operator_replicas)
    if replicas is None or not 1 <= replicas <= 5:
        problem("operator_replicas", f"{describe(s.operator_replicas)} is not a number of operator replicas from 1 to 5")
    if problems:
        raise SpecError(problems, title="invalid Cilium settings")
    return {"network": network, "mtu": mtu, "replicas": replicas}


def cilium_objects(settings: CiliumSettings, prefix: str = "cilium_") -> list[dict]:
    """The Kubernetes objects of a Cilium install, in apply order."""
    checked = check_settings(settings, prefix)
    s = settings
    labels = {MANAGED_BY: "kuberos", "app.kubernetes.io/part-of": "cilium"}
    config = _config_map(s, checked, labels)
    objects = [
        {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": {"name": name, "namespace": s.namespace, "labels": labels}}
        for name in (AGENT, OPERATOR)
    ]
    objects.append(config)
    for name, rules in ((AGENT, _agent_rules()), (OPERATOR, _operator_rules())):
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
    # The agent's leases (its state for the Kubernetes-backed identity allocator lives in CRDs; leases are its
    # election for node-wide tasks) and the operator's leader election, in the namespace only.
    for name in (AGENT, OPERATOR):
        objects.append(
            {
                "apiVersion": RBAC_API,
                "kind": "Role",
                "metadata": {"name": f"{name}-leases", "namespace": s.namespace, "labels": labels},
                "rules": [_rule("coordination.k8s.io", ["leases"], ["create", "get", "update", "list", "delete"])],
            }
        )
        objects.append(
            {
                "apiVersion": RBAC_API,
                "kind": "RoleBinding",
                "metadata": {"name": f"{name}-leases", "namespace": s.namespace, "labels": labels},
                "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "Role", "name": f"{name}-leases"},
                "subjects": [{"kind": "ServiceAccount", "name": name, "namespace": s.namespace}],
            }
        )
    objects.append(_operator_deployment(s, checked, labels, config))
    objects.append(_agent_daemonset(s, labels, config))
    return objects


def images(settings: CiliumSettings) -> dict[str, str]:
    return {
        "agent": f"{settings.image_registry}/cilium:{settings.version}",
        "operator": f"{settings.image_registry}/operator-generic:{settings.version}",
    }


def _config_map(s: CiliumSettings, checked: dict, labels: dict) -> dict:
    data = {
        "cluster-name": "default",
        "cluster-id": "0",
        "identity-allocation-mode": "crd",
        "debug": "false",
        "enable-policy": "default",
        "enable-ipv4": "true",
        "enable-ipv6": "false",
        "ipam": "kubernetes",  # every node's podCIDR, which kubeadm's controller manager allocates
        "cluster-pool-ipv4-cidr": str(checked["network"]),
        "routing-mode": "tunnel",
        "tunnel-protocol": s.tunnel_protocol,
        "mtu": str(checked["mtu"]),
        "enable-ipv4-masquerade": "true" if s.masquerade else "false",
        "enable-bpf-masquerade": "false",  # iptables masquerading beside kube-proxy's rules
        "kube-proxy-replacement": "false",  # kubeadm's kube-proxy serves Services
        "bpf-lb-sock": "false",
        "enable-l7-proxy": "false",  # no Envoy in the image
        "enable-hubble": "false",
        "enable-health-checking": "false",
        "enable-endpoint-health-checking": "false",
        "enable-remote-node-identity": "true",
        "enable-well-known-identities": "false",
        "enable-k8s-endpoint-slice": "true",
        "enable-bgp-control-plane": "false",
        "enable-local-redirect-policy": "false",
        "enable-xt-socket-fallback": "true",
        "install-no-conntrack-iptables-rules": "false",
        "auto-direct-node-routes": "false",
        "preallocate-bpf-maps": "false",
        "bpf-map-dynamic-size-ratio": "0.0025",
        "bpf-root": "/sys/fs/bpf",
        "cgroup-root": "/run/cilium/cgroupv2",
        "monitor-aggregation": "medium",
        "monitor-aggregation-interval": "5s",
        "monitor-aggregation-flags": "all",
        "synchronize-k8s-nodes": "true",
        "set-cilium-is-up-condition": "true",
        "set-cilium-node-taints": "false",
        "remove-cilium-node-taints": "true",
        "operator-api-serve-addr": f"127.0.0.1:{OPERATOR_HEALTH_PORT}",
        "cni-exclusive": "true",
        "cni-log-file": "/var/run/cilium/cilium-cni.log",
        "write-cni-conf-when-ready": "/host/etc/cni/net.d/05-cilium.conflist",
        "agent-health-port": str(HEALTH_PORT),
    }
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": CONFIG, "namespace": s.namespace, "labels": labels},
        "data": data,
    }


def _config_hash(config: dict) -> str:
    return hashlib.sha256(json.dumps(config["data"], sort_keys=True).encode()).hexdigest()[:16]


# --- RBAC ---------------------------------------------------------------------------------------------


def _agent_rules() -> list[dict]:
    return [
        _rule("networking.k8s.io", ["networkpolicies"], _READ),
        _rule("discovery.k8s.io", ["endpointslices"], _READ),
        _rule("", ["namespaces", "services", "pods", "endpoints", "nodes"], _READ),
        _rule("", ["nodes/status"], ["patch"]),  # the node's NetworkUnavailable and CiliumIsUp conditions
        _rule("apiextensions.k8s.io", ["customresourcedefinitions"], ["list", "watch", "get"]),
        _rule(GROUP, AGENT_WATCHES, ["list", "watch"]),
        _rule(GROUP, ["ciliumidentities", "ciliumendpoints", "ciliumnodes"], ["create"]),
        _rule(GROUP, ["ciliumidentities"], ["update"]),
        _rule(GROUP, ["ciliumendpoints"], ["delete", "get"]),
        _rule(GROUP, ["ciliumnodes", "ciliumnodes/status"], ["get", "update"]),
        _rule(
            GROUP,
            [
                "ciliumnetworkpolicies/status",
                "ciliumclusterwidenetworkpolicies/status",
                "ciliumendpoints/status",
                "ciliumendpoints",
                "ciliuml2announcementpolicies/status",
                "ciliumbgpnodeconfigs/status",
            ],
            ["patch"],
        ),
    ]


def _operator_rules() -> list[dict]:
    return [
        _rule("", ["pods"], ["get", "list", "watch", "delete"]),  # restarts pods that started before the agent
        _rule("", ["nodes"], ["list", "watch"]),
        _rule("", ["nodes", "nodes/status"], ["patch"]),  # removes the agent-not-ready taint
        _rule("discovery.k8s.io", ["endpointslices"], _READ),
        _rule("", ["services/status"], ["update", "patch"]),
        _rule("", ["namespaces", "secrets"], _READ),
        _rule("", ["services", "endpoints"], ["get", "list", "watch", "create", "update", "delete", "patch"]),
        _rule(
            GROUP,
            ["ciliumnetworkpolicies", "ciliumclusterwidenetworkpolicies"],
            ["create", "update", "deletecollection", "patch", "get", "list", "watch"],
        ),
        _rule(GROUP, ["ciliumnetworkpolicies/status", "ciliumclusterwidenetworkpolicies/status"], ["patch", "update"]),
        _rule(GROUP, ["ciliumendpoints", "ciliumidentities"], ["delete", "list", "watch"]),
        _rule(GROUP, ["ciliumidentities"], ["update"]),
        _rule(GROUP, ["ciliumnodes"], ["create", "update", "get", "list", "watch", "delete"]),
        _rule(GROUP, ["ciliumnodes/status"], ["update"]),
        _rule(
            GROUP,
            [
                "ciliumendpointslices",
                "ciliumenvoyconfigs",
                "ciliumbgppeerconfigs",
                "ciliumbgpadvertisements",
                "ciliumbgpnodeconfigs",
            ],
            ["create", "update", "get", "list", "watch", "delete", "patch"],
        ),
        _rule("apiextensions.k8s.io", ["customresourcedefinitions"], ["create", "get", "list", "watch"]),
        _rule("apiextensions.k8s.io", ["customresourcedefinitions"], ["update"], OPERATOR_CRDS),
        _rule(
            GROUP,
            ["ciliumloadbalancerippools", "ciliumpodippools", "ciliumbgpclusterconfigs", "ciliumbgpnodeconfigoverrides"],
            _READ,
        ),
        _rule(GROUP, ["ciliumpodippools"], ["create"]),
        _rule(GROUP, ["ciliumloadbalancerippools/status"], ["patch"]),
    ]


# --- workloads ----------------------------------------------------------------------------------------


def _host_path(name: str, path: str, kind: str | None = None) -> dict:
    source = {"path": path}
    if kind:
        source["type"] = kind
    return {"name": name, "hostPath": source}


def _agent_daemonset(s: CiliumSettings, labels: dict, config: dict) -> dict:
    image = images(s)["agent"]
    env = [
        {"name": "K8S_NODE_NAME", "valueFrom": {"fieldRef": {"apiVersion": "v1", "fieldPath": "spec.nodeName"}}},
        {"name": "CILIUM_K8S_NAMESPACE", "valueFrom": {"fieldRef": {"apiVersion": "v1", "fieldPath": "metadata.namespace"}}},
    ]
    probe = {
        "httpGet": {
            "host": "127.0.0.1",
            "path": "/healthz",
            "port": HEALTH_PORT,
            "scheme": "HTTP",
            "httpHeaders": [{"name": "brief", "value": "true"}],
        },
    }
    privileged = {"privileged": True}
    pod_labels = {"k8s-app": AGENT, "app.kubernetes.io/name": "cilium-agent", **labels}
    resources = {"requests": {"memory": "200Mi"}}
    if s.agent_cpu_request != "0":
        resources["requests"]["cpu"] = s.agent_cpu_request
    return {
        "apiVersion": "apps/v1",
        "kind": "DaemonSet",
        "metadata": {"name": AGENT, "namespace": s.namespace, "labels": pod_labels},
        "spec": {
            "selector": {"matchLabels": {"k8s-app": AGENT}},
            "updateStrategy": {"type": "RollingUpdate", "rollingUpdate": {"maxUnavailable": 1}},
            "template": {
                "metadata": {"labels": pod_labels, "annotations": {CONFIG_HASH_ANNOTATION: _config_hash(config)}},
                "spec": {
                    "hostNetwork": True,
                    "priorityClassName": "system-node-critical",
                    "serviceAccountName": AGENT,
                    "automountServiceAccountToken": True,
                    "terminationGracePeriodSeconds": 1,
                    "restartPolicy": "Always",
                    # every node, whatever its taints (robots, control planes, not-ready nodes): it is their network
                    "tolerations": [{"operator": "Exists"}],
                    "nodeSelector": {"kubernetes.io/os": "linux"},
                    "initContainers": [
                        {
                            # the node's BPF filesystem, where the agent pins its maps (they outlive its restarts)
                            "name": "mount-bpf-fs",
                            "image": image,
                            "imagePullPolicy": "IfNotPresent",
                            "command": ["/bin/sh", "-c", "--"],
                            "args": ['mount | grep "/sys/fs/bpf type bpf" || mount -t bpf bpf /sys/fs/bpf'],
                            "securityContext": privileged,
                            "volumeMounts": [
                                {"name": "bpf-maps", "mountPath": "/sys/fs/bpf", "mountPropagation": "Bidirectional"}
                            ],
                        },
                        {
                            # the CNI plugin (and the loopback plugin where the node has none) into the node's /opt/cni/bin
                            "name": "install-cni-binaries",
                            "image": image,
                            "imagePullPolicy": "IfNotPresent",
                            "command": ["/install-plugin.sh"],
                            "securityContext": {"capabilities": {"drop": ["ALL"]}},
                            "volumeMounts": [{"name": "cni-path", "mountPath": "/host/opt/cni/bin"}],
                        },
                    ],
                    "containers": [
                        {
                            "name": "cilium-agent",
                            "image": image,
                            "imagePullPolicy": "IfNotPresent",
                            "command": ["cilium-agent"],
                            "args": ["--config-dir=/tmp/cilium/config-map"],
                            "env": env,
                            "startupProbe": {**probe, "failureThreshold": 150, "periodSeconds": 2, "successThreshold": 1},
                            "livenessProbe": {**probe, "periodSeconds": 30, "failureThreshold": 10, "timeoutSeconds": 5},
                            "readinessProbe": {**probe, "periodSeconds": 30, "failureThreshold": 3, "timeoutSeconds": 5},
                            "resources": resources,
                            "securityContext": privileged,
                            "terminationMessagePolicy": "FallbackToLogsOnError",
                            "volumeMounts": [
                                {"name": "bpf-maps", "mountPath": "/sys/fs/bpf", "mountPropagation": "HostToContainer"},
                                {"name": "cilium-run", "mountPath": "/var/run/cilium"},
                                {"name": "etc-cni-netd", "mountPath": "/host/etc/cni/net.d"},
                                {"name": "cilium-config-path", "mountPath": "/tmp/cilium/config-map", "readOnly": True},
                                {"name": "lib-modules", "mountPath": "/lib/modules", "readOnly": True},
                                {"name": "xtables-lock", "mountPath": "/run/xtables.lock"},
                                {"name": "host-proc-sys-net", "mountPath": "/host/proc/sys/net"},
                                {"name": "host-proc-sys-kernel", "mountPath": "/host/proc/sys/kernel"},
                                {"name": "tmp", "mountPath": "/tmp"},
                            ],
                        }
                    ],
                    "volumes": [
                        {"name": "tmp", "emptyDir": {}},
                        _host_path("cilium-run", "/var/run/cilium", "DirectoryOrCreate"),
                        _host_path("bpf-maps", "/sys/fs/bpf", "DirectoryOrCreate"),
                        _host_path("cni-path", "/opt/cni/bin", "DirectoryOrCreate"),
                        _host_path("etc-cni-netd", "/etc/cni/net.d", "DirectoryOrCreate"),
                        _host_path("lib-modules", "/lib/modules"),
                        _host_path("xtables-lock", "/run/xtables.lock", "FileOrCreate"),
                        _host_path("host-proc-sys-net", "/proc/sys/net", "Directory"),
                        _host_path("host-proc-sys-kernel", "/proc/sys/kernel", "Directory"),
                        {"name": "cilium-config-path", "configMap": {"name": CONFIG}},
                    ],
                },
            },
        },
    }


def _operator_deployment(s: CiliumSettings, checked: dict, labels: dict, config: dict) -> dict:
    pod_labels = {"k8s-app": OPERATOR, "io.cilium/app": "operator", "app.kubernetes.io/name": OPERATOR, **labels}
    probe = {"httpGet": {"host": "127.0.0.1", "path": "/healthz", "port": OPERATOR_HEALTH_PORT, "scheme": "HTTP"}}
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {"name": OPERATOR, "namespace": s.namespace, "labels": pod_labels},
        "spec": {
            "replicas": checked["replicas"],
            "selector": {"matchLabels": {"k8s-app": OPERATOR}},
            "strategy": {"type": "RollingUpdate", "rollingUpdate": {"maxSurge": 0, "maxUnavailable": 1}},
            "template": {
                "metadata": {"labels": pod_labels, "annotations": {CONFIG_HASH_ANNOTATION: _config_hash(config)}},
                "spec": {
                    # before any pod network exists: the operator registers the CRDs the agents wait for
                    "hostNetwork": True,
                    "priorityClassName": "system-cluster-critical",
                    "serviceAccountName": OPERATOR,
                    "restartPolicy": "Always",
                    "tolerations": [{"operator": "Exists"}],
                    "nodeSelector": {"kubernetes.io/os": "linux"},
                    # on the control planes (the edge servers of the server room) where there are any; one per node
                    "affinity": {
                        "nodeAffinity": {
                            "preferredDuringSchedulingIgnoredDuringExecution": [
                                {
                                    "weight": 100,
                                    "preference": {
                                        "matchExpressions": [
                                            {"key": "node-role.kubernetes.io/control-plane", "operator": "Exists"}
                                        ]
                                    },
                                }
                            ]
                        },
                        "podAntiAffinity": {
                            "requiredDuringSchedulingIgnoredDuringExecution": [
                                {
                                    "labelSelector": {"matchLabels": {"io.cilium/app": "operator"}},
                                    "topologyKey": "kubernetes.io/hostname",
                                }
                            ]
                        },
                    },
                    "containers": [
                        {
                            "name": "cilium-operator",
                            "image": images(s)["operator"],
                            "imagePullPolicy": "IfNotPresent",
                            "command": ["cilium-operator-generic"],
                            "args": ["--config-dir=/tmp/cilium/config-map", "--debug=false"],
                            "env": [
                                {
                                    "name": "K8S_NODE_NAME",
                                    "valueFrom": {"fieldRef": {"apiVersion": "v1", "fieldPath": "spec.nodeName"}},
                                },
                                {
                                    "name": "CILIUM_K8S_NAMESPACE",
                                    "valueFrom": {"fieldRef": {"apiVersion": "v1", "fieldPath": "metadata.namespace"}},
                                },
                            ],
                            "livenessProbe": {**probe, "initialDelaySeconds": 60, "periodSeconds": 10, "timeoutSeconds": 3},
                            "readinessProbe": {**probe, "periodSeconds": 5, "failureThreshold": 5, "timeoutSeconds": 3},
                            "resources": {"requests": {"memory": "64Mi"}},
                            "securityContext": {"allowPrivilegeEscalation": False, "capabilities": {"drop": ["ALL"]}},
                            "terminationMessagePolicy": "FallbackToLogsOnError",
                            "volumeMounts": [
                                {"name": "cilium-config-path", "mountPath": "/tmp/cilium/config-map", "readOnly": True}
                            ],
                        }
                    ],
                    "volumes": [{"name": "cilium-config-path", "configMap": {"name": CONFIG}}],
                },
            },
        },
    }
