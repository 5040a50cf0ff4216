"""The real nodes' configuration, rendered from their names and paths (pure): each node's names and addresses
(``NodeNet``), containerd's config, the CNI bridge's, the kubelet's and kube-proxy's configurations, CoreDNS's
Corefile. The lab (``kuberos_lab.real_nodes``) writes them and runs the programs."""

from __future__ import annotations

import json
from dataclasses import dataclass

CLUSTER_DOMAIN = "cluster.local"


def host_address(base: int) -> str:
    """The root namespace's address on the management bridge of the real nodes of ``base``: the API server relay,
    CoreDNS and the registry listen there (and the API server advertises it)."""
    return f"10.{base}.0.1"


@dataclass(frozen=True)
class NodeNet:
    """One real node's names and addresses."""

    name: str
    index: int
    tag: str
    base: int

    @property
    def netns(self) -> str:
        return f"{self.tag}n-{self.name}"

    @property
    def veth(self) -> str:
        return f"{self.tag}m{self.index}"

    @property
    def mgmt_ip(self) -> str:
        return f"10.{self.base}.0.{10 + self.index}"

    @property
    def node_ip(self) -> str:
        return f"10.{self.base + 1}.0.{10 + self.index}"

    @property
    def pod_cidr(self) -> str:
        return f"10.{self.base + 2}.{self.index}.0/24"

    @property
    def cgroup(self) -> str:
        return f"{self.tag}-{self.name}"

    @property
    def cni_network(self) -> str:
        return f"kuberos-{self.tag}-{self.name}"


def containerd_config(directory: str, socket: str, cni_bin_dir: str | None, cni_conf_dir: str) -> str:
    """containerd's config.toml of a node whose state lives under ``directory``, serving on ``socket``."""
    return "\n".join(
        [
            "version = 2",
            f'root = "{directory}/root"',
            f'state = "{directory}/state"',
            "[grpc]",
            f'  address = "{socket}"',
            "[ttrpc]",
            f'  address = "{socket}.ttrpc"',
            '[plugins."io.containerd.internal.v1.opt"]',
            f'  path = "{directory}/opt"',
            '[plugins."io.containerd.grpc.v1.cri"]',
            '  sandbox_image = "kuberos.local/pause:3.10"',
            "  restrict_oom_score_adj = true  # root here lacks CAP_SYS_RESOURCE",
            "  enable_selinux = false",
            '  stream_server_address = "127.0.0.1"',
            "  netns_mounts_under_state_dir = true  # pod network namespaces under the node's state, not /run/netns",
            '[plugins."io.containerd.grpc.v1.cri".registry]',
            f'  config_path = "{directory}/certs.d"  # hosts.toml per registry: the lab registry\'s CA',
            '[plugins."io.containerd.grpc.v1.cri".cni]',
            f'  bin_dir = "{cni_bin_dir}"',
            f'  conf_dir = "{cni_conf_dir}"',
            '[plugins."io.containerd.grpc.v1.cri".containerd]',
            '  snapshotter = "overlayfs"',
            '[plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc]',
            '  runtime_type = "io.containerd.runc.v2"',
            '[plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc.options]',
            "  SystemdCgroup = false",
            "",
        ]
    )


def cni_config(net: NodeNet, ipam_dir: str) -> str:
    """The node's CNI network: a bridge with the node's pod range, addresses kept in ``ipam_dir``."""
    return json.dumps(
        {
            "cniVersion": "0.4.0",
            "name": net.cni_network,
            "plugins": [
                {
                    "type": "bridge",
                    "bridge": "cni0",
                    "isGateway": True,
                    "ipMasq": False,  # pods keep their addresses across nodes; the root namespace routes back
                    "hairpinMode": True,
                    "ipam": {
                        "type": "host-local",
                        "ranges": [[{"subnet": net.pod_cidr}]],
                        "routes": [{"dst": "0.0.0.0/0"}],
                        "dataDir": ipam_dir,
                    },
                },
                {"type": "portmap", "capabilities": {"portMappings": True}},
            ],
        },
        indent=1,
    )


def kubelet_config(net: NodeNet, node: dict, *, ca_file: str, dns: str, resolv_conf: str, socket: str, pod_logs: str) -> dict:
    """The node's KubeletConfiguration (``node``: its taints as the cluster's node plan gives them)."""
    return {
        "apiVersion": "kubelet.config.k8s.io/v1beta1",
        "kind": "KubeletConfiguration",
        "authentication": {
            "anonymous": {"enabled": False},
            "webhook": {"enabled": True},
            "x509": {"clientCAFile": ca_file},
        },
        "authorization": {"mode": "Webhook"},
        "address": net.node_ip,
        "healthzBindAddress": "127.0.0.1",
        "readOnlyPort": 0,
        "cgroupDriver": "cgroupfs",
        "cgroupRoot": f"/{net.cgroup}",
        "cgroupsPerQOS": True,
        "failCgroupV1": False,
        "failSwapOn": False,
        "protectKernelDefaults": False,
        "clusterDNS": [dns],
        "clusterDomain": CLUSTER_DOMAIN,
        "resolvConf": resolv_conf,
        "containerRuntimeEndpoint": f"unix://{socket}",
        "podLogsDir": pod_logs,
        "podCIDR": net.pod_cidr,
        "registerNode": True,
        "registerWithTaints": node.get("taints") or [],
        "serializeImagePulls": False,
        "rotateCertificates": False,
        "imageGCHighThresholdPercent": 100,  # the imported images cannot be pulled again
        "imageGCLowThresholdPercent": 99,
        "evictionHard": {"memory.available": "100Mi", "nodefs.available": "1%", "imagefs.available": "1%"},
        "nodeStatusUpdateFrequency": "5s",
        "maxPods": 110,
    }


def kube_proxy_config(net: NodeNet, kubeconfig: str, cluster_cidr: str) -> dict:
    """The node's KubeProxyConfiguration (iptables mode; host-wide conntrack limits left as they are)."""
    return {
        "apiVersion": "kubeproxy.config.k8s.io/v1alpha1",
        "kind": "KubeProxyConfiguration",
        "mode": "iptables",
        "clientConnection": {"kubeconfig": kubeconfig},
        "hostnameOverride": net.name,
        "bindAddress": "0.0.0.0",
        "clusterCIDR": cluster_cidr,
        "healthzBindAddress": "127.0.0.1:10256",
        "metricsBindAddress": "127.0.0.1:10249",
        # conntrack limits are host-wide: left as they are
        "conntrack": {"maxPerCore": 0, "min": 0, "tcpEstablishedTimeout": "0s", "tcpCloseWaitTimeout": "0s"},
        "iptables": {"localhostNodePorts": False, "masqueradeAll": False},
        "nodePortAddresses": ["primary"],
    }


def corefile(host_ip: str, kubeconfig: str) -> str:
    """CoreDNS's Corefile: the cluster's names from the API server, served on the host's management address."""
    return "\n".join(
        [
            ".:53 {",
            f"    bind {host_ip}",
            "    errors",
            f"    health {host_ip}:8080",
            f"    ready {host_ip}:8181",
            f"    kubernetes {CLUSTER_DOMAIN} in-addr.arpa ip6.arpa {{",
            f"        kubeconfig {kubeconfig} kuberos-local",
            "        pods insecure",
            "        fallthrough in-addr.arpa ip6.arpa",
            "    }",
            "    cache 5",
            "}",
            "",
        ]
    )
