"""The sample site on lab machines: ``inventories/sample`` with its addresses filled in, as separate hosts.

What the site chain (``tests/site``) and its benchmark (``bench/bench_site.py``) start from. Every host of the sample
inventory that this machine can be is booted as a lab machine (`kuberos_lab.machines`: Debian under systemd-nspawn,
its own network stack, systemd, containerd and cgroup subtree, reached over SSH as a non-root user with sudo):

- ``edge-a``, ``edge-b``, ``edge-c``: the three control planes (stacked etcd) sharing the API server's virtual IP
  (``<subnet>.10``, keepalived); ``edge-a`` is also the VPN's hub, with a second, public address on the lab's
  stand-in for the internet;
- ``edge-d``: an edge worker;
- ``fetch-01`` and ``fetch-02``: the picking fleet's robots;
- ``gpu-vm-1``: a cloud VM on the lab's internet only. It reaches the site through the WireGuard tunnel to the hub
  (wireguard-go: this kernel has no WireGuard module) and joins with its tunnel address as node IP.

Left out, each for a reason of this machine: ``scanner-01`` (an arm64 computer; this machine runs amd64 only) and
``gpu-vm-2`` (one cloud VM shows the path through the tunnel; a second costs the two cores' time only).
``fetch-03`` is the robot the chain boots and registers later (``register_robot.yml``, the join switched on).

The inventory the playbooks get is the sample's own, group variables unchanged, with what a site fills in per host
(``ansible_host``, ``kuberos_address``, the hub's public endpoint) and what the lab's machines really have (2 cores
shared by all, no GPU: ``kuberos_cpu`` is what is left for modules after the control plane and the add-ons, so the
placement and the kubelets agree). The lab's choices for the roles are in ``group_vars/all/10-lab.yml``: the
machines' (`machines.site_vars`), the endpoint as the virtual IP's address (the sample's DNS name exists on no
resolver here), the site network behind the hub, and the site's registry mirror: the lab registry on this machine
(`kuberos_lab.registry`, TLS, pulls without credentials as from a site's internal mirror) serving the images the
specs name (``ghcr.io/kuberos/...``, ``ros:jazzy-ros-base``) for ``ghcr.io`` and ``docker.io``.

``KUBEROS_SITE_KUBERNETES_VERSION`` (unset or empty: the pinned release, ``local_cluster_kubernetes_version``) builds
the site at an older Kubernetes release, to test an upgrade to the pinned one on it: its programs built first with
``KUBERNETES_VERSION=<release> SKIP_KUBECTL=1 SKIP_KUBEADM=0 SKIP_NODES=0 roles/local_cluster/files/build-binaries.sh``.
The site's ``kuberos_kubernetes_version``, kubelet and kubeadm are that release's; the mirror serves kubeadm's images
of both releases (the older one's and the pinned one's, with pause 3.10 and 3.10.1), and the inventory's
``kuberos_lab_upgrade_binaries`` names the pinned release's kubelet and kubeadm (`machines.site_vars`). A 1.33 release
to use here: v1.33.13 (the Go module proxy here does not serve seven of v1.33.7's staging modules at v0.33.7).

    python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_lab up --state DIR
    ansible-playbook playbooks/site.yml -i DIR/inventory
    python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_lab down --state DIR
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import is_ready
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KINDS, Kube, api_clients, status_of
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import machines as lab_machines

TAG = "ks"
SUBNET = "10.215.0"
VIP = f"{SUBNET}.10"
SAMPLE = os.path.join("inventories", "sample")
# sample inventory host -> (machine name, networks, cores left for modules)
MACHINES = {
    "edge-a.site.example.internal": ("edge-a", "site+wan", "1"),
    "edge-b.site.example.internal": ("edge-b", "site", "1"),
    "edge-c.site.example.internal": ("edge-c", "site", "1"),
    "edge-d.site.example.internal": ("edge-d", "site", "1500m"),
    "fetch-01.robots.example.internal": ("fetch-01", "site", "1500m"),
    "fetch-02.robots.example.internal": ("fetch-02", "site", "1500m"),
    "gpu-vm-1": ("gpu-vm-1", "wan", "2"),  # the example's motion planner asks for 2 cores: all of a machine
}
LEFT_OUT = {
    "scanner-01.robots.example.internal": "an arm64 onboard computer; this machine runs amd64 only",
    "gpu-vm-2": "one cloud VM shows the path through the tunnel",
}
CONTROL_PLANES = ("edge-a", "edge-b", "edge-c")  # machine and node names
CLOUD_VM = "gpu-vm-1"  # joins with its address inside the WireGuard tunnel as node IP (SiteLab.vpn_address)
UNUSED_ADDRESS = f"{SUBNET}.99"  # no lab machine has it: a robot there never answers
NEW_ROBOT = "fetch-03"  # its inventory name, machine and node name: register_robot.yml adds it to the inventory
KUBERNETES_VERSION_ENV = "KUBEROS_SITE_KUBERNETES_VERSION"  # an older release to build the site at (module docstring)
RECAP = re.compile(r"^(\S+)\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=(\d+)\s+failed=(\d+)", re.MULTILINE)


class SiteLabError(RuntimeError):
    """The lab site could not be made; the message says what and why."""


PLAYBOOK_TIMEOUT = 900  # site.yml from bare machines takes 5 to 8 minutes here; upgrade.yml passes its own


def run_bounded(command: list[str], timeout: float, **options) -> subprocess.CompletedProcess:
    """Run ``command`` in a session of its own, its output captured; past ``timeout`` seconds the whole session is
    killed (ansible-playbook's forked workers too: they hold the output's pipes, and one waiting on a dead connection
    would keep ``subprocess.run``'s own timeout waiting forever) and the result says so, with return code 124."""
    process = subprocess.Popen(
        command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, **options,
    )  # fmt: skip
    try:
        stdout, stderr = process.communicate(timeout=timeout)
        return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        try:
            stdout, stderr = process.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # a process that left the session still holds a pipe
            process.kill()
            stdout, stderr = "", ""
        said = f"\n{os.path.basename(command[0])}: stopped after {timeout:.0f} s (its limit), with every process it started\n"
        return subprocess.CompletedProcess(command, 124, (stdout or "") + said, (stderr or "") + said)


def recap(stdout: str) -> dict[str, dict[str, int]]:
    """The PLAY RECAP of an ansible-playbook run: host -> ok, changed, unreachable, failed."""
    return {
        host: dict(zip(("ok", "changed", "unreachable", "failed"), map(int, counts), strict=True))
        for host, *counts in RECAP.findall(stdout)
    }


def _prune(group: dict, keep: set[str]) -> None:
    """Drop the hosts not kept from an inventory group and its children, in place."""
    hosts = group.get("hosts") or {}
    for host in list(hosts):
        if host not in keep:
            del hosts[host]
    for child in (group.get("children") or {}).values():
        if isinstance(child, dict):
            _prune(child, keep)


def _host_entries(group: dict):
    """Every (host, its variables dict) of a group and its children (a host may appear in several groups)."""
    yield from (group.get("hosts") or {}).items()
    for child in (group.get("children") or {}).values():
        if isinstance(child, dict):
            yield from _host_entries(child)


def site_kubernetes_version() -> str | None:
    """The Kubernetes release the site is built at: KUBEROS_SITE_KUBERNETES_VERSION, None (the pinned one) unset."""
    return os.environ.get(KUBERNETES_VERSION_ENV, "").strip() or None


class SiteLab:
    """The sample site as lab machines, its inventory, and the registry mirror."""

    def __init__(self, state: str, repo_root: str, cache_dir: str = "~/.cache/kuberos", log=print):
        self.state = os.path.abspath(state)
        self.root = os.path.abspath(repo_root)
        self.cache_dir = os.path.abspath(os.path.expanduser(cache_dir))
        self.log = log
        self.machines = self._machine_lab()

    # -- names ---------------------------------------------------------------------------------------------------
    def path(self, *parts: str) -> str:
        return os.path.join(self.state, *parts)

    @property
    def inventory(self) -> str:
        return self.path("inventory")

    @property
    def kubeconfig(self) -> str:
        return self.path("admin.conf")

    def _machine_lab(self) -> lab_machines.MachineLab:
        if os.path.exists(self.path("lab", "lab.json")):
            return lab_machines.MachineLab.load(self.path("lab"))
        return lab_machines.MachineLab(self.path("lab"), tag=TAG, subnet=SUBNET, cache_dir=self.cache_dir)

    def _registry(self):
        return self.machines.registry()

    def _sample(self) -> dict:
        import yaml

        with open(os.path.join(self.root, SAMPLE, "hosts.yml"), encoding="utf-8") as handle:
            return yaml.safe_load(handle)

    def vpn_address(self, machine: str) -> str:
        """A machine's address inside the WireGuard VPN, as the sample inventory gives it (empty: none)."""
        host = next(h for h, (name, _networks, _cpu) in MACHINES.items() if name == machine)
        found = [v.get("kuberos_vpn_address") for h, v in _host_entries(self._sample()["all"]) if h == host and v]
        return next((address for address in found if address), "")

    # -- lifecycle -----------------------------------------------------------------------------------------------
    def up(self) -> dict:
        """Boot the machines, start the registry mirror and push the images, write the inventory. Returns the lab's
        site variables."""
        sample = self._sample()
        groups = _groups_of(sample["all"])
        specs = [(name, groups.get(host, []), networks) for host, (name, networks, _cpu) in MACHINES.items()]
        hub = next(h for h in MACHINES if "vpn_gateway" in groups.get(h, []))
        vpn_network = self._sample_var("wireguard_network")
        self.machines.routes[vpn_network] = MACHINES[hub][0]  # this machine is the site's router
        self.machines.up(specs, log=self.log)
        site_vars = lab_machines.site_vars(self.cache_dir, log=self.log, kubernetes_version=site_kubernetes_version())
        # The site pulls what each node runs from its mirror, instead of every archive copied to every machine (with
        # an older release: both releases' images, those of the upgrade too).
        archives = site_vars.pop("node_prereqs_image_archives")
        self.write_inventory(site_vars, self._mirror(archives))
        return site_vars

    def add_new_robot(self) -> str:
        """Boot the robot that register_robot.yml adds; returns its address."""
        self.machines.up([(NEW_ROBOT, ["robots"], "site")], log=self.log)
        return self.machines.machines[NEW_ROBOT].address

    def down(self, remove: bool = False) -> None:
        self.machines.down(remove=remove)  # the registry too
        if remove:
            shutil.rmtree(self.state, ignore_errors=True)

    # -- the registry mirror -------------------------------------------------------------------------------------
    def _mirror(self, archives: list[str]) -> dict:
        return serve_images(self._registry(), archives, self.root, self.cache_dir, app_images=True, log=self.log)

    # -- inventory -----------------------------------------------------------------------------------------------
    def _sample_var(self, name: str):
        import yaml

        with open(os.path.join(self.root, SAMPLE, "group_vars", "all.yml"), encoding="utf-8") as handle:
            return yaml.safe_load(handle)[name]

    def write_inventory(self, site_vars: dict, mirrors: dict) -> str:
        """The sample inventory with its addresses filled in (hosts.yml) and the lab's choices (group_vars/all)."""
        import yaml

        sample = self._sample()
        keep = set(MACHINES)
        _prune(sample["all"], keep)
        connection = self.machines.connection_vars()
        cores = {host: cpu for host, (_name, _networks, cpu) in MACHINES.items()}
        names = {host: name for host, (name, _networks, _cpu) in MACHINES.items()}
        for host, variables in _host_entries(sample["all"]):
            if variables is None or host not in keep:
                continue
            machine = self.machines.machines[names[host]]
            variables.update(connection)
            variables["ansible_host"] = machine.address
            if "site" in machine.networks:
                variables["kuberos_address"] = machine.address
            variables.update(kuberos_cpu=cores[host], kuberos_memory="8Gi", kuberos_gpu=0)
            if machine.wan_address and "wireguard_hub_endpoint" in variables:
                variables["wireguard_hub_endpoint"] = f"{machine.wan_address}:51820"  # its public address
        os.makedirs(self.inventory, exist_ok=True)
        shutil.rmtree(self.path("inventory", "group_vars"), ignore_errors=True)
        shutil.copytree(os.path.join(self.root, SAMPLE, "group_vars"), self.path("inventory", "group_vars"))
        all_dir = self.path("inventory", "group_vars", "all")
        os.makedirs(all_dir)
        os.rename(self.path("inventory", "group_vars", "all.yml"), os.path.join(all_dir, "00-sample.yml"))
        lab = {
            **site_vars,
            "kuberos_control_plane_vip": VIP,
            "kuberos_control_plane_endpoint": f"{VIP}:6443",  # no resolver here knows the sample's DNS name
            "wireguard_hub_routed_networks": [f"{SUBNET}.0/24"],  # the site network behind the hub
            "node_prereqs_registry_mirrors": mirrors,
            "cilium_agent_cpu_request": "0",  # every core of the lab's machines is the modules'
            "kuberos_kubeconfig": self.kubeconfig,
            "cilium_render_dir": self.path("rendered", "cilium"),
        }
        # How this machine reaches a robot that register_robot.yml adds later (its host_vars name its address and
        # user only): the robots' group has the lab's key and known hosts too, as a site's group_vars would (added
        # to the sample's robots.yml: a folder group_vars/robots would hide that file).
        robots_vars = self.path("inventory", "group_vars", "robots.yml")
        with open(robots_vars, encoding="utf-8") as handle:
            robots = {**(yaml.safe_load(handle) or {}), **connection}
        with open(robots_vars, "w", encoding="utf-8") as handle:
            handle.write("# inventories/sample's robots.yml and how the lab reaches every robot (kuberos_lab.site_lab).\n")
            yaml.safe_dump(robots, handle, sort_keys=False)
        with open(os.path.join(all_dir, "10-lab.yml"), "w", encoding="utf-8") as handle:
            handle.write("# The lab's choices (kuberos_lab.site_lab): each a documented variable a site may set too.\n")
            yaml.safe_dump(lab, handle, sort_keys=False)
        with open(self.path("inventory", "hosts.yml"), "w", encoding="utf-8") as handle:
            handle.write("# inventories/sample with the lab's addresses and hardware filled in (kuberos_lab.site_lab).\n")
            yaml.safe_dump(sample, handle, sort_keys=False)
        return self.inventory

    # -- playbooks -----------------------------------------------------------------------------------------------
    def playbook(self, name: str, *extra: str, timeout: float = PLAYBOOK_TIMEOUT) -> subprocess.CompletedProcess:
        """Run playbooks/<name> against the lab's inventory; ``result.recap`` has the per-host counts. A run past
        ``timeout`` is stopped whole (`run_bounded`) and comes back failed, saying so."""
        env = {
            **os.environ,
            "ANSIBLE_CONFIG": os.path.join(self.root, "ansible.cfg"),
            "ANSIBLE_NOCOLOR": "1",
            "ANSIBLE_FORCE_COLOR": "0",
        }
        binary = os.path.join(os.path.dirname(sys.executable), "ansible-playbook")
        command = [binary, os.path.join("playbooks", name), "-i", self.inventory, *extra]
        result = run_bounded(command, timeout, cwd=self.root, env=env)
        result.recap = recap(result.stdout)
        with open(self.path(f"{name.replace('/', '_')}-{int(time.time())}.log"), "w", encoding="utf-8") as handle:
            handle.write(result.stdout + "\n--- stderr ---\n" + result.stderr)
        return result


CHECK_NAMESPACE = "kuberos-site-check"
BIG_FILE_KIB = 256  # larger than any window: the TCP stream fills packets to the path's MTU


def kube(kubeconfig: str) -> Kube:
    """The access layer (`kuberos_kube.api`) to the site's cluster."""
    return Kube(api_clients(kubeconfig))


def _new(kind: str, metadata: dict, **fields) -> dict:
    """An object of ``kind`` to create: its apiVersion and kind, ``metadata`` and the other top-level ``fields``."""
    return {"apiVersion": KINDS[kind].api_version, "kind": kind, "metadata": metadata, **fields}


def bootstrap_tokens(kube: Kube) -> list[dict]:
    """The cluster's bootstrap tokens (Secrets of type bootstrap.kubernetes.io/token): each one's description, whether
    it authenticates (a join token; kubeadm's proxy for the kubeadm-certs Secret's lifetime does not), and its
    lifetime (from its creation to its expiration, in seconds)."""
    import base64
    import datetime

    def moment(text: str) -> datetime.datetime:
        return datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))

    found = []
    for secret in kube.list("Secret", "kube-system"):
        if secret.get("type") != "bootstrap.kubernetes.io/token":
            continue
        data = {key: base64.b64decode(value).decode() for key, value in (secret.get("data") or {}).items()}
        expires = data.get("expiration")
        created = secret["metadata"]["creationTimestamp"]
        found.append({
            "name": secret["metadata"]["name"],
            "description": data.get("description", ""),
            "authenticates": data.get("usage-bootstrap-authentication") == "true",
            "lifetime_s": (moment(expires) - moment(created)).total_seconds() if expires else None,
        })  # fmt: skip
    return found


def wait_for(what: str, check, timeout: float, interval: float = 2.0):
    """Call ``check`` until it returns something true; raise with ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = check()
        except Exception as error:  # an API server between leaders answers with errors: ask again
            last = error
        else:
            if last:
                return last
        time.sleep(interval)
    raise SiteLabError(f"{what}: not within {timeout:.0f} s (last: {last!r})")


def nodes(kube: Kube) -> dict[str, dict]:
    """node -> Ready, its InternalIP, labels and taints."""
    found = {}
    for node in kube.list("Node"):
        status, meta = node.get("status") or {}, node["metadata"]
        internal = [a.get("address") for a in status.get("addresses") or [] if a.get("type") == "InternalIP"]
        taints = (node.get("spec") or {}).get("taints") or []
        found[meta["name"]] = {
            "ready": is_ready(node),
            "internal_ip": internal[0] if internal else "",
            "labels": dict(meta.get("labels") or {}),
            "taints": [f"{t.get('key')}={t.get('value') or ''}:{t.get('effect')}" for t in taints],
        }
    return found


def pod_network_check(kube: Kube, toolbox: str, servers: dict[str, str], clients: list[tuple[str, str, str, bool]]) -> dict:
    """Web servers (name -> node) that admit only pods labelled access=granted (a NetworkPolicy), and clients
    (name, node, server, admitted) that each fetch a file of BIG_FILE_KIB KiB from a server's pod IP. Returns
    client -> {"phase", "bytes"} (the reply's, headers included): an admitted client reads the whole file through
    the pod network (the CNI's VXLAN, and the VPN for a cloud node, at the MTU the role set); a refused one reads
    nothing."""
    try:
        kube.delete("Namespace", CHECK_NAMESPACE)
    except Exception as error:  # the API server's refusal (gone, or already terminating) is no matter
        if status_of(error) is None:
            raise
    wait_for("the check's old namespace is gone", lambda: CHECK_NAMESPACE not in _namespaces(kube), 120)
    kube.create(_new("Namespace", {"name": CHECK_NAMESPACE}))
    kube.create(
        _new(
            "NetworkPolicy",
            {"name": "servers-admit-granted", "namespace": CHECK_NAMESPACE},
            spec={
                "podSelector": {"matchLabels": {"app": "server"}},
                "policyTypes": ["Ingress"],
                "ingress": [{"from": [{"podSelector": {"matchLabels": {"access": "granted"}}}], "ports": [{"port": 8080}]}],
            },
        )
    )
    toleration = [{"key": "kuberos.io/robot", "operator": "Exists", "effect": "NoSchedule"}]
    serve = (
        f"mkdir -p /www && busybox dd if=/dev/zero of=/www/big bs=1024 count={BIG_FILE_KIB} 2>/dev/null "
        "&& exec busybox httpd -f -p 8080 -h /www"
    )
    for name, node in servers.items():
        kube.create(
            _new(
                "Pod",
                {"name": name, "namespace": CHECK_NAMESPACE, "labels": {"app": "server"}},
                spec={
                    "nodeName": node,
                    "tolerations": toleration,
                    "containers": [
                        {
                            "name": "httpd",
                            "image": toolbox,
                            "command": ["/bin/sh", "-c", serve],
                            "readinessProbe": {"tcpSocket": {"port": 8080}, "periodSeconds": 1},
                        }
                    ],
                },
            )
        )

    def server_ips():
        pods = {p["metadata"]["name"]: p for p in kube.list("Pod", CHECK_NAMESPACE, selector="app=server")}
        ready = {
            name: (pod.get("status") or {}).get("podIP")
            for name, pod in pods.items()
            if (pod.get("status") or {}).get("podIP") and is_ready(pod)
        }
        return ready if len(ready) == len(servers) else None

    ips = wait_for("the check's web servers are Ready", server_ips, 180)
    for name, node, server, admitted in clients:
        fetch = (
            f"printf 'GET /big HTTP/1.0\\r\\n\\r\\n' | busybox nc -w 10 {ips[server]} 8080 > /tmp/reply; "
            "busybox wc -c < /tmp/reply; busybox head -n 1 /tmp/reply | busybox grep -q ' 200 '"
        )
        labels = {"access": "granted" if admitted else "none", "role": "client"}
        kube.create(
            _new(
                "Pod",
                {"name": name, "namespace": CHECK_NAMESPACE, "labels": labels},
                spec={
                    "nodeName": node,
                    "tolerations": toleration,
                    "restartPolicy": "Never",
                    "containers": [{"name": "fetch", "image": toolbox, "command": ["/bin/sh", "-c", fetch]}],
                },
            )
        )

    def ended():
        pods = kube.list("Pod", CHECK_NAMESPACE, selector="role=client")
        phases = {p["metadata"]["name"]: (p.get("status") or {}).get("phase") for p in pods}
        return phases if all(phase in ("Succeeded", "Failed") for phase in phases.values()) else None

    phases = wait_for("the check's clients ended", ended, 180)
    results = {}
    for name, phase in phases.items():
        log = kube.log(name, CHECK_NAMESPACE) or ""
        numbers = [int(line) for line in log.split() if line.isdigit()]
        results[name] = {"phase": phase, "bytes": numbers[-1] if numbers else 0}
    kube.delete("Namespace", CHECK_NAMESPACE)
    return results


def fleet_isolation_check(kube: Kube, toolbox: str, fleet_namespace: str, node: str, clients: list[tuple[str, str]]) -> dict:
    """A web server in ``fleet_namespace`` (under the policies deploy rendered there) and clients (name, namespace)
    that each fetch from its pod IP; a client's namespace that does not exist is made a fleet of its own, with the
    policies deploy renders for any fleet. Every pod runs as the restricted level asks (the fleet namespaces enforce
    it). Returns client -> {"phase", "bytes"}."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import network_policy, pod_security

    made = []
    for namespace in sorted({ns for _name, ns in clients} - _namespaces(kube)):
        kube.create(_new("Namespace", {"name": namespace, "labels": pod_security.namespace_labels("restricted")}))
        for policy in network_policy.fleet_policies(namespace, {"app.kubernetes.io/managed-by": "kuberos-site-check"}):
            kube.create(policy)
        made.append(namespace)
    toleration = [{"key": "kuberos.io/robot", "operator": "Exists", "effect": "NoSchedule"}]
    serve = (
        f"mkdir -p /tmp/www && busybox dd if=/dev/zero of=/tmp/www/big bs=1024 count={BIG_FILE_KIB} 2>/dev/null "
        "&& exec busybox httpd -f -p 8080 -h /tmp/www"
    )
    server = "isolation-server"
    # the toolbox image has no /tmp, and its root is not the user's to write: a scratch volume
    scratch, mount = [{"name": "tmp", "emptyDir": {}}], [{"name": "tmp", "mountPath": "/tmp"}]
    kube.create(
        _new(
            "Pod",
            {"name": server, "namespace": fleet_namespace, "labels": {"app": "isolation-check"}},
            spec=pod_security.harden(
                {
                    "nodeName": node,
                    "tolerations": toleration,
                    "volumes": scratch,
                    "containers": [
                        {
                            "name": "httpd",
                            "image": toolbox,
                            "command": ["/bin/sh", "-c", serve],
                            "volumeMounts": mount,
                            "readinessProbe": {"tcpSocket": {"port": 8080}, "periodSeconds": 1},
                        }
                    ],
                }
            ),
        )
    )
    try:

        def server_ip():
            pod = kube.get("Pod", server, fleet_namespace)
            return (pod.get("status") or {}).get("podIP") if pod and is_ready(pod) else None

        address = wait_for("the isolation check's web server is Ready", server_ip, 180)
        fetch = (
            f"printf 'GET /big HTTP/1.0\\r\\n\\r\\n' | busybox nc -w 10 {address} 8080 > /tmp/reply; "
            "busybox wc -c < /tmp/reply; busybox head -n 1 /tmp/reply | busybox grep -q ' 200 '"
        )
        for name, namespace in clients:
            fetcher = {"name": "fetch", "image": toolbox, "command": ["/bin/sh", "-c", fetch], "volumeMounts": mount}
            spec = {"nodeName": node, "tolerations": toleration, "restartPolicy": "Never", "volumes": scratch}
            kube.create(
                _new(
                    "Pod",
                    {"name": name, "namespace": namespace, "labels": {"app": "isolation-check"}},
                    spec=pod_security.harden({**spec, "containers": [fetcher]}),
                )
            )

        def ended():
            pods = {name: kube.get("Pod", name, ns) for name, ns in clients}
            if any(pod is None for pod in pods.values()):
                return None
            phases = {name: (pod.get("status") or {}).get("phase") for name, pod in pods.items()}
            return phases if all(phase in ("Succeeded", "Failed") for phase in phases.values()) else None

        phases = wait_for("the isolation check's clients ended", ended, 180)
        results = {}
        for name, namespace in clients:
            log = kube.log(name, namespace) or ""
            numbers = [int(line) for line in log.split() if line.isdigit()]
            results[name] = {"phase": phases[name], "bytes": numbers[-1] if numbers else 0}
        return results
    finally:
        for name, namespace in [(server, fleet_namespace), *clients]:
            if namespace not in made:
                with contextlib.suppress(Exception):
                    kube.delete("Pod", name, namespace, grace_seconds=0)
        for namespace in made:
            with contextlib.suppress(Exception):
                kube.delete("Namespace", namespace)


def etcd_gateway(machines, name: str, path: str, body: bytes | None = None) -> dict:
    """One request to control plane ``name``'s etcd through its v3 HTTP gateway (POST with ``body``, else GET), with
    the health-check client certificate kubeadm made on that machine; the answer's JSON, read up to 1 MiB, in 10 s."""
    import http.client
    import ssl

    pki = os.path.join(machines.rootfs(name), "etc", "kubernetes", "pki", "etcd")
    context = ssl.create_default_context(cafile=os.path.join(pki, "ca.crt"))
    context.load_cert_chain(os.path.join(pki, "healthcheck-client.crt"), os.path.join(pki, "healthcheck-client.key"))
    connection = http.client.HTTPSConnection(machines.machines[name].address, 2379, context=context, timeout=10)
    try:
        connection.request("POST" if body is not None else "GET", path, body=body)
        return json.loads(connection.getresponse().read(1 << 20) or b"{}")
    finally:
        connection.close()


def etcd_members(machines, name: str) -> list[str]:
    """etcd's member names as one control plane's etcd lists them."""
    listed = etcd_gateway(machines, name, "/v3/cluster/member/list", b"{}")
    return sorted(member.get("name", "") for member in listed.get("members", []))


def vip_holders(machines, control_planes) -> list[str]:
    """The control planes that hold the virtual IP now: exactly one while keepalived works."""
    return [n for n in control_planes if f"inet {VIP}/" in machines.exec(n, "ip", "-4", "-o", "addr", check=False).stdout]


def _held_elsewhere(machines, holder: str) -> str:
    """The control plane holding the virtual IP if it is not ``holder`` (empty otherwise)."""
    now = vip_holder(machines, CONTROL_PLANES)
    return now if now != holder else ""


def vip_holder(machines, control_planes) -> str:
    """The control plane that holds the virtual IP now (empty when none does)."""
    return next(iter(vip_holders(machines, control_planes)), "")


def _namespaces(kube: Kube) -> set[str]:
    return {n["metadata"]["name"] for n in kube.list("Namespace")}


FLEET = "picking"
CPU_SCALE = 4  # the lab's seven machines share 2 cores: every module asks a quarter of the example's CPU


def lab_example(source: str, destination: str) -> str:
    """``examples/pick-and-place.yml`` for the lab site: aimed at the sample site's picking fleet, each module's CPU
    request divided by CPU_SCALE (three robots' motion planners at 2 cores each would need six; each machine's kubelet
    has the two this machine has). Everything else, images and launch commands included, is the example's."""
    import yaml

    with open(source, encoding="utf-8") as handle:
        documents = list(yaml.safe_load_all(handle))
    for document in documents:
        document["metadata"]["targetFleet"] = FLEET
        for module in document.get("rosModules", []):
            resources = module.get("resources") or {}
            if "cpu" in resources:
                text = str(resources["cpu"])
                millis = int(text[:-1]) if text.endswith("m") else round(float(text) * 1000)
                resources["cpu"] = f"{max(1, millis // CPU_SCALE)}m"
    with open(destination, "w", encoding="utf-8") as handle:
        yaml.safe_dump_all(documents, handle, sort_keys=False)
    return destination


class SiteChain:
    """The infrastructure engineer's and the developer's days chained on the lab site, one step per method; each
    step records its figures in ``figures`` (the benchmark's keys) and returns what the test asserts on."""

    def __init__(self, lab: SiteLab, spec: str, log=print):
        self.lab = lab
        self.spec = spec  # the example, aimed at the sample site's picking fleet
        self.log = log
        self.figures: dict = {}
        self.kube: Kube | None = None  # the chain's own reads and writes
        self.core = None  # the typed CoreV1Api under it, for the test's own assertions

    def _play(self, name: str, *extra: str, timeout: float = PLAYBOOK_TIMEOUT) -> subprocess.CompletedProcess:
        started = time.monotonic()
        result = self.lab.playbook(name, *extra, timeout=timeout)
        result.seconds = time.monotonic() - started
        self.log(f"site chain: {name} {' '.join(extra)} -> rc {result.returncode} in {result.seconds:.0f} s")
        return result

    def connect(self):
        self.kube = kube(self.lab.kubeconfig)
        self.core = self.kube.clients["core"]
        return self

    def site(self, key: str = "bare_to_ready_s") -> subprocess.CompletedProcess:
        """site.yml; the first run's figure is from bare machines to every node Ready. Records the nodes' figures
        (``hosts``, ``control_planes``, ``cloud_node_joined_over_vpn``: the cloud VM Ready with its tunnel address)."""
        result = self._play("site.yml")
        if result.returncode == 0:
            self.connect()
            expected = len(self.lab.machines.machines)
            wait_for("every node Ready", lambda: len([n for n in nodes(self.kube).values() if n["ready"]]) == expected, 300)
            found = nodes(self.kube)
            cloud = found.get(CLOUD_VM, {})
            self.figures.update(hosts=len(found), control_planes=len(CONTROL_PLANES))
            tunnel_ip = self.lab.vpn_address(CLOUD_VM)
            self.figures["cloud_node_joined_over_vpn"] = bool(cloud.get("ready")) and cloud.get("internal_ip") == tunnel_ip
            self.figures["cni"] = self.cni()
        self.figures[key] = round(result.seconds, 1)
        return result

    def cni(self) -> dict:
        """The pod network the cluster runs, read from it: the CNI's name and its agent image's tag, and how many
        nodes run a Ready agent."""
        names = {"cilium": "cilium", "calico-node": "calico"}
        for daemonset in self.kube.clients["apps"].list_namespaced_daemon_set("kube-system").items:
            if daemonset.metadata.name in names:
                image = daemonset.spec.template.spec.containers[0].image
                ready = (daemonset.status and daemonset.status.number_ready) or 0
                return {"name": names[daemonset.metadata.name], "version": image.rpartition(":")[2], "ready_agents": ready}
        return {"name": "", "version": "", "ready_agents": 0}

    def network(self, toolbox: str, robot: str, edge: str, other_edge: str, cloud: str) -> dict:
        """Pod to pod across nodes (robot to edge worker, robot to cloud VM through the VPN) and a refusal."""
        results = pod_network_check(
            self.kube, toolbox, {"server-edge": edge, "server-cloud": cloud},
            [("robot-to-edge", robot, "server-edge", True), ("robot-to-cloud", robot, "server-cloud", True),
             ("edge-refused", other_edge, "server-edge", False)],
        )  # fmt: skip
        whole = BIG_FILE_KIB * 1024

        def reached(name: str) -> bool:
            return results[name]["phase"] == "Succeeded" and results[name]["bytes"] >= whole

        self.figures["cross_node_pod_traffic"] = reached("robot-to-edge")
        self.figures["cloud_pod_traffic_over_vpn"] = reached("robot-to-cloud")
        self.figures["policy_denied"] = results["edge-refused"]["phase"] == "Failed" and results["edge-refused"]["bytes"] == 0
        return results

    def fleet_isolation(self, toolbox: str, node: str) -> dict:
        """The app's fleet namespace under the policies deploy rendered: its own pods reach a server there, a pod of
        another fleet and one of the metrics namespace (on a port that is not a metrics port) do not."""
        results = fleet_isolation_check(
            self.kube, toolbox, f"kuberos-{FLEET}", node,
            [("same-fleet", f"kuberos-{FLEET}"), ("other-fleet", "kuberos-other-fleet"), ("metrics-ns", "kuberos-system")],
        )  # fmt: skip
        whole = BIG_FILE_KIB * 1024
        self.figures["fleet_isolation"] = {
            name: result["phase"] == "Succeeded" and result["bytes"] >= whole for name, result in results.items()
        }
        return results

    def second_site(self) -> subprocess.CompletedProcess:
        result = self._play("site.yml")
        self.figures["second_run_s"] = round(result.seconds, 1)
        self.figures["second_run_changed"] = sum(counts["changed"] for counts in result.recap.values())
        return result

    def controller(self) -> subprocess.CompletedProcess:
        return self._play("controller.yml", "-e", "controller_mode=in_cluster")

    def deploy(self, render_dir: str, key: str = "redeploy_s") -> subprocess.CompletedProcess:
        # The robots' simulated hardware, which publishes the camera and joint topics the example's modules subscribe
        # (external: true), starts after the deploy: the deploy's live graph check would find no publisher of them yet.
        result = self._play("deploy.yml", "-e", f"rosdeployment_file={self.spec}", "-e", f"kuberos_render_dir={render_dir}",
                            "-e", "rosdeployment_graph_check=false")  # fmt: skip
        self.figures[key] = round(result.seconds, 1)
        return result

    def app(self, render_dir: str) -> subprocess.CompletedProcess:
        """controller.yml (in the cluster), then deploy.yml of the example until every pod is Ready where placed;
        records ``ready_to_app_running_s`` for both. Returns the first that failed, or the deploy."""
        started = time.monotonic()
        result = self.controller()
        if result.returncode == 0:
            result = self.deploy(render_dir, key="deploy_s")
        self.figures["ready_to_app_running_s"] = round(time.monotonic() - started, 1)
        return result

    def pick_cycles(self, robot: str, fleet: str, cycles: int = 1, time_limit: float = 600) -> dict:
        """The robot's simulated hardware as a pod on its node, until the deployed modules complete ``cycles``."""
        paths = [
            os.path.join(self.lab.root, "sim"),
            os.path.join(self.lab.root, ".collections"),
            os.environ.get("PYTHONPATH", ""),
        ]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
        command = [
            sys.executable, "-m", "kuberos_sim.real_pods", "--kubeconfig", self.lab.kubeconfig, "--robots", robot,
            "--fleet", fleet, "--cycles", str(cycles), "--time-limit", str(time_limit),
        ]  # fmt: skip
        started = time.monotonic()
        done = run_bounded(command, time_limit + 120, cwd=self.lab.root, env=env)
        summary = {}
        with contextlib.suppress(ValueError):
            summary = json.loads(done.stdout[done.stdout.index("{\n") :])
        succeeded = sum(c.get("succeeded", 0) for c in summary.get("cycles", {}).values())
        self.figures["pick_cycles_completed"] = succeeded
        self.figures["pick_cycles_s"] = round(time.monotonic() - started, 1)
        return {"returncode": done.returncode, "summary": summary, "output": done.stdout[-3000:] + done.stderr[-2000:]}

    def undeploy(self) -> subprocess.CompletedProcess:
        result = self._play("undeploy.yml", "-e", f"rosdeployment_file={self.spec}")
        self.figures["undeploy_s"] = round(result.seconds, 1)
        return result

    def register_robot(self) -> subprocess.CompletedProcess:
        """Boot the new robot, then register_robot.yml with the join on (its default), until its node is Ready."""
        address = self.lab.add_new_robot()
        connection = self.lab.machines.connection_vars()
        extra = {
            # how this machine reaches every lab machine (the SSH user and become come from the role and the play)
            "ansible_ssh_private_key_file": connection["ansible_ssh_private_key_file"],
            "ansible_ssh_common_args": connection["ansible_ssh_common_args"],
            "robot_register_name": NEW_ROBOT,
            "robot_register_address": address,
            "robot_register_fleet": "picking",
            "robot_register_user": connection["ansible_user"],
            "robot_register_admin_key": connection["ansible_ssh_private_key_file"],
            "robot_register_cluster_key": connection["ansible_ssh_private_key_file"] + ".pub",
            "robot_register_extra_devices": ["gripper"],
        }
        with open(self.lab.path("register.json"), "w", encoding="utf-8") as handle:
            json.dump(extra, handle)
        started = time.monotonic()
        result = self._play("register_robot.yml", "-e", f"@{self.lab.path('register.json')}")
        if result.returncode == 0:  # the join returns once the kubelet started; Ready comes with its CNI
            wait_for(f"{NEW_ROBOT} Ready", lambda: nodes(self.kube).get(NEW_ROBOT, {}).get("ready"), 300)
        self.figures["register_robot_s"] = round(time.monotonic() - started, 1)
        return result

    def site_with_robots_offline(self, robot: str, ghost: str, ghost_address: str) -> subprocess.CompletedProcess:
        """Power ``robot`` (a machine that joined) off, add ``ghost`` to the inventory (a robot of the picking fleet at
        an address where no machine answers: one that never joined), and run site.yml: it must succeed, name both
        once, and make no Node for the ghost. Records ``site_run_with_robot_offline_ok`` and ``..._s``; the ghost's
        inventory file is removed afterwards, the robot stays off."""
        import yaml

        self.lab.machines.power_off(robot)
        ghost_file = self.lab.path("inventory", "offline-robot.yml")
        variables = {**self.lab.machines.connection_vars(), "ansible_host": ghost_address, "kuberos_address": ghost_address,
                     "kuberos_robot": ghost.split(".")[0], "kuberos_devices": ["camera", "gripper"],
                     "kuberos_cpu": "1500m", "kuberos_memory": "8Gi", "kuberos_gpu": 0}  # fmt: skip
        groups = {"all": {"children": {"robots": {"children": {"fleet_picking": {"hosts": {ghost: variables}}}}}}}
        with open(ghost_file, "w", encoding="utf-8") as handle:
            yaml.safe_dump(groups, handle, sort_keys=False)
        try:
            result = self._play("site.yml")
        finally:
            os.remove(ghost_file)
        # each time the run says it, up to the next task (the YAML callback folds a long message over lines)
        said = [part.split("TASK [")[0] for part in result.stdout.split("Robots left out (powered off or unreachable)")[1:]]
        ok = result.returncode == 0 and len(said) == 1 and robot in said[0] and ghost in said[0]
        self.figures["site_run_with_robot_offline_ok"] = ok and ghost.split(".")[0] not in str(sorted(nodes(self.kube)))
        self.figures["site_run_with_robot_offline_s"] = round(result.seconds, 1)
        result.said = said
        return result

    def _nodes_within(self, seconds: float) -> list[dict]:
        """Every node, the request bounded by ``seconds`` (an API server behind a lost virtual IP may not answer)."""
        return Kube(self.kube.clients, read_timeout=seconds).list("Node")

    def hand_vip_to(self, machine: str, timeout: float = 60) -> None:
        """Move the virtual IP to control plane ``machine`` as an operator would: keepalived stopped on the holder
        (it gives the address up at once, to the highest priority left: the first control plane's is the highest) and
        started again there (keepalived's nopreempt: it comes back as a backup), until ``machine`` holds it. Where the
        address is after an etcd restore or a renewal depends on which API server came back first."""
        machines = self.lab.machines
        for _turn in CONTROL_PLANES:
            holder = vip_holder(machines, CONTROL_PLANES)
            if holder == machine:
                return
            if not holder:
                raise SiteLabError(f"no control plane holds the virtual IP {VIP}")
            machines.exec(holder, "systemctl", "stop", "keepalived")
            try:
                moved = functools.partial(_held_elsewhere, machines, holder)
                wait_for(f"the virtual IP away from {holder}", moved, timeout, 0.5)
            finally:
                machines.exec(holder, "systemctl", "start", "keepalived")
            self.log(f"site chain: the virtual IP handed from {holder} to {vip_holder(machines, CONTROL_PLANES)}")
        raise SiteLabError(f"the virtual IP did not reach {machine}: held by {vip_holders(machines, CONTROL_PLANES)}")

    def lose_vip_holder(self, timeout: float = 120) -> str:
        """Cut the power of the control plane holding the virtual IP (its PID 1 killed) and wait until the API
        answers through the same endpoint; records ``api_back_after_losing_the_vip_holder_s`` (to the first answer)
        and returns the lost control plane."""
        holder = vip_holder(self.lab.machines, CONTROL_PLANES)
        if not holder:
            raise SiteLabError(f"no control plane holds the virtual IP {VIP}")
        started = time.monotonic()
        self.lab.machines.power_off(holder)
        wait_for("the API through the virtual IP", lambda: self._nodes_within(3), timeout, 1)
        self.figures["api_back_after_losing_the_vip_holder_s"] = round(time.monotonic() - started, 1)
        return holder


def serve_images(registry, archives: list[str], repo_root: str, cache_dir: str, app_images: bool, log=print) -> dict:
    """Start ``registry`` (a `registry.LocalRegistry`) and push every image a site runs under the name its specs,
    kubeadm and the CNI's role use: the ``archives`` (``registry.k8s.io/...``, ``quay.io/cilium/...``, the lab's
    toolbox) and, with ``app_images``, the collection's images (``ghcr.io/kuberos/...``, ``ros:jazzy-ros-base``).
    Returns node_prereqs_registry_mirrors: the registry as the mirror of each of those registries."""
    names = {_archive_name(archive): archive for archive in archives}
    if app_images:
        images = local_images.build_images(repo_root, cache_dir, log=log)
        for alias, reference in local_images.image_aliases(images).items():
            if not alias.startswith("kuberos.local/prometheus"):  # no site runs the lab's Prometheus image
                names[alias] = images.get(reference) or images[_unqualified(reference, images)]
    registry.start()
    client = registry.client()
    hosts, first_repository = set(), {}
    started = time.monotonic()
    for name, archive in sorted(names.items()):
        host, repository, tag = _split(name)
        _digest, done = client.push_archive(archive, repository, tag, mount_from=first_repository.get(archive))
        first_repository.setdefault(archive, repository)
        hosts.add(host)
        if done["uploaded"]:
            log(f"lab mirror: pushed {name} ({done['bytes'] / 2**20:.1f} MiB)")
    log(f"lab mirror: {registry.address} serves {len(names)} images ({time.monotonic() - started:.1f} s)")
    with open(registry.ca_file, encoding="utf-8") as handle:
        ca = handle.read()
    return {host: [{"url": f"https://{registry.address}", "ca": ca}] for host in sorted(hosts)}


def _groups_of(group: dict, name: str = "all", parents: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """host -> every group it is in (its own and the ancestors), from an inventory's YAML."""
    found: dict[str, list[str]] = {}
    chain = (*parents, name) if name != "all" else parents
    for host in group.get("hosts") or {}:
        found.setdefault(host, [])
        found[host] += [g for g in chain if g not in found[host]]
    for child, body in (group.get("children") or {}).items():
        for host, groups in _groups_of(body or {}, child, chain).items():
            found.setdefault(host, [])
            found[host] += [g for g in groups if g not in found[host]]
    return found


def _split(reference: str) -> tuple[str, str, str]:
    """``ghcr.io/kuberos/pnp-planner:0.1`` -> (``ghcr.io``, ``kuberos/pnp-planner``, ``0.1``)."""
    host, _sep, rest = reference.partition("/")
    name, _sep, tag = rest.rpartition(":")
    return host, name, tag


def _archive_name(archive: str) -> str:
    """The name an OCI archive of the lab's builds gives its image (containerd's annotation)."""
    import tarfile

    with tarfile.open(archive, "r:") as tar:
        (descriptor,) = json.load(tar.extractfile("index.json"))["manifests"]
    return local_images._qualified(descriptor["annotations"]["io.containerd.image.name"])


def _unqualified(reference: str, images: dict) -> str:
    for built in images:
        if reference.endswith("/" + built) or reference.endswith(built):
            return built
    raise SiteLabError(f"{reference}: no built image of that name")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="The sample site on lab machines (kuberos_lab.site_lab).")
    sub = parser.add_subparsers(dest="command", required=True)
    up = sub.add_parser("up", help="boot the machines, start the registry mirror, write DIR/inventory")
    up.add_argument("--state", required=True)
    up.add_argument("--cache-dir", default=os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    down = sub.add_parser("down", help="power off and remove what the lab made on this machine")
    down.add_argument("--state", required=True)
    down.add_argument("--remove", action="store_true", help="also delete the machines' files and the state")
    args = parser.parse_args(argv)
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), *[os.pardir] * 3))
    try:
        if args.command == "up":
            SiteLab(args.state, root, args.cache_dir).up()
            print(os.path.join(os.path.abspath(args.state), "inventory"))
        else:
            SiteLab(args.state, root).down(remove=args.remove)
    except (SiteLabError, lab_machines.MachineError) as error:
        print(f"site lab: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
