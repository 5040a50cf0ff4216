"""Real nodes of the local cluster: a kubelet, containerd and kube-proxy per node, each node a network namespace.

Next to the kwok nodes of ``local_control_plane``, the hosts an inventory marks ``kuberos_local_node: real``
run pods for real: containers from images built from this repository (local_images.py), pod networks routed
between the nodes, Services through kube-proxy (iptables), names through CoreDNS, and the inventory's
round-trip times between the nodes. No Ansible imports; the ``local_cluster`` module and the tests drive it.

The network, for base ``B`` (default 231; one tier per base on a machine)::

    root namespace: bridge <tag>mgmt 10.B.0.1/24 -- API server relay (socat, 10.B.0.1:<apiserver port>),
                    CoreDNS (10.B.0.1:53), the registry (10.B.0.1:<registry port>, TLS and htpasswd; optional),
                    routes to every node's address and pod network via its veth
         |  veth <tag>m<i> / mgmt0 10.B.0.(10+i): control traffic, not delayed
    node namespace <tag>n-<node>: kubelet, containerd, kube-proxy (iptables), CNI bridge cni0 for pods
         |  TUN eth0 10.(B+1).0.(10+i) = the node's InternalIP; the other nodes' pod networks routed to it
    delay fabric (delay_fabric.py, root namespace): node and pod traffic between nodes, delayed per pair
    pods: 10.(B+2).<i>.0/24 per node (host-local IPAM), cluster CIDR 10.(B+2).0.0/16

Every program runs in its node's network namespace only (``nsenter --net``): kubelet, containerd and runc share
the host's mount namespace, so the volumes the kubelet mounts are the ones the containers see. Each kubelet
has a cgroup root of its own (``/<tag>-<node>``, cgroupfs, cgroup v1) and containerd state under the cluster's
state directory. The kubelet changes host sysctls (kernel.panic, kernel.panic_on_oops, vm.overcommit_memory):
their values are saved before the first start and put back when the tier stops.

With a registry port, the lab's registry (`kuberos_lab.registry`, the CNCF distribution registry) runs on the
management bridge; every built image is pushed to it by digest (``kuberos/<name>@sha256:...``) and each node's
containerd trusts its CA (``config_path``: a ``hosts.toml`` per registry), so pods pull from it with a pull
secret as from a site's registry. The images are imported as well, under the names the specs use.

Stopping removes everything the tier made: containers (through containerd), processes, mounts under the
state directory, pod network namespaces, CNI state, cgroups, namespaces, links and routes, and restores the
sysctls. ``snapshot_host()`` records what the tests compare before and after.
"""

from __future__ import annotations

import glob
import inspect
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import real_node_config as config
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.real_node_config import (
    NodeNet,
    host_address,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, api_clients, message
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import background_process as bg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import delay_fabric
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import (
    LocalRegistry,
    RegistryError,
    lab_repository,
)

HOST_SYSCTLS = ("kernel/panic", "kernel/panic_on_oops", "vm/overcommit_memory", "net/ipv4/ip_forward")
CGROUP_ROOT = bg.CGROUP_ROOT
CNI_BIN_DIRS = ("/usr/lib/cni", "/opt/cni/bin")
CNI_PLUGINS = ("bridge", "host-local", "loopback", "portmap")
NODE_COMPONENTS = ("containerd", "kubelet", "kube-proxy")
SHARED_COMPONENTS = ("fabric", "apiserver-relay", "coredns")
DEVICE_PLUGIN_SOCKET = "/var/lib/kubelet/device-plugins/kubelet.sock"  # fixed in the kubelet, whatever --root-dir is
SUN_PATH_MAX = 104  # what containerd accepts for a Unix socket path (sun_path, less its terminating NUL and margin)


class RealNodeError(RuntimeError):
    """A real node could not be set up or torn down."""


def in_netns(netns: str, command: list[str]) -> list[str]:
    """``command`` in a node's network namespace only (the host's mounts stay shared)."""
    return ["nsenter", f"--net=/var/run/netns/{netns}", "--", *command]


def run(*command: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
    return bg.run_checked(command, RealNodeError, check, timeout)


@dataclass
class RealNodes:
    """The real nodes of one local cluster (``plane``: its LocalControlPlane)."""

    plane: object
    nodes: list[dict]  # name, labels, taints (filter real_nodes)
    delay_ms: dict
    binaries: dict  # kubelet, kube-proxy, coredns (paths); containerd, runc, socat from PATH
    images: dict = field(default_factory=dict)  # reference -> OCI archive
    aliases: dict = field(default_factory=dict)  # alias -> reference
    base: int = 231
    tag: str = "kr"
    registry_port: int = 0  # the lab registry on the management bridge (0: none)
    links: dict = field(default_factory=dict)  # link_bps and link_loss of the fabric (node -> value)
    log: list = field(default_factory=list)
    _children: dict = field(default_factory=dict, repr=False)  # (component, node) -> Popen, started by this object
    _served: dict = field(default_factory=dict, repr=False)  # built image -> its pull reference in the lab registry
    _kube: Kube | None = field(default=None, repr=False)  # the access layer as the administrator, made when first used

    def __post_init__(self):
        if not 1 <= len(self.tag) <= 4 or not self.tag.isalnum():
            raise RealNodeError(f"tag {self.tag!r}: expected 1 to 4 letters or digits (interface names are short)")
        if not 2 <= self.base <= 250:
            raise RealNodeError(f"base {self.base}: expected 2 to 250 (addresses 10.<base>..10.<base+2>)")
        self.nets = {
            n["name"]: NodeNet(n["name"], i, self.tag, self.base)
            for i, n in enumerate(sorted(self.nodes, key=lambda n: n["name"]))
        }
        self.registry = LocalRegistry(self.path("registry"), self.host_ip, self.registry_port) if self.registry_port else None

    @classmethod
    def from_state(cls, plane, binaries: dict) -> RealNodes | None:
        """The real nodes a cluster's state directory says were started (to stop them), or None."""
        try:
            with open(plane.path("nodes", "state.json"), encoding="utf-8") as handle:
                state = json.load(handle)
        except (OSError, ValueError):
            return None
        nodes = [{"name": name, "labels": {}, "taints": []} for name in state.get("nodes", [])]
        return cls(
            plane, nodes, {}, binaries, base=state.get("base", 231), tag=state.get("tag", "kr"),
            registry_port=state.get("registry_port", 0),
        )  # fmt: skip

    # -- paths and names ---------------------------------------------------------------------------
    def path(self, *parts: str) -> str:
        return self.plane.path("nodes", *parts)

    @property
    def bridge(self) -> str:
        return f"{self.tag}mgmt"

    @property
    def host_ip(self) -> str:
        return host_address(self.base)

    @property
    def cluster_cidr(self) -> str:
        return f"10.{self.base + 2}.0.0/16"

    def _pidfile(self, component: str, node: str | None = None) -> str:
        return self.plane.path("run", f"{node}-{component}.pid" if node else f"nodes-{component}.pid")

    def _logfile(self, component: str, node: str | None = None) -> str:
        return self.plane.path("logs", f"{node}-{component}.log" if node else f"nodes-{component}.log")

    def _marker(self, component: str, node: str | None = None):
        if node:
            needle = self.path(node)  # every program of a node names a file under its directory
        elif component == "apiserver-relay":
            needle = f"bind={self.host_ip}"
        else:
            needle = self.path({"fabric": "fabric.json", "coredns": "Corefile"}[component])
        return lambda argv: any(needle in part for part in argv)

    def pid(self, component: str, node: str | None = None) -> int | None:
        return bg.running_pid(self._pidfile(component, node), self._marker(component, node))

    def socket(self, node: str) -> str:
        return self.path(node, "containerd", "containerd.sock")

    # -- checks --------------------------------------------------------------------------------------
    def problems(self) -> list[str]:
        """What this machine lacks for real nodes (empty when nothing)."""
        found = []
        if os.geteuid() != 0:
            found.append("real nodes need root (network namespaces, cgroups, mounts)")
        for program in ("containerd", "runc", "ctr", "socat", "nsenter", "ip", "iptables", "conntrack"):
            if not shutil.which(program):
                found.append(f"`{program}` is not installed (scripts/setup.sh installs it)")
        cni = self.cni_bin_dir()
        if cni is None:
            found.append(f"the CNI plugins ({', '.join(CNI_PLUGINS)}) are not installed (package containernetworking-plugins)")
        for component in ("kubelet", "kube-proxy", "coredns"):
            if not os.access(self.binaries.get(component, ""), os.X_OK):
                found.append(f"{component} is not built: {self.binaries.get(component)} (make binaries WITH_NODES=1)")
        if not os.path.exists("/dev/net/tun"):
            found.append("/dev/net/tun is missing (the delay fabric needs TUN devices)")
        if not os.path.isdir(os.path.join(CGROUP_ROOT, "cpu")):
            found.append("cgroup v1 controllers are not mounted under /sys/fs/cgroup (the kubelets use cgroupfs v1)")
        longest = max((self.socket(node) + ".ttrpc" for node in self.nets), key=len, default="")
        if len(longest) > SUN_PATH_MAX:
            found.append(
                f"the state folder is too deep for containerd's sockets: {longest} has {len(longest)} characters, "
                f"a Unix socket path at most {SUN_PATH_MAX} (choose a shorter state folder)"
            )
        if self.registry is not None:
            found += self.registry.problems()
        return found

    @staticmethod
    def cni_bin_dir() -> str | None:
        for directory in CNI_BIN_DIRS:
            if all(os.access(os.path.join(directory, p), os.X_OK) for p in CNI_PLUGINS):
                return directory
        return None

    def running(self) -> dict[str, int | None]:
        status = {c: self.pid(c) for c in SHARED_COMPONENTS}
        if self.registry is not None:
            status["registry"] = self.registry.pid()
        for node in self.nets:
            status.update({f"{node}/{c}": self.pid(c, node) for c in NODE_COMPONENTS})
        return status

    # -- lifecycle -------------------------------------------------------------------------------------
    def start(self, timeout: float = 120.0) -> bool:
        """Make every real node run and be Ready; True when anything changed."""
        problems = self.problems()
        if problems:
            raise RealNodeError("real nodes cannot run here: " + "; ".join(problems))
        state = self._read_state()
        if state and state.get("nodes") != sorted(self.nets) and any(self.running().values()):
            raise RealNodeError(
                f"real nodes {', '.join(state['nodes'])} run with another set of nodes than {', '.join(sorted(self.nets))}; "
                "stop them first (local_cluster_state=stopped)"
            )
        os.makedirs(self.path(), exist_ok=True)
        self._save_sysctls()
        self._write_state()
        changed = self._network()
        self._certificates()
        changed = self._start_shared() or changed
        changed = self._start_registry() or changed
        for net in self.nets.values():
            changed = self._start_runtime(net) or changed
        changed = self._import_images() or changed
        for net in self.nets.values():
            changed = self._start_kubelet(net) or changed
        self._wait_ready(timeout)
        return changed

    def stop(self, remove: bool = False) -> bool:
        """Stop every real node and leave the host as it was; ``remove``: also delete their state (images too)."""
        changed = False
        for net in self.nets.values():
            changed = self._stop_node(net) or changed
        if self.registry is not None:
            pid = self.registry.pid()
            if self.registry.stop():
                self.log.append(f"stopped registry (pid {pid})")
                changed = True
        for component in reversed(SHARED_COMPONENTS):
            changed = self._stop(component) or changed
        if os.path.exists(f"/sys/class/net/{self.bridge}"):
            run("ip", "link", "delete", self.bridge, check=False)
            self.log.append(f"removed bridge {self.bridge}")
            changed = True
        changed = self._restore_sysctls() or changed
        if remove and os.path.exists(self.path()):
            self._unmount_under(self.path())
            shutil.rmtree(self.path(), ignore_errors=True)
            self.log.append(f"removed {self.path()}")
            changed = True
        return changed

    def stop_kubelet(self, node: str) -> bool:
        """Stop one node's kubelet only (its containers keep running, as on a machine whose kubelet died)."""
        return self._stop("kubelet", node)

    PARTITION_UPLINKS = ("mgmt0", "eth0")  # the control link (API server, registry) and the node's link to the others

    def _partition_rules(self) -> list[list[str]]:
        rules = []
        for link in self.PARTITION_UPLINKS:
            for chain, direction in (("INPUT", "-i"), ("OUTPUT", "-o"), ("FORWARD", "-i"), ("FORWARD", "-o")):
                rules.append([chain, direction, link, "-m", "comment", "--comment", "kuberos-partition", "-j", "DROP"])
        return rules

    def partitioned(self, node: str) -> bool:
        """Whether ``partition`` cut the node off (its rules are in place)."""
        ns = self.nets[node].netns
        return all(run(*in_netns(ns, ["iptables", "-C", *rule]), check=False).returncode == 0 for rule in self._partition_rules())

    def partition(self, node: str, cut: bool = True) -> bool:
        """Cut a node off the network (``cut``), or reconnect it: every packet in and out of its control link and
        its link to the other nodes is dropped, as for a robot in a dead zone. What runs on the node goes on, and
        its pods still talk to each other on its own bridge. True when something changed."""
        ns = self.nets[node].netns
        changed = False
        for rule in self._partition_rules():
            present = run(*in_netns(ns, ["iptables", "-C", *rule]), check=False).returncode == 0
            if present != cut:
                run(*in_netns(ns, ["iptables", "-I" if cut else "-D", *rule]))
                changed = True
        if changed:
            self.log.append(f"{'cut' if cut else 'reconnected'} {node}")
        return changed

    def shape(self, node: str, rate_bps: float | None) -> bool:
        """Limit a node's control link (the API server, the lab registry: what image pulls cross) to ``rate_bps`` each
        way with a token bucket (tbf: this kernel has no netem), as a robot's slow wireless link; ``None`` lifts it.
        True when something changed. (The links between nodes take the inventory's bandwidth in the fabric.)"""
        net = self.nets[node]
        ends = ((in_netns(net.netns, ["tc"]), "mgmt0"), (["tc"], net.veth))  # uplink in the node, downlink on the host
        changed = False
        for tc, device in ends:
            shaped = "tbf" in run(*tc, "qdisc", "show", "dev", device, check=False).stdout
            if rate_bps is None and shaped:
                run(*tc, "qdisc", "del", "dev", device, "root")
                changed = True
            elif rate_bps is not None:
                burst = max(16_000, int(rate_bps / 8 / 100))  # 10 ms of traffic, at least a few packets
                run(*tc, "qdisc", "replace", "dev", device, "root", "tbf", "rate", f"{int(rate_bps)}bit",
                    "burst", str(burst), "latency", "400ms")  # fmt: skip
                changed = True
        if changed:
            self.log.append(f"{node}: control link " + (f"limited to {rate_bps:g} bit/s" if rate_bps else "not limited"))
        return changed

    # -- state -------------------------------------------------------------------------------------------
    def _read_state(self) -> dict:
        try:
            with open(self.path("state.json"), encoding="utf-8") as handle:
                return json.load(handle)
        except (OSError, ValueError):
            return {}

    def _write_state(self) -> None:
        state = {"nodes": sorted(self.nets), "base": self.base, "tag": self.tag, "registry_port": self.registry_port}
        _write(self.path("state.json"), json.dumps(state))

    def _save_sysctls(self) -> None:
        saved = self.path("sysctls.json")
        if os.path.exists(saved):
            return  # the values from before the first start, not the kubelet's
        _write(saved, json.dumps({key: _read(f"/proc/sys/{key}").strip() for key in HOST_SYSCTLS}))

    def _restore_sysctls(self) -> bool:
        saved = self.path("sysctls.json")
        if not os.path.exists(saved):
            return False
        with open(saved, encoding="utf-8") as handle:
            values = json.load(handle)
        restored = []
        for key, value in values.items():
            if _read(f"/proc/sys/{key}").strip() != value:
                _write(f"/proc/sys/{key}", value)
                restored.append(f"{key.replace('/', '.')}={value}")
        os.remove(saved)
        if restored:
            self.log.append("restored sysctls " + ", ".join(restored))
        return bool(restored)

    # -- network --------------------------------------------------------------------------------------------
    def _network(self) -> bool:
        changed = False
        if not os.path.exists(f"/sys/class/net/{self.bridge}"):
            run("ip", "link", "add", self.bridge, "type", "bridge")
            run("ip", "addr", "add", f"{self.host_ip}/24", "dev", self.bridge)
            run("ip", "link", "set", self.bridge, "up")
            self.log.append(f"created bridge {self.bridge} ({self.host_ip}/24)")
            changed = True
        # The root namespace routes between the lab's sites (another cluster of real nodes on another base), as the
        # network between two sites does: packets that come in on a management bridge are forwarded. Only these
        # bridges forward (the host's net.ipv4.ip_forward stays as it is); the setting goes with the bridge.
        forwarding = f"/proc/sys/net/ipv4/conf/{self.bridge}/forwarding"
        if _read(forwarding).strip() != "1":
            _write(forwarding, "1")
            changed = True
        for net in self.nets.values():
            if not os.path.exists(f"/var/run/netns/{net.netns}"):
                self._create_netns(net)
                changed = True
            run("ip", "route", "replace", f"{net.node_ip}/32", "via", net.mgmt_ip, "dev", self.bridge)
            run("ip", "route", "replace", net.pod_cidr, "via", net.mgmt_ip, "dev", self.bridge)
        return changed

    def _create_netns(self, net: NodeNet) -> None:
        ns = net.netns
        run("ip", "netns", "add", ns)
        run("ip", "-n", ns, "link", "set", "lo", "up")
        run("ip", "link", "add", net.veth, "type", "veth", "peer", "name", "mgmt0", "netns", ns)
        run("ip", "link", "set", net.veth, "master", self.bridge, "up")
        run("ip", "-n", ns, "addr", "add", f"{net.mgmt_ip}/24", "dev", "mgmt0")
        run("ip", "-n", ns, "link", "set", "mgmt0", "up")
        run("ip", "-n", ns, "route", "add", "default", "via", self.host_ip, "dev", "mgmt0")
        run("ip", "-n", ns, "tuntap", "add", "dev", "eth0", "mode", "tun")
        run("ip", "-n", ns, "addr", "add", f"{net.node_ip}/24", "dev", "eth0")
        run("ip", "-n", ns, "link", "set", "eth0", "txqueuelen", "4096", "up")
        for other in self.nets.values():
            if other.name != net.name:
                run("ip", "-n", ns, "route", "add", other.pod_cidr, "dev", "eth0")
        settings = [
            "net.ipv4.ip_forward=1", "net.ipv4.conf.all.rp_filter=0", "net.ipv4.conf.default.rp_filter=0",
            "net.ipv6.conf.all.disable_ipv6=1", "net.ipv6.conf.default.disable_ipv6=1",
        ]  # fmt: skip
        if os.path.exists("/proc/sys/net/bridge/bridge-nf-call-iptables"):
            settings.append("net.bridge.bridge-nf-call-iptables=1")  # Services between pods of one node's bridge
        run(*in_netns(ns, ["sysctl", "-qw", *settings]))
        self.log.append(f"created network namespace {ns} ({net.node_ip}, pods {net.pod_cidr})")

    # -- certificates and configuration ------------------------------------------------------------------
    def _certificates(self) -> None:
        """Client certificates and kubeconfigs of the kubelets, kube-proxy (through the relay) and CoreDNS."""
        relay = f"https://{self.host_ip}:{self.plane.ports.apiserver}"
        for net in self.nets.values():
            self.plane.ensure_certificate(f"kubelet-{net.name}", f"system:node:{net.name}", "system:nodes", server=relay)
        self.plane.ensure_certificate("kube-proxy", "system:kube-proxy", None, server=relay)
        self.plane.ensure_certificate("coredns", "system:kuberos:coredns", None)

    def _coredns_rbac(self) -> None:
        """What CoreDNS's kubernetes plugin reads (the ClusterRole a cluster's CoreDNS has)."""
        role = {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRole",
            "metadata": {"name": "system:kuberos:coredns", "labels": {"app.kubernetes.io/managed-by": "kuberos"}},
            "rules": [
                {"apiGroups": [""], "resources": ["endpoints", "services", "pods", "namespaces"], "verbs": ["list", "watch"]},
                {"apiGroups": ["discovery.k8s.io"], "resources": ["endpointslices"], "verbs": ["list", "watch"]},
            ],
        }
        binding = {
            "apiVersion": "rbac.authorization.k8s.io/v1",
            "kind": "ClusterRoleBinding",
            "metadata": {"name": "system:kuberos:coredns", "labels": {"app.kubernetes.io/managed-by": "kuberos"}},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": "system:kuberos:coredns"},
            "subjects": [{"apiGroup": "rbac.authorization.k8s.io", "kind": "User", "name": "system:kuberos:coredns"}],
        }
        for obj in (role, binding):
            self._as_admin(lambda kube, obj=obj: kube.apply(obj, manager="kuberos-local-cluster"))

    def _as_admin(self, call):
        """``call(kube)`` through the access layer as the local control plane's administrator; RealNodeError saying
        what went wrong when the API server cannot be used."""
        if self._kube is None:
            self._kube = Kube(api_clients(self.plane.kubeconfig), "kuberos-local-cluster")
        try:
            return call(self._kube)
        except Exception as exc:
            raise RealNodeError(message(exc, self.plane.kubeconfig)) from exc

    def _containerd_config(self, net: NodeNet) -> str:
        directory = self.path(net.name, "containerd")
        return config.containerd_config(directory, self.socket(net.name), self.cni_bin_dir(), self.path(net.name, "cni", "net.d"))

    def _cni_config(self, net: NodeNet) -> str:
        return config.cni_config(net, self.path(net.name, "cni", "ipam"))

    def _kubelet_config(self, net: NodeNet, node: dict) -> dict:
        return config.kubelet_config(
            net,
            node,
            ca_file=self.plane.path("pki", "ca.crt"),
            dns=self.host_ip,
            resolv_conf=self.path(net.name, "resolv.conf"),
            socket=self.socket(net.name),
            pod_logs=self.path(net.name, "pod-logs"),
        )

    def _kube_proxy_config(self, net: NodeNet) -> dict:
        return config.kube_proxy_config(net, self.plane.path("kube-proxy.kubeconfig"), self.cluster_cidr)

    def _corefile(self) -> str:
        return config.corefile(self.host_ip, self.plane.path("coredns.kubeconfig"))

    # -- processes ----------------------------------------------------------------------------------------
    def _start(self, component: str, command: list[str], node: str | None = None, netns: str | None = None) -> bool:
        if self.pid(component, node) is not None:
            return False
        if netns:
            command = in_netns(netns, command)
        process = bg.start(command, self._pidfile(component, node), self._logfile(component, node))
        self._children[(component, node)] = process
        self.log.append(f"started {node + '/' if node else ''}{component} (pid {process.pid})")
        return True

    def _stop(self, component: str, node: str | None = None, timeout: float = 15.0) -> bool:
        started = time.monotonic()
        pid = bg.stop(self._pidfile(component, node), self._marker(component, node), timeout)
        if pid is not None:
            self.log.append(f"stopped {node + '/' if node else ''}{component} (pid {pid}, {time.monotonic() - started:.1f} s)")
        return pid is not None

    def _start_shared(self) -> bool:
        fabric = {
            "hosts": [
                {"node": n.name, "netns": n.netns, "tun": "eth0", "address": n.node_ip, "routes": [n.pod_cidr]}
                for n in self.nets.values()
            ],
            "delay_ms": self.delay_ms,
            **{key: dict(value) for key, value in self.links.items() if value},
            "broadcasts": [f"10.{self.base + 1}.0.255"],
            "stats_file": self.path("fabric-stats.json"),
            "stats_interval": 1.0,
        }
        _write(self.path("fabric.json"), json.dumps(fabric, indent=1))
        # The fabric is a standard-library script; inside an Ansible module its file is in the module's zip
        # payload, so its source is written beside its configuration.
        _write(self.path("delay_fabric.py"), inspect.getsource(delay_fabric))
        changed = self._start("fabric", [sys.executable, self.path("delay_fabric.py"), self.path("fabric.json")])
        if changed:
            self._wait_for(lambda: "fabric ready" in _read(self._logfile("fabric")), 15, "the delay fabric", "fabric")
        port = self.plane.ports.apiserver
        changed = (
            self._start(
                "apiserver-relay",
                ["socat", f"TCP-LISTEN:{port},bind={self.host_ip},reuseaddr,fork", f"TCP:127.0.0.1:{port}"],
            )
            or changed
        )
        self._coredns_rbac()
        _write(self.path("Corefile"), self._corefile())
        changed = self._start("coredns", [self.binaries["coredns"], "-conf", self.path("Corefile")]) or changed
        return changed

    def _start_runtime(self, net: NodeNet) -> bool:
        node = next(n for n in self.nodes if n["name"] == net.name)
        directory = self.path(net.name)
        for sub in ("containerd", "cni/net.d", "cni/ipam", "kubelet", "pod-logs"):
            os.makedirs(os.path.join(directory, sub), exist_ok=True)
        _write(os.path.join(directory, "containerd", "config.toml"), self._containerd_config(net))
        if self.registry is not None:
            _write(os.path.join(directory, "containerd", "certs.d", self.registry.address, "hosts.toml"),
                   self.registry.containerd_hosts())  # fmt: skip
        _write(os.path.join(directory, "cni", "net.d", "10-kuberos.conflist"), self._cni_config(net))
        _write(os.path.join(directory, "resolv.conf"), f"nameserver {self.host_ip}\n")
        _write(os.path.join(directory, "kubelet.json"), json.dumps(self._kubelet_config(net, node), indent=1))
        _write(os.path.join(directory, "kube-proxy.json"), json.dumps(self._kube_proxy_config(net), indent=1))
        self._cgroups(net)
        changed = self._start(
            "containerd", ["containerd", "--config", os.path.join(directory, "containerd", "config.toml")], net.name, net.netns
        )
        self._wait_for(lambda: os.path.exists(self.socket(net.name)), 30, f"containerd of {net.name}", "containerd", net.name)
        return changed

    def _start_registry(self) -> bool:
        """The lab registry on the management bridge, every built image pushed to it by digest; what it serves is
        written to ``<state>/nodes/registry/images.json`` ({built reference: pull reference by digest})."""
        if self.registry is None:
            return False
        try:
            changed = self.registry.start()
            if changed:
                self.log.append(f"started registry on {self.registry.address} ({self.registry.path('registry.log')})")
            served = {}
            client = self.registry.client()
            for reference, archive in sorted(self.images.items()):
                repository, tag = lab_repository(reference)
                started = time.monotonic()
                digest, done = client.push_archive(archive, repository, tag)
                served[reference] = f"{self.registry.address}/{repository}@{digest}"
                if done["uploaded"]:
                    changed = True
                    self.log.append(
                        f"pushed {served[reference]}: {done['uploaded']} blobs, {done['bytes'] / 2**20:.1f} MiB "
                        f"({time.monotonic() - started:.1f} s)"
                    )
        except RegistryError as error:
            raise RealNodeError(str(error)) from None
        _write(self.registry.path("images.json"), json.dumps(served, indent=1, sort_keys=True))
        self._served = served
        return changed

    def registry_info(self) -> dict:
        """The registry as the module returns it after a start: address, user, CA file, and what it serves (as
        ``images.json`` says; no password)."""
        return {
            "address": self.registry.address,
            "username": self.registry.username,
            "ca_file": self.registry.ca_file,
            "images": self._served,
        }

    def _import_images(self) -> bool:
        """The images into every node's containerd, the nodes side by side (each import unpacks every layer)."""
        if not self.images:
            return False
        from concurrent.futures import ThreadPoolExecutor

        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images import import_images

        def one(net: NodeNet) -> tuple[str, list[str], float]:
            started = time.monotonic()
            done = import_images("ctr", self.socket(net.name), self.images, self.aliases, log=lambda _m: None)
            return net.name, done, time.monotonic() - started

        with ThreadPoolExecutor(max_workers=len(self.nets)) as pool:
            results = list(pool.map(one, self.nets.values()))
        for name, done, seconds in results:
            if done:
                imported = sum(1 for line in done if line.startswith("imported"))
                tagged = len(done) - imported
                self.log.append(f"{name}: {imported} images imported, {tagged} names tagged or pinned ({seconds:.1f} s)")
        return any(done for _name, done, _seconds in results)

    def _start_kubelet(self, net: NodeNet) -> bool:
        node = next(n for n in self.nodes if n["name"] == net.name)
        directory = self.path(net.name)
        changed = False
        labels = ",".join(f"{k}={v}" for k, v in sorted(node.get("labels", {}).items()) if not k.startswith("kubernetes.io/"))
        kubelet = [
            self.binaries["kubelet"],
            f"--config={os.path.join(directory, 'kubelet.json')}",
            f"--kubeconfig={self.plane.path(f'kubelet-{net.name}.kubeconfig')}",
            f"--hostname-override={net.name}",
            f"--node-ip={net.node_ip}",
            f"--root-dir={os.path.join(directory, 'kubelet')}",
            f"--cert-dir={os.path.join(directory, 'kubelet', 'pki')}",
            f"--node-labels={labels}",
            "--v=1",
        ]
        since = time.time()
        if self._start("kubelet", kubelet, net.name, net.netns):
            changed = True
            self._wait_for_device_plugin_socket(net, since)
        proxy = [self.binaries["kube-proxy"], f"--config={os.path.join(directory, 'kube-proxy.json')}", "--v=1"]
        return self._start("kube-proxy", proxy, net.name, net.netns) or changed

    def _wait_for_device_plugin_socket(self, net: NodeNet, since: float, timeout: float = 10.0) -> None:
        """Until this kubelet has bound its device-plugin socket (or exited, or ``timeout``). The path is fixed in the
        kubelet, not under ``--root-dir``, so every kubelet of this host binds the same one, removing the file first:
        started together, one removed another's file between that one's remove and bind, and the other failed with
        "address already in use". Started one after another, each binds in turn (no device plugins are used here)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self._exited("kubelet", net.name):
            try:
                if os.stat(DEVICE_PLUGIN_SOCKET).st_mtime >= since:
                    return
            except OSError:
                pass
            time.sleep(0.05)

    def _cgroups(self, net: NodeNet) -> None:
        """The kubelet's cgroup root in every v1 hierarchy (cpuset needs the parent's cpus and mems)."""
        for hierarchy in bg.cgroup_hierarchies():
            path = os.path.join(hierarchy, net.cgroup)
            os.makedirs(path, exist_ok=True)
            if os.path.basename(hierarchy) == "cpuset":
                for key in ("cpuset.cpus", "cpuset.mems"):
                    if not _read(os.path.join(path, key)).strip():
                        _write(os.path.join(path, key), _read(os.path.join(hierarchy, key)).strip())

    def _exited(self, component: str, node: str | None = None) -> bool:
        """Whether a program has exited: a child of ours by its exit status (its command line is briefly empty or
        nsenter's while it execs), another one by its pid file and command line."""
        child = self._children.get((component, node))
        if child is not None:
            return child.poll() is not None
        return self.pid(component, node) is None

    def _wait_for(self, check, timeout: float, what: str, component: str, node: str | None = None) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if check():
                return
            if self._exited(component, node):
                break
            time.sleep(0.1)
        raise RealNodeError(
            f"{what} did not start; see {self._logfile(component, node)}:\n{bg.tail(self._logfile(component, node))}"
        )

    def _wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        waiting = set(self.nets)
        while waiting and time.monotonic() < deadline:
            for name in sorted(waiting):
                node = self._as_admin(lambda kube, name=name: kube.get("Node", name)) or {}
                conditions = {c["type"]: c["status"] for c in node.get("status", {}).get("conditions", [])}
                if conditions.get("Ready") == "True":
                    waiting.discard(name)
                elif self._exited("kubelet", name):
                    log = self._logfile("kubelet", name)
                    raise RealNodeError(f"the kubelet of {name} exited; see {log}:\n{bg.tail(log)}")
            time.sleep(0.5)
        if waiting:
            name = sorted(waiting)[0]
            raise RealNodeError(
                f"nodes {', '.join(sorted(waiting))} not Ready after {timeout:.0f} s; see {self._logfile('kubelet', name)}:\n"
                + bg.tail(self._logfile("kubelet", name))
            )

    # -- teardown --------------------------------------------------------------------------------------------
    def _stop_node(self, net: NodeNet) -> bool:
        started = time.monotonic()
        changed = self._stop("kubelet", net.name)
        changed = self._stop("kube-proxy", net.name) or changed
        containers = self._remove_containers(net) if self.pid("containerd", net.name) is not None else []
        changed = self._stop("containerd", net.name) or changed
        # whatever is left: container processes in the node's cgroups, shims of its containerd
        changed = self._kill_leftovers(net) or changed
        changed = self._unmount_under(self.path(net.name)) or changed
        for cache in glob.glob("/var/lib/cni/**/*", recursive=True):  # libcni's results of the node's containers
            name = os.path.basename(cache)
            if os.path.isfile(cache) and (name.startswith(f"{net.cni_network}-") or any(f"-{c}-" in name for c in containers)):
                os.remove(cache)
        _remove_empty_dirs("/var/lib/cni")
        shutil.rmtree(self.path(net.name, "cni", "ipam"), ignore_errors=True)
        changed = self._remove_cgroups(net) or changed
        if os.path.exists(f"/var/run/netns/{net.netns}"):
            run("ip", "netns", "delete", net.netns, check=False)
            self.log.append(f"removed network namespace {net.netns} ({time.monotonic() - started:.1f} s for the node)")
            changed = True
        # The kernel destroys a deleted namespace's devices in the background, and the host end of the node's link
        # with them: remove it here if it is still there, so that nothing of the node is left when this returns.
        if os.path.exists(f"/sys/class/net/{net.veth}"):
            run("ip", "link", "delete", net.veth, check=False)
            changed = True
        return changed

    def _remove_containers(self, net: NodeNet) -> list[str]:
        """Kill and delete every container through containerd; returns their ids (for the CNI cache)."""
        ctr = ["ctr", "-a", self.socket(net.name), "-n", "k8s.io"]
        tasks = run(*ctr, "tasks", "ls", "-q", check=False).stdout.split()
        if tasks:
            run(*ctr, "tasks", "delete", "--force", *tasks, check=False)  # kills what runs, then deletes
        containers = run(*ctr, "containers", "ls", "-q", check=False).stdout.split()
        if containers:
            run(*ctr, "containers", "delete", *containers, check=False)
        if tasks:
            self.log.append(f"{net.name}: removed {len(tasks)} containers")
        return containers

    def _cgroup_pids(self, net: NodeNet) -> set[int]:
        pids = set()
        for hierarchy in bg.cgroup_hierarchies():
            for procs in glob.glob(os.path.join(hierarchy, net.cgroup, "**", "cgroup.procs"), recursive=True):
                pids.update(int(p) for p in _read(procs).split())
        return pids

    def _kill_leftovers(self, net: NodeNet) -> bool:
        killed = False
        socket = self.socket(net.name)
        for _attempt in range(50):
            pids = self._cgroup_pids(net)
            pids |= {
                pid for pid in _all_pids() if "containerd-shim" in " ".join(bg.cmdline(pid)[:1]) and socket in bg.cmdline(pid)
            }
            if not pids:
                break
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                    killed = True
                except ProcessLookupError:
                    pass
            time.sleep(0.1)
        if killed:
            self.log.append(f"{net.name}: killed processes left behind")
        return killed

    def _unmount_under(self, directory: str) -> bool:
        prefix = os.path.realpath(directory).rstrip("/") + "/"
        mounts = [m for m in _mount_points() if (m + "/").startswith(prefix)]
        for mount in sorted(mounts, key=len, reverse=True):
            run("umount", "-l", mount, check=False)
        return bool(mounts)

    def _remove_cgroups(self, net: NodeNet) -> bool:
        removed = False
        for hierarchy in bg.cgroup_hierarchies():
            top = os.path.join(hierarchy, net.cgroup)
            if not os.path.isdir(top):
                continue
            for directory in sorted((d for d, _subdirs, _files in os.walk(top)), key=len, reverse=True):
                try:
                    os.rmdir(directory)
                    removed = True
                except OSError:
                    pass
        return removed


# -- host inspection -------------------------------------------------------------------------------------------
def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as handle:
            return handle.read()
    except OSError:
        return ""


def _write(path: str, text: str) -> None:
    """Write a file unless it already holds ``text``: kube-proxy exits when its configuration file is written."""
    if _read(path) == text:
        return
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(text)


def _remove_empty_dirs(top: str) -> None:
    """Remove ``top`` and the folders under it that are empty (what libcni made for the nodes' pods)."""
    for directory in sorted((d for d, _subdirs, _files in os.walk(top)), key=len, reverse=True):
        try:
            os.rmdir(directory)
        except OSError:
            pass


def _is_shim_of(pid: int, socket: str) -> bool:
    argv = bg.cmdline(pid)
    return bool(argv) and "containerd-shim" in argv[0] and socket in argv


def _all_pids() -> list[int]:
    return [int(p) for p in os.listdir("/proc") if p.isdigit()]


def _mount_points() -> list[str]:
    points = []
    for line in _read("/proc/self/mountinfo").splitlines():
        parts = line.split()
        if len(parts) > 4:
            points.append(parts[4].replace("\\040", " "))
    return points


def snapshot_changes(before: dict, after: dict) -> dict:
    """What differs between two ``snapshot_host()`` records, per part: the entries gone and the new ones (a setting
    as ``name=value``), so that a failure names the leftover instead of two long lists."""
    changes = {}
    for key in before:
        old, new = before[key], after.get(key)
        if old == new:
            continue
        if isinstance(old, dict):
            old, new = (sorted(f"{k}={v}" for k, v in side.items()) for side in (old, new or {}))
        gone, added = sorted(set(old) - set(new or [])), sorted(set(new or []) - set(old))
        changes[key] = {"gone": gone, "new": added} if gone or added else {"order or count": (old, new)}
    return changes


def snapshot_host() -> dict:
    """What the real nodes may change on the host, to compare before and after: network namespaces, links,
    mounts, cgroups, root namespace routes and iptables rules, sysctls, CNI state, processes of the tier."""
    cgroups = sorted(
        os.path.join(os.path.basename(h), d)
        for h in bg.cgroup_hierarchies()
        for d in os.listdir(h)
        if os.path.isdir(os.path.join(h, d))
    )
    processes = sorted(
        " ".join(bg.cmdline(pid)[:1])
        for pid in _all_pids()
        if any(word in " ".join(bg.cmdline(pid)[:1]) for word in ("containerd", "kubelet", "kube-proxy", "coredns", "pause"))
    )
    return {
        "netns": sorted(os.listdir("/var/run/netns")) if os.path.isdir("/var/run/netns") else [],
        "links": sorted(os.listdir("/sys/class/net")),
        "mounts": sorted(_mount_points()),
        "cgroups": cgroups,
        "routes": run("ip", "route", "show", check=False).stdout.splitlines(),
        "iptables": [line for line in run("iptables-save", check=False).stdout.splitlines() if not line.startswith(("#", ":"))],
        "sysctls": {key: _read(f"/proc/sys/{key}").strip() for key in HOST_SYSCTLS},
        "cni": sorted(glob.glob("/var/lib/cni/**", recursive=True)),
        "processes": processes,
    }
