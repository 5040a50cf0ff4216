"""The runtime: a rendered RosDeployment run for real on this machine.

    with Runtime("rendered/pick-and-place", inventory, "/tmp/run") as runtime:
        runtime.start()                       # hosts, fabric, discovery servers, then the modules
        runtime.start_on("fetch-1", "physics", ["python3", "-m", "kuberos_pnp.world"], cgroup="hardware")
        ...
        runtime.cpu_seconds()[("fetch-1", "node")], runtime.fabric_stats()
    # closed: processes stopped, namespaces, cgroups and /etc/netns/<ns> removed; figures kept

Hosts are the nodes the Deployments are pinned to, plus those added with ``add_host``. Hosts can come and go
while the run goes on (cloud VMs provisioned for a peak): ``add_host`` after ``start`` makes the host at once, with
the lowest free address (a running host's never moves), and the fabric reloads its config (SIGHUP);
``remove_host`` stops the host's processes, detaches it from the fabric and removes it, its CPU seconds still
counted. Each is a network namespace ``krs-<suffix>-<node>`` (netns.py) with a TUN eth0 whose packets the fabric
process (fabric.py) delays by the inventory's latencies (delays.py), and two cgroups,
``kuberos-sim-<suffix>/<node>`` with the node's scaled CPU quota (and a weight in proportion to it) and
``.../<node>.hardware`` without one (with the default weight; cgroups.py). Every container of
every Deployment runs its rendered command on its node's host (processes.py), with the ROS wheels'
environment, the container's env and its configMap volumes.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

from . import cgroups, delays, netns
from . import fabric as fabric_script
from ._core import COLLECTIONS_DIR, SIM_DIR, Problem, SpecError, labels, manifests, ros_wheels
from .processes import SimProcess, VolumeMount, launch, stop_all
from .rendered import Deployment, RenderedDir, configmap_files, load_rendered, parse_deployment, resolve_env

DEFAULT_CPU_SCALE = 0.125  # a 4-CPU robot gets half a core, a 16-CPU edge server 2 cores (capped at this machine's)
DEFAULT_SUBNET = "10.213.64.0/24"  # exists only inside the run's namespaces
DEFAULT_MTU = 65000  # Fast DDS's 64 KB datagrams cross unfragmented
FABRIC_READY_TIMEOUT = 15.0  # the fabric attaching every host at start, or reloading its config
FABRIC_RELOADED = "fabric reloaded"  # the fabric's line once it reloaded its config (SIGHUP)
FABRIC_RELOAD_FAILED = "fabric reload failed"  # its line when it could not (it keeps the hosts it had)
SERVER_READY_TIMEOUT = 20.0  # a discovery server binding its UDP port
SETTLE_SECONDS = 1.5  # modules exiting this soon after start are reported
STOP_TIMEOUT = 5.0  # per signal (SIGINT, SIGTERM) before SIGKILL
CGROUPS = ("node", "hardware")


def metrics_file(run_dir: str, process: str) -> str:
    """Where a module process may write its Prometheus exposition (``KUBEROS_METRICS_FILE``): the simulator's
    scaler reads it there, as a controller scrapes a pod's ``/metrics``."""
    return os.path.join(run_dir, "metrics", re.sub(r"[^A-Za-z0-9_.-]+", "_", process) + ".prom")


class ProcessExitedError(RuntimeError):
    """Processes exited right after they were started; the message holds their log tails."""


@dataclass
class Host:
    """A node of the inventory, simulated: its namespace, address and CPU groups."""

    node: str
    tier: str
    netns: str
    address: str
    cpu_cores: float
    cgroups: dict[str, cgroups.Cgroup] = field(default_factory=dict)


@dataclass
class RemovedHost:
    """A host removed while the run went on, with its figures then."""

    host: Host
    cpu_seconds: dict[str, float]  # "node" | "hardware" -> CPU seconds its cgroup used in all
    tun_tx_dropped: int = 0  # packets its TUN dropped before the fabric read them (see Runtime.fabric_stats)


def default_prefix() -> str:
    """The venv the processes run from: the checkout's .venv, else this interpreter's."""
    venv = os.path.join(os.path.dirname(SIM_DIR), ".venv")
    return venv if os.path.exists(os.path.join(venv, "bin", "python3")) else sys.prefix


def environment_problem() -> str | None:
    """Why the runtime cannot run here (None if it can): root, ip netns, TUN, cgroup v1 cpu/cpuacct."""
    return netns.netns_problem() or cgroups.cgroup_problem()


class Runtime:
    """Runs a rendered directory on this machine; a context manager that closes everything on exit."""

    def __init__(
        self,
        rendered_dir: str,
        inventory,
        run_dir: str,
        cpu_scale: float = DEFAULT_CPU_SCALE,
        *,
        extra_hosts: tuple[str, ...] = (),
        prefix: str | None = None,
        cluster_domain: str = "cluster.local",
        subnet: str = DEFAULT_SUBNET,
        mtu: int = DEFAULT_MTU,
        settle_seconds: float = SETTLE_SECONDS,
        stop_timeout: float = STOP_TIMEOUT,
        fabric_options: dict | None = None,
    ):
        self.rendered: RenderedDir = load_rendered(rendered_dir)
        self.inventory = inventory
        self.run_dir = os.path.abspath(run_dir)
        if any(c in self.run_dir for c in ",:\n"):
            raise ValueError(f"run_dir {self.run_dir}: ',' and ':' would break the overlay mount options")
        if cpu_scale <= 0:
            raise ValueError(f"cpu_scale {cpu_scale} is not valid; expected a number > 0")
        self.cpu_scale = cpu_scale
        self.prefix = prefix or default_prefix()
        self.cluster_domain = cluster_domain
        self.subnet, self.mtu = subnet, mtu
        self.settle_seconds, self.stop_timeout = settle_seconds, stop_timeout
        self.fabric_options = dict(fabric_options or {})
        self.suffix = secrets.token_hex(3)
        self.cgroup_parent = f"kuberos-sim-{self.suffix}"
        self.hosts: dict[str, Host] = {}
        self.processes: dict[str, SimProcess] = {}
        self.stopped: list[SimProcess] = []  # processes of Deployments (or hosts) stopped while the run went on
        self.removed: list[RemovedHost] = []  # hosts removed while the run went on, in the order they were
        self.fabric_reload_seconds: list[float] = []  # how long each reload of the fabric took (SIGHUP to its line)
        # hosts and removed change together: a scaler's thread adds and removes hosts while the figures are read
        self._hosts_lock = threading.Lock()
        self.fabric: subprocess.Popen | None = None
        self._started = self._closed = False
        self._etc_netns_created = False
        self._fabric_config: dict = {}
        self._fabric_config_path = self._fabric_log = ""
        self._final_cpu: dict[tuple[str, str], float] | None = None
        self._final_fabric: dict | None = None
        self._final_fabric_cpu: float | None = None
        self.close_problems: list[str] = []
        self._check_nodes(self.rendered.nodes, self.rendered.deployments.values())
        self._nodes = list(self.rendered.nodes)
        for node in extra_hosts:
            self.add_host(node)

    # --- set-up ---------------------------------------------------------------------------------------

    def _check_nodes(self, nodes, deployments=()) -> None:
        problems = []
        for deployment in deployments:
            if deployment.node not in self.inventory.nodes:
                problems.append(
                    Problem(
                        deployment.source, "spec.template.spec.nodeSelector", f"node '{deployment.node}' is not in the inventory"
                    )
                )
        for node in nodes:
            if node not in self.inventory.nodes and not any(p.message.startswith(f"node '{node}'") for p in problems):
                problems.append(Problem("hosts", node, "is not a node of the inventory"))
        if problems:
            raise SpecError(problems, title="the rendered deployment does not fit the inventory")

    def add_host(self, node: str, inventory=None) -> Host | None:
        """Simulate this inventory node too: a robot computer no module runs on, or a cloud VM provisioned while the
        run goes on. ``inventory`` replaces the run's (it must hold every host and ``node``, e.g. the run's
        ``inventory.with_nodes([...])``). Before ``start`` the node is planned with the others (None returned).
        After, its host is made at once and returned: namespace, cgroups, the lowest free address (no running
        host's moves), its /etc/netns hosts file, and the fabric attached to it (config rewritten with the delays
        recomputed, SIGHUP, waited for). When any of that fails, what it made is removed, the inventory restored
        and the error raised (RuntimeError with the fabric log's tail when the fabric did not reload)."""
        if self._started:
            self._require_started()
            if node in self.hosts:
                raise ValueError(f"{node!r} is a host of this run already")
        previous = self.inventory
        if inventory is not None:
            self.inventory = inventory
        try:
            self._check_nodes([*self._nodes, node], self.rendered.deployments.values())
        except SpecError:
            self.inventory = previous
            raise
        if not self._started:
            if node not in self._nodes:
                self._nodes.append(node)
            return None
        host, making, signalled = None, False, False
        try:
            host = self._make_host(node, netns.free_address(self.subnet, [h.address for h in self.hosts.values()]))
            left = self._host_leftovers(host)
            if left:
                raise RuntimeError(f"{node}: an earlier host of that name left {', '.join(left)}")
            with self._hosts_lock:
                self.hosts[node], making = host, True
            self._create_host(host)
            self._etc_netns_created |= netns.write_hosts(host.netns, self._hosts_text())
            signalled = True
            self._reload_fabric()
        except BaseException:
            self.inventory = previous
            if making:
                with self._hosts_lock:
                    del self.hosts[node]
                if signalled:
                    try:
                        self._reload_fabric()  # detaches it, should the fabric have attached it after all
                    except RuntimeError as error:
                        self.close_problems.append(f"{node}: the fabric did not reload after a failed add: {error}")
                self.close_problems.extend(self._remove_host_parts(host))
            raise
        self._nodes.append(node)
        return host

    def remove_host(self, node: str) -> list[SimProcess]:
        """Stop simulating a node; the Deployments pinned to it are dropped from the run. Before ``start`` it is
        just forgotten. While the run goes on, every process on its host is stopped (as ``stop_deployment`` stops
        them; they go to ``stopped``), its cgroups' CPU seconds recorded (``removed``: ``cpu_seconds`` goes on
        counting them), the fabric detached from it (config rewritten, SIGHUP, waited for), then its cgroups, namespace and
        /etc/netns dir removed (problems in ``close_problems``). Returns the processes it stopped; RuntimeError
        after all that when the fabric did not reload."""
        if node not in (self.hosts if self._started else self._nodes):
            raise KeyError(f"{node!r} is not a host of this run; hosts: {', '.join(self.hosts or self._nodes)}")
        if self._started:
            self._require_started()
        for name in [d.name for d in self.rendered.deployments.values() if d.node == node]:
            self.rendered.deployments.pop(name)
        self._nodes.remove(node)
        if not self._started:
            return []
        host = self.hosts[node]
        processes = [p for p in self.processes.values() if p.host == node]
        stop_all(list(reversed(processes)), self.stop_timeout)
        for process in processes:
            self.processes.pop(process.name, None)
            self.stopped.append(process)
        removed = RemovedHost(host, {kind: g.usage_seconds() for kind, g in host.cgroups.items()}, _tun_tx_dropped(host.netns))
        with self._hosts_lock:
            self.removed.append(removed)
            del self.hosts[node]
        failed = None
        try:
            self._reload_fabric()
        except RuntimeError as error:
            failed = error
        self.close_problems.extend(self._remove_host_parts(host))
        if failed is not None:
            raise failed
        return processes

    def _make_host(self, node: str, address: str) -> Host:
        """The host a node is simulated as (nothing made yet): its namespace's name, the node's scaled CPU quota,
        its ``node`` cgroup with that quota and a weight in proportion, its ``hardware`` cgroup without one."""
        model = self.inventory.nodes[node]
        cores = cgroups.quota_cores(model.cpu_millis, self.cpu_scale)
        host = Host(node, model.tier, f"krs-{self.suffix}-{node}"[:60], address, cores)
        base = f"{self.cgroup_parent}/{node}"
        host.cgroups = {
            "node": cgroups.Cgroup(base, cores, cgroups.shares_for(cores)),
            "hardware": cgroups.Cgroup(f"{base}.hardware", None, cgroups.HARDWARE_SHARES),
        }
        return host

    def _plan_hosts(self) -> None:
        nodes = sorted(self._nodes)
        addresses = netns.host_addresses(self.subnet, nodes)
        for node in nodes:
            self.hosts[node] = self._make_host(node, addresses[node])

    def _hosts_text(self) -> str:
        names: dict[str, str] = {host.node: host.address for host in self.hosts.values()}
        short: dict[str, set[str]] = {}
        for service, node in self.rendered.service_nodes():
            address = self.hosts[node].address
            for name in netns.service_names(service.name, service.namespace, self.cluster_domain):
                names[name] = address
            short.setdefault(service.name, set()).add(address)
        names.update({name: next(iter(found)) for name, found in short.items() if len(found) == 1 and name not in names})
        return netns.hosts_file(names)

    def _create_host(self, host: Host) -> None:
        netns.create_host(host.netns, host.address, ipaddress.ip_network(self.subnet).prefixlen, self.mtu)
        for group in host.cgroups.values():
            group.create()

    def _create_hosts(self) -> None:
        for host in self.hosts.values():
            self._create_host(host)
        text = self._hosts_text()
        for host in self.hosts.values():
            self._etc_netns_created |= netns.write_hosts(host.netns, text)

    def _write_fabric_config(self) -> None:
        """The fabric's config.json: the hosts as they are now, their delays from the inventory (replaced whole)."""
        directory = os.path.dirname(self._fabric_config_path)
        self._fabric_config = {
            "hosts": [{"node": h.node, "netns": h.netns, "tun": netns.TUN, "address": h.address} for h in self.hosts.values()],
            "delay_ms": delays.one_way_delays_ms(self.inventory, list(self.hosts)),
            "link_bps": delays.link_rates_bps(self.inventory, list(self.hosts)),
            "link_loss": delays.link_losses(self.inventory, list(self.hosts)),
            "broadcasts": [str(ipaddress.ip_network(self.subnet).broadcast_address)],
            "stats_file": os.path.join(directory, "stats.json"),
            "stats_interval": 1.0,
            **self.fabric_options,
        }
        with open(self._fabric_config_path + ".tmp", "w", encoding="utf-8") as handle:
            json.dump(self._fabric_config, handle, indent=1)
        os.replace(self._fabric_config_path + ".tmp", self._fabric_config_path)

    def _start_fabric(self) -> None:
        directory = os.path.join(self.run_dir, "fabric")
        os.makedirs(directory, exist_ok=True)
        self._fabric_config_path = os.path.join(directory, "config.json")
        self._write_fabric_config()
        self._fabric_log = os.path.join(directory, "fabric.log")
        script = fabric_script.SCRIPT
        with open(self._fabric_log, "ab") as out:
            self.fabric = subprocess.Popen(
                [sys.executable, script, self._fabric_config_path],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + FABRIC_READY_TIMEOUT
        while time.monotonic() < deadline:
            if "fabric ready" in _read(self._fabric_log):
                return
            if self.fabric.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"the fabric did not start (exit {self.fabric.poll()}):\n{_read(self._fabric_log)[-3000:]}")

    def _reload_fabric(self) -> None:
        """Rewrite the fabric's config with the hosts as they are now, SIGHUP it and wait for its reload (its
        ``fabric reloaded`` line; the seconds it took go to ``fabric_reload_seconds``). RuntimeError with the
        log's tail when it failed, exited or took more than FABRIC_READY_TIMEOUT."""
        if self.fabric is None:
            raise RuntimeError("the fabric is not running")
        self._write_fabric_config()
        log = _read(self._fabric_log)
        reloaded, failed = log.count(FABRIC_RELOADED), log.count(FABRIC_RELOAD_FAILED)
        start = time.monotonic()
        self.fabric.send_signal(signal.SIGHUP)
        while time.monotonic() - start < FABRIC_READY_TIMEOUT:
            log = _read(self._fabric_log)
            if log.count(FABRIC_RELOADED) > reloaded:
                self.fabric_reload_seconds.append(time.monotonic() - start)
                return
            if log.count(FABRIC_RELOAD_FAILED) > failed or self.fabric.poll() is not None:
                break
            time.sleep(0.01)
        raise RuntimeError(f"the fabric did not reload its config (exit {self.fabric.poll()}):\n{log[-3000:]}")

    def base_env(self) -> dict[str, str]:
        """What every process gets before its own env: the ROS wheels' environment, PYTHONPATH with sim/."""
        env = ros_wheels.ros_environment(self.prefix, log_dir=os.path.join(self.run_dir, "ros-log"))
        env["PYTHONPATH"] = os.pathsep.join([SIM_DIR, COLLECTIONS_DIR])
        env["HOME"] = os.path.join(self.run_dir, "home")
        return env

    # --- processes ------------------------------------------------------------------------------------

    def _launch(self, name, host, command, env, mounts, cgroup, deployment=None) -> SimProcess:
        if name in self.processes:
            raise ValueError(f"a process named {name!r} runs already")
        if host not in self.hosts:
            raise ValueError(f"{host!r} is not a host of this run; hosts: {', '.join(self.hosts)}")
        if cgroup not in CGROUPS:
            raise ValueError(f"cgroup {cgroup!r} is not valid; expected one of {', '.join(CGROUPS)}")
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
        process = launch(
            name,
            host,
            self.hosts[host].netns,
            self.hosts[host].cgroups[cgroup].procs_files,
            [str(c) for c in command],
            {**self.base_env(), **(env or {})},
            mounts,
            os.path.join(self.run_dir, "logs", f"{safe}.log"),
            os.path.join(self.run_dir, "scratch", safe),
            cgroup,
            deployment,
            os.path.join(self.run_dir, "shm", host),
        )
        self.processes[name] = process
        return process

    def start_on(
        self, host: str, name: str, command: list[str], env: dict[str, str] | None = None, cgroup: str = "node"
    ) -> SimProcess:
        """Start an extra process on a host: its ``node`` cgroup (the node's quota) or ``hardware`` (none)."""
        self._require_started()
        return self._launch(name, host, command, env, [], cgroup)

    def container_env(self, deployment: str, container: str | None = None) -> dict[str, str]:
        """A rendered container's environment as resolved on its host (the first container by default)."""
        dep = self.rendered.deployments[deployment]
        chosen = next((c for c in dep.containers if container in (None, c.name)), None)
        if chosen is None:
            raise KeyError(f"{deployment} has no container {container!r}")
        return self._resolved_env(dep, chosen)

    def _resolved_env(self, dep: Deployment, container) -> dict[str, str]:
        """As the kubelet sets it on the Deployment's host, with the service links of its namespace."""
        links = self.rendered.service_links(dep.namespace, self.host_address, dep.node)
        return resolve_env(container, dep, self.host_address(dep.node), self.rendered.configmaps, links)

    def _volumes(self, dep: Deployment, container_name: str, mounts) -> list[VolumeMount]:
        result = []
        for mount in mounts:
            directory = os.path.join(self.run_dir, "volumes", dep.name, mount.volume)
            if not os.path.isdir(directory):
                os.makedirs(directory)
                volume = dep.volumes[mount.volume]
                if "configMap" in volume:
                    configmap = self.rendered.configmaps.get((dep.namespace, volume["configMap"].get("name")), {})
                    for rel, content in configmap_files(configmap, volume).items():
                        path = os.path.join(directory, rel)
                        os.makedirs(os.path.dirname(path), exist_ok=True)
                        with open(path, "wb") as handle:
                            handle.write(content)
            result.append(VolumeMount(directory, mount.path, mount.read_only))
        return result

    # --- changes while it runs (a controller's: scaling adds and removes instances, moves robots) ----------------

    def add_deployment(self, obj: dict) -> Deployment:
        """Take a rendered Deployment object (a plain dict, as ``render_deployment`` makes it) into the run, on one
        of its hosts; start it with ``start_deployment``."""
        deployment = parse_deployment(obj, self.rendered.configmaps)
        if deployment.name in self.rendered.deployments:
            raise ValueError(f"a Deployment named {deployment.name!r} is in the run already")
        self._check_nodes([deployment.node])
        if deployment.node not in self.hosts:
            raise ValueError(f"{deployment.name} is pinned to {deployment.node}, which is not a host of this run")
        self.rendered.deployments[deployment.name] = deployment
        return deployment

    def update_configmap(self, obj: dict) -> list[str]:
        """A ConfigMap's new data, written into every volume made from it, as the kubelet updates a mounted
        ConfigMap: each file replaced whole (a reader sees the old or the new content, never half). Returns the
        files written."""
        key = (obj["metadata"].get("namespace", ""), obj["metadata"]["name"])
        self.rendered.configmaps[key] = obj
        written = []
        for dep in self.rendered.deployments.values():
            for volume_name, volume in dep.volumes.items():
                if dep.namespace != key[0] or (volume.get("configMap") or {}).get("name") != key[1]:
                    continue
                directory = os.path.join(self.run_dir, "volumes", dep.name, volume_name)
                if not os.path.isdir(directory):
                    continue  # not mounted yet: made with the new content when the Deployment starts
                for rel, content in configmap_files(obj, volume).items():
                    path = os.path.join(directory, rel)
                    with open(path + ".new", "wb") as handle:
                        handle.write(content)
                    os.replace(path + ".new", path)
                    written.append(path)
        return written

    def stop_deployment(self, name: str) -> list[SimProcess]:
        """Stop every process of a Deployment (SIGINT, SIGTERM, SIGKILL as at the end of a run) and drop it from
        the run; its CPU time stays counted in its host's cgroups."""
        processes = [p for p in self.processes.values() if p.deployment == name]
        stop_all(processes, self.stop_timeout)
        for process in processes:
            self.processes.pop(process.name, None)
            self.stopped.append(process)
        self.rendered.deployments.pop(name, None)
        return processes

    def start_deployment(self, name: str) -> list[SimProcess]:
        """Every container of a rendered Deployment on its node's host, exactly as rendered."""
        self._require_started()
        dep = self.rendered.deployments[name]
        if dep.replicas == 0:
            return []
        started = []
        for container in dep.containers:
            process_name = dep.name if len(dep.containers) == 1 else f"{dep.name}/{container.name}"
            env = self._resolved_env(dep, container)
            mounts = self._volumes(dep, container.name, container.mounts)
            os.makedirs(os.path.join(self.run_dir, "metrics"), exist_ok=True)
            env["KUBEROS_METRICS_FILE"] = metrics_file(self.run_dir, process_name)
            started.append(self._launch(process_name, dep.node, container.argv, env, mounts, "node", dep.name))
        return started

    def _wait_for_ports(self, processes: list[SimProcess]) -> None:
        """Wait until each discovery server binds its rendered UDP containerPort in its host namespace."""
        waiting = []
        for process in processes:
            dep = self.rendered.deployments[process.deployment]
            ports = [p for c in dep.containers for p in c.udp_ports]
            if ports:
                waiting.append((process, self.hosts[process.host].netns, ports))
        deadline = time.monotonic() + SERVER_READY_TIMEOUT
        while waiting and time.monotonic() < deadline:
            waiting = [(p, ns, ports) for p, ns, ports in waiting if p.running and not set(ports) <= _udp_ports(ns)]
            if any(not p.running for p, _, _ in waiting):
                break
            time.sleep(0.1)
        if waiting:
            raise ProcessExitedError("discovery servers did not bind their ports:\n" + "\n".join(p.tail() for p, _, _ in waiting))

    def _settle(self, processes: list[SimProcess]) -> None:
        deadline = time.monotonic() + self.settle_seconds
        while time.monotonic() < deadline and all(p.running for p in processes):
            time.sleep(0.1)
        exited = [p for p in processes if not p.running]
        if exited:
            raise ProcessExitedError(
                f"{len(exited)} process(es) exited right after start:\n" + "\n".join(p.tail() for p in exited)
            )

    # --- the run --------------------------------------------------------------------------------------

    def start(self, modules: bool = True, strict: bool = True) -> Runtime:
        """Hosts, fabric, discovery servers (waited for), then the module Deployments (unless ``modules`` is
        False: start them later with ``start_deployment``). ``strict``: raise ``ProcessExitedError`` when a
        process exits within ``settle_seconds``; otherwise see ``exited()``. Anything failing closes the run."""
        if self._started:
            raise RuntimeError("start() was called already")
        problem = environment_problem()
        if problem:
            raise RuntimeError(f"the simulator cannot run here: {problem}")
        self._started = True
        try:
            os.makedirs(os.path.join(self.run_dir, "logs"), exist_ok=True)
            self._plan_hosts()
            self._create_hosts()
            self._start_fabric()
            servers = [
                p for d in self.rendered.deployments.values() if d.is_discovery_server for p in self.start_deployment(d.name)
            ]
            self._wait_for_ports(servers)
            if modules:
                started = [
                    p
                    for d in self.rendered.deployments.values()
                    if not d.is_discovery_server
                    for p in self.start_deployment(d.name)
                ]
                if strict:
                    self._settle(servers + started)
        except BaseException:
            self.close()
            raise
        return self

    def _require_started(self) -> None:
        if not self._started or self._closed:
            raise RuntimeError("the runtime is not running; call start() first")

    def host_address(self, node: str) -> str:
        """The host's address on the fabric."""
        if node not in self.hosts:
            raise KeyError(f"{node!r} is not a host of this run; hosts: {', '.join(self.hosts) or 'none (not started)'}")
        return self.hosts[node].address

    def exited(self) -> list[SimProcess]:
        """Processes that are no longer running."""
        return [p for p in self.processes.values() if not p.running]

    def check(self) -> str | None:
        """None while every process runs; else which exited, with their log tails."""
        exited = self.exited()
        if not exited:
            return None
        return f"{len(exited)} process(es) exited:\n" + "\n".join(p.tail() for p in exited)

    def logs(self) -> list[str]:
        """Every process's log file, in start order."""
        return [p.log for p in [*self.stopped, *self.processes.values()]]

    def fleet_env(self, fleet: str | None = None) -> dict[str, str]:
        """The environment every ROS module Deployment of the fleet shares as rendered (ROS_DISCOVERY_SERVER,
        RMW_IMPLEMENTATION, ROS_DOMAIN_ID, KUBEROS_FLEET, ...), once started with the Services' addresses expanded
        as the kubelet expands them: for processes that join the fleet's ROS graph."""
        modules = [d for d in self.rendered.deployments.values() if not d.is_discovery_server]
        fleets = sorted({d.pod_labels.get(labels.FLEET, "") for d in modules})
        if fleet is None and len(fleets) != 1:
            raise ValueError(f"the rendered modules belong to fleets {fleets}; name one")
        chosen = fleet if fleet is not None else fleets[0]
        shared: dict[str, str] | None = None
        for dep in (d for d in modules if d.pod_labels.get(labels.FLEET, "") == chosen):
            links = self.rendered.service_links(dep.namespace, self.host_address) if self._started else {}
            for container in dep.containers:
                # an onboard module lists its robot's own discovery server too: the fleet's servers are shared
                raw = {e["name"]: e["value"] for e in container.env if "value" in e}
                if "ROS_DISCOVERY_SERVER" in raw:
                    raw["ROS_DISCOVERY_SERVER"] = manifests.fleet_discovery_part(raw["ROS_DISCOVERY_SERVER"])
                values = {name: manifests.expand_references(value, links) for name, value in raw.items()}
                shared = values if shared is None else {k: v for k, v in shared.items() if values.get(k) == v}
        if shared is None:
            raise ValueError(f"no rendered module belongs to fleet {chosen!r}; fleets: {fleets}")
        return shared

    def cpu_seconds(self) -> dict[tuple[str, str], float]:
        """(host, "node" | "hardware") -> CPU seconds used in that cgroup so far (cpuacct.usage), removed hosts
        included (what they used until they were removed); kept after close."""
        if self._final_cpu is not None:
            return dict(self._final_cpu)
        used: dict[tuple[str, str], float] = {}
        with self._hosts_lock:  # a host being removed is counted once: live or removed
            figures = [(r.host.node, r.cpu_seconds) for r in self.removed]
            figures += [(node, {kind: g.usage_seconds() for kind, g in h.cgroups.items()}) for node, h in self.hosts.items()]
        for node, seconds in figures:
            for kind, value in seconds.items():
                used[(node, kind)] = used.get((node, kind), 0.0) + value
        return used

    def fabric_cpu_seconds(self) -> float:
        """CPU seconds the fabric process used so far (it runs outside every cgroup of the run); kept after close."""
        if self._final_fabric_cpu is not None:
            return self._final_fabric_cpu
        if self.fabric is None:
            return 0.0
        return process_cpu_seconds(self.fabric.pid)

    def cpu_seconds_by_tier(self) -> dict[str, float]:
        """Tier (onboard, edge, cloud) -> CPU seconds in the node cgroups of its hosts, removed ones included
        (hardware left out)."""
        used_by_host = self.cpu_seconds()
        with self._hosts_lock:
            tiers = {r.host.node: r.host.tier for r in self.removed} | {node: h.tier for node, h in self.hosts.items()}
        totals: dict[str, float] = {}
        for (node, kind), used in used_by_host.items():
            if kind == "node":
                totals[tiers[node]] = totals.get(tiers[node], 0.0) + used
        return totals

    def fabric_stats(self) -> dict:
        """Packets, bytes and drops (by reason and per pair) of the fabric so far, written by it every second,
        plus ``tun_tx_dropped``: per host, packets the kernel dropped before the fabric read them (a host
        sending faster than the fabric reads overflows its TUN queue; a removed host's until it was). Final
        figures after close."""
        if self._final_fabric is not None:
            return self._final_fabric
        path = self._fabric_config.get("stats_file")
        try:
            with open(path or "", encoding="utf-8") as handle:
                stats = json.load(handle)
        except (OSError, ValueError):
            return {}
        with self._hosts_lock:
            removed, hosts = list(self.removed), list(self.hosts.values())
        dropped: dict[str, int] = {}
        for figures in removed:
            dropped[figures.host.node] = dropped.get(figures.host.node, 0) + figures.tun_tx_dropped
        for host in hosts:
            dropped[host.node] = dropped.get(host.node, 0) + _tun_tx_dropped(host.netns)
        stats["tun_tx_dropped"] = dropped
        return stats

    # --- teardown -------------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop every process, the fabric; remove namespaces, cgroups and /etc/netns dirs. Idempotent;
        SIGINT and SIGTERM wait until it is done. Problems are kept in ``close_problems``."""
        if self._closed:
            return
        self._closed = True
        blocked = _block_signals()
        try:
            self._teardown()
        finally:
            _unblock_signals(blocked)

    def _teardown(self) -> None:
        problems = self.close_problems
        stop_all(list(reversed(self.processes.values())), self.stop_timeout)
        if self.hosts or self.removed:
            self._final_cpu = self.cpu_seconds()
        if self.fabric is not None:
            self._final_fabric_cpu = self.fabric_cpu_seconds()
            if self.fabric.poll() is None:
                self.fabric.send_signal(signal.SIGTERM)
            try:
                self.fabric.wait(self.stop_timeout)
            except subprocess.TimeoutExpired:
                self.fabric.kill()
                self.fabric.wait(self.stop_timeout)
                problems.append("the fabric did not stop on SIGTERM; killed")
            self._final_fabric = self.fabric_stats()
        for host in self.hosts.values():
            problems.extend(self._remove_host_parts(host))
        for host in self._removed_hosts():
            if self._host_leftovers(host):  # its removal had problems: once more
                problems.extend(self._remove_host_parts(host))
        problems.extend(cgroups.remove_parent(self.cgroup_parent))
        if self._etc_netns_created:
            try:
                os.rmdir(netns.ETC_NETNS)
            except OSError:
                pass  # another run's namespaces have files there

    @staticmethod
    def _remove_host_parts(host: Host) -> list[str]:
        """Remove a host's cgroups (killing what is left in them), namespace and /etc/netns dir; problems as text."""
        problems = []
        for group in host.cgroups.values():
            problems.extend(group.remove())
        problems.extend(netns.delete_host(host.netns))
        return problems

    @staticmethod
    def _host_leftovers(host: Host) -> list[str]:
        """What of a host exists on the machine: its namespace, /etc/netns dir, cgroup dirs."""
        found = [f"netns {host.netns}"] if os.path.exists(f"/var/run/netns/{host.netns}") else []
        if os.path.exists(os.path.join(netns.ETC_NETNS, host.netns)):
            found.append(f"/etc/netns/{host.netns}")
        return found + [d for group in host.cgroups.values() for d in group.dirs if os.path.isdir(d)]

    def _removed_hosts(self) -> list[Host]:
        """Removed hosts whose node is not a host again (one added anew has the same names), each once."""
        return list({r.host.netns: r.host for r in self.removed if r.host.node not in self.hosts}.values())

    def leftovers(self) -> list[str]:
        """What of this run still exists on the machine (empty after a clean close), removed hosts included."""
        found = [f"netns {h.netns}" for h in self.hosts.values() if os.path.exists(f"/var/run/netns/{h.netns}")]
        found += [f"/etc/netns/{h.netns}" for h in self.hosts.values() if os.path.exists(os.path.join(netns.ETC_NETNS, h.netns))]
        found += [item for host in self._removed_hosts() for item in self._host_leftovers(host)]
        found += [
            os.path.join(root, self.cgroup_parent)
            for root in (cgroups.CPU_ROOT, cgroups.CPUACCT_ROOT)
            if os.path.exists(os.path.join(root, self.cgroup_parent))
        ]
        found += [f"pid {p.pid} ({p.name})" for p in [*self.stopped, *self.processes.values()] if p.running]
        if self.fabric is not None and self.fabric.poll() is None:
            found.append(f"fabric pid {self.fabric.pid}")
        return found

    def __enter__(self) -> Runtime:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def process_cpu_seconds(pid: int) -> float:
    """User and system CPU seconds of a running process (/proc/<pid>/stat); 0 when it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def machine_cpu_seconds() -> dict[str, float]:
    """Since boot, over all cores (/proc/stat): ``busy``, CPU seconds this machine's processes and kernel ran
    (not idle, iowait or steal), and ``steal``, seconds a hypervisor gave this VM's cores to others."""
    try:
        with open("/proc/stat", encoding="utf-8") as handle:
            values = [int(v) for v in handle.readline().split()[1:]]
    except (OSError, ValueError):
        return {"busy": 0.0, "steal": 0.0}
    user, nice, system, _idle, _iowait, irq, softirq, steal = (values + [0] * 8)[:8]
    tick = os.sysconf("SC_CLK_TCK")
    return {"busy": (user + nice + system + irq + softirq) / tick, "steal": steal / tick}


def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as handle:
            return handle.read()
    except OSError:
        return ""


def _tun_tx_dropped(namespace: str) -> int:
    """Packets the host's TUN dropped on its way to the fabric (its queue full); 0 when unknown."""
    done = netns.run("ip", "-j", "-s", "-n", namespace, "link", "show", netns.TUN, check=False, timeout=10)
    try:
        return int(json.loads(done.stdout)[0]["stats64"]["tx"]["dropped"])
    except (ValueError, LookupError, TypeError):
        return 0


def _udp_ports(namespace: str) -> set[int]:
    """UDP ports bound in a network namespace (/proc/net/udp as seen from inside it)."""
    done = netns.run("ip", "netns", "exec", namespace, "cat", "/proc/net/udp", check=False, timeout=10)
    ports = set()
    for line in done.stdout.splitlines()[1:]:
        fields = line.split()
        if len(fields) > 1 and ":" in fields[1]:
            ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def _block_signals() -> set | None:
    try:
        return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    except (ValueError, OSError):
        return None


def _unblock_signals(previous: set | None) -> None:
    if previous is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
