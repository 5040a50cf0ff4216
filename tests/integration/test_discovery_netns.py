"""The rendered Fast DDS discovery configuration, proven with real processes in network namespaces.

listing1 is rendered with the project's own code, and what it renders is used unchanged: each discovery
server Deployment's container command (`fast-discovery-server -i <id> -l 0.0.0.0 -p 11811`, the program
from the ros-fastrtps wheel) runs in a network namespace of its own, and rclpy talker and listener
processes run in others with a module container's environment (ROS_DISCOVERY_SERVER, RMW_IMPLEMENTATION,
ROS_DOMAIN_ID, ...). /etc/netns/<ns>/hosts resolves the servers' cluster DNS names to the namespaces'
addresses, and every process gets a private /dev/shm, as pods on different nodes would, so that all
traffic crosses the bridge.

The bridge joining the namespaces floods no multicast (multicast snooping off, mcast_flood off on every
port), so participants can meet only through the discovery servers. The negative control shows it: without
ROS_DISCOVERY_SERVER a talker and a listener never meet, and the same two processes meet as soon as the
bridge floods multicast again.

Needs root and `ip netns` (skipped otherwise) and requirements-ros.txt installed in the venv (fails
otherwise). Traffic stays between the namespaces this module creates; every wait is bounded.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field

import pytest
from helpers import ROOT
from sshlab import run

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests, scheduler, spec
from ansible_collections.kuberos.platform.plugins.module_utils.ros_wheels import PRIVATE_SHM, ros_environment, ros_problem

pytestmark = pytest.mark.ros

HERE = os.path.dirname(os.path.abspath(__file__))
TALKER = os.path.join(HERE, "ros", "talker.py")
LISTENER = os.path.join(HERE, "ros", "listener.py")
SUBNET = "10.213.7"  # a /24 that exists only inside the namespaces and on the bridge this module creates
TOPIC = "/kuberos_chatter"
STARTUP_TIMEOUT = 20.0  # a process printing that it is up
DISCOVERY_TIMEOUT = 30.0  # a listener receiving its first message
NEGATIVE_WINDOW = 8.0  # simple discovery gets this long to fail; with multicast it succeeds in under a second
STOP_TIMEOUT = 5.0


# --- ROS 2 from PyPI wheels (plugins/module_utils/ros_wheels.py) ------------------------------------------


def require_ros() -> None:
    problem = ros_problem()
    if problem:
        pytest.fail(
            f"rclpy with Fast DDS is not usable from {sys.prefix}; install the ROS 2 wheels with "
            f"`{sys.prefix}/bin/pip install -r requirements-ros.txt`.\n{problem}",
            pytrace=False,
        )


# --- what the project renders -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Rendered:
    servers: dict[str, list[str]]  # discovery server Deployment name -> its container command
    addresses: dict[str, str]  # host name in ROS_DISCOVERY_SERVER -> the discovery server Deployment it names
    module_env: dict[str, dict[str, str]]  # module Deployment name -> its container's environment


def container_env(deployment: dict) -> dict[str, str]:
    """A container's environment; entries set by the kubelet (valueFrom, e.g. KUBEROS_NODE_NAME) are left out."""
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    return {e["name"]: e["value"] for e in container.get("env", []) if "value" in e}


@pytest.fixture(scope="module")
def rendered(local_inventory) -> Rendered:
    options = manifests.RenderOptions()
    deployments = spec.load_rosdeployment_file(os.path.join(ROOT, "examples", "listing1.yml"), "examples/listing1.yml")
    placement = scheduler.place_modules(deployments, local_inventory)
    objects = manifests.render_deployment(deployments, placement, options)
    by_component: dict[str, list[dict]] = {}
    for obj in objects:
        if obj["kind"] == "Deployment":
            by_component.setdefault(obj["metadata"]["labels"][manifests.COMPONENT], []).append(obj)
    servers = {
        d["metadata"]["name"]: d["spec"]["template"]["spec"]["containers"][0]["command"] for d in by_component["discovery-server"]
    }
    dns_names = {
        f"{d['metadata']['name']}.{d['metadata']['namespace']}.svc.{options.cluster_domain}": d["metadata"]["name"]
        for d in by_component["discovery-server"]
    }
    module_env = {d["metadata"]["name"]: container_env(d) for d in by_component["ros-module"]}
    values = {env["ROS_DISCOVERY_SERVER"] for env in module_env.values()}
    assert len(values) == 1, f"modules of one fleet disagree on ROS_DISCOVERY_SERVER: {values}"
    assert all(env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp" for env in module_env.values())
    addresses = {}
    for slot in values.pop().split(";"):
        host, _port = slot.rsplit(":", 1)
        assert host in dns_names, f"{host} in ROS_DISCOVERY_SERVER names no discovery server Deployment ({sorted(dns_names)})"
        addresses[host] = dns_names[host]
    assert len(servers) == 2 and set(addresses.values()) == set(servers), (servers, addresses)
    return Rendered(servers=servers, addresses=addresses, module_env=module_env)


def module_env(rendered: Rendered, module: str, robot: str) -> dict[str, str]:
    (name,) = [n for n, env in rendered.module_env.items() if n.endswith(f"-{module}-{robot}")]
    return rendered.module_env[name]


# --- network namespaces -----------------------------------------------------------------------------------


@dataclass
class Lab:
    """Namespaces kr-<role>-<suffix> with an eth0 each, on one bridge that floods no multicast."""

    suffix: str = field(default_factory=lambda: secrets.token_hex(2))
    namespaces: dict[str, str] = field(default_factory=dict)  # role -> namespace
    addresses: dict[str, str] = field(default_factory=dict)  # role -> IPv4 address
    ports: list[str] = field(default_factory=list)  # the bridge's ports (host ends of the veth pairs)
    etc_netns_created: bool = False

    @property
    def bridge(self) -> str:
        return f"krbr{self.suffix}"

    def create_bridge(self) -> None:
        # Without snooping the bridge floods multicast, to the ports that allow it: none (see add()).
        run("ip", "link", "add", self.bridge, "type", "bridge", "mcast_snooping", "0")
        run("ip", "link", "set", self.bridge, "up")

    def add(self, role: str) -> str:
        index = len(self.namespaces)
        namespace, port, address = f"kr-{role}-{self.suffix}", f"krv{self.suffix}{index}", f"{SUBNET}.{10 + index}"
        run("ip", "netns", "add", namespace)
        self.namespaces[role] = namespace
        run("ip", "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", namespace)
        self.ports.append(port)
        run("ip", "link", "set", port, "master", self.bridge, "up")
        run("bridge", "link", "set", "dev", port, "mcast_flood", "off")
        run("ip", "-n", namespace, "addr", "add", f"{address}/24", "dev", "eth0")
        run("ip", "-n", namespace, "link", "set", "eth0", "up")
        run("ip", "-n", namespace, "link", "set", "lo", "up")
        self.addresses[role] = address
        return namespace

    def set_multicast_flood(self, on: bool) -> None:
        for port in self.ports:
            run("bridge", "link", "set", "dev", port, "mcast_flood", "on" if on else "off")

    def write_hosts(self, names: dict[str, str]) -> None:
        """/etc/netns/<ns>/hosts, which `ip netns exec` bind-mounts over /etc/hosts: host name -> address."""
        if not os.path.isdir("/etc/netns"):
            os.makedirs("/etc/netns")
            self.etc_netns_created = True
        lines = ["127.0.0.1 localhost", "::1 localhost", *(f"{address} {name}" for name, address in names.items())]
        for namespace in self.namespaces.values():
            os.makedirs(f"/etc/netns/{namespace}", exist_ok=True)
            with open(f"/etc/netns/{namespace}/hosts", "w", encoding="utf-8") as handle:
                handle.write("\n".join(lines) + "\n")

    def close(self) -> None:
        for namespace in self.namespaces.values():
            run("ip", "netns", "delete", namespace, check=False)  # also removes both ends of its veth pair
            shutil.rmtree(f"/etc/netns/{namespace}", ignore_errors=True)
        run("ip", "link", "delete", self.bridge, check=False)
        if self.etc_netns_created:
            try:
                os.rmdir("/etc/netns")
            except OSError:
                pass  # something else put a namespace's files there meanwhile


def open_lab(request, first: str) -> Lab:
    """A Lab with its bridge and a first namespace, closed at the end; skips where namespaces cannot be made."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if not shutil.which("ip") or not shutil.which("bridge") or run("ip", "netns", "list", check=False).returncode != 0:
        pytest.skip("`ip netns` (iproute2) is not available")
    lab = Lab()
    request.addfinalizer(lab.close)
    try:
        lab.create_bridge()
        lab.add(first)
    except RuntimeError as error:
        pytest.skip(f"`ip netns` is not usable here: {error}")
    return lab


@pytest.fixture(scope="module")
def lab(request, rendered) -> Lab:
    lab = open_lab(request, "ds0")
    for role in ("ds1", "talk", "listen", "late"):
        lab.add(role)
    # ROS_DISCOVERY_SERVER's names resolve to the namespaces running the Deployments they name.
    lab.write_hosts({host: lab.addresses[server_role(rendered, server)] for host, server in rendered.addresses.items()})
    return lab


def server_role(rendered: Rendered, server: str) -> str:
    return f"ds{sorted(rendered.servers).index(server)}"


# --- processes --------------------------------------------------------------------------------------------


@dataclass
class Process:
    name: str
    popen: subprocess.Popen
    log: str

    def output(self) -> str:
        with open(self.log, encoding="utf-8", errors="replace") as handle:
            return handle.read()

    def received(self) -> list[int]:
        return [int(n) for n in re.findall(r"^received kuberos (\d+)$", self.output(), re.MULTILINE)]

    def published(self) -> list[int]:
        return [int(n) for n in re.findall(r"^published kuberos (\d+) subscribers=\d+$", self.output(), re.MULTILINE)]

    def subscribers(self) -> int | None:
        counts = re.findall(r"^published kuberos \d+ subscribers=(\d+)$", self.output(), re.MULTILINE)
        return int(counts[-1]) if counts else None

    def tail(self, lines: int = 15) -> str:
        return f"--- {self.name} (exit {self.popen.poll()}) ---\n" + "\n".join(self.output().splitlines()[-lines:])

    def kill(self, sig: int = signal.SIGTERM) -> None:
        if self.popen.poll() is None:
            os.killpg(self.popen.pid, sig)  # its own session: the process started here, and nothing else
        try:
            self.popen.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait(STOP_TIMEOUT)


class Processes:
    def __init__(self, lab: Lab, directory: str):
        self.lab, self.directory, self.started = lab, directory, []
        self.base_env = ros_environment(log_dir=os.path.join(directory, "ros-log"))

    def start(self, name: str, role: str, command: list[str], env: dict[str, str] | None = None) -> Process:
        """Run command in the role's namespace with a private /dev/shm and the ROS environment plus env."""
        log = os.path.join(self.directory, f"{name}.log")
        with open(log, "wb") as out:
            popen = subprocess.Popen(
                [shutil.which("ip"), "netns", "exec", self.lab.namespaces[role], "sh", "-c", PRIVATE_SHM, "sh", *command],
                env={**self.base_env, **(env or {})},
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        process = Process(name, popen, log)
        self.started.append(process)
        return process

    def tails(self) -> str:
        return "\n".join(p.tail() for p in self.started)

    def wait_until(self, condition, timeout: float, what: str) -> float:
        """Seconds until condition() held; fails with every process's last lines after timeout seconds."""
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            if condition():
                return time.monotonic() - start
            time.sleep(0.2)
        pytest.fail(f"{what}: not within {timeout:.0f} s\n{self.tails()}", pytrace=False)

    def close(self) -> None:
        for process in reversed(self.started):
            process.kill()


@pytest.fixture
def procs(lab, tmp_path):
    processes = Processes(lab, str(tmp_path))
    yield processes
    processes.close()


def start_servers(procs: Processes, rendered: Rendered) -> dict[str, Process]:
    """Each discovery server Deployment's command, exactly as rendered, in its own namespace."""
    servers = {}
    for name, command in sorted(rendered.servers.items()):
        servers[name] = procs.start(name, server_role(rendered, name), command)
    for name, process in servers.items():
        server_id = rendered.servers[name][rendered.servers[name].index("-i") + 1]
        procs.wait_until(
            lambda p=process, i=server_id: re.search(rf"Server ID:\s+{i}\b", p.output()) is not None,
            STARTUP_TIMEOUT,
            f"{name} did not report itself running as server {server_id}",
        )
    return servers


def start_talker(procs: Processes, name: str, role: str, env: dict[str, str]) -> Process:
    talker = procs.start(name, role, [sys.executable, TALKER, TOPIC], env)
    procs.wait_until(lambda: len(talker.published()) >= 2, STARTUP_TIMEOUT, f"{name} did not start publishing")
    return talker


def start_listener(procs: Processes, name: str, role: str, env: dict[str, str]) -> Process:
    listener = procs.start(name, role, [sys.executable, LISTENER, TOPIC], env)
    procs.wait_until(lambda: "ready" in listener.output().split(), STARTUP_TIMEOUT, f"{name} did not subscribe")
    return listener


# --- tests ------------------------------------------------------------------------------------------------


def test_negative_control_without_ros_discovery_server_modules_never_meet(procs, lab, rendered):
    """Multicast is really blocked: simple discovery fails, and succeeds once the bridge floods multicast."""
    require_ros()
    simple = {k: v for k, v in module_env(rendered, "fetch-controller-foxy", "fetch-1").items() if k != "ROS_DISCOVERY_SERVER"}
    talker = start_talker(procs, "talker-simple", "talk", simple)
    simple = {k: v for k, v in module_env(rendered, "fetch-motion-planner", "fetch-1").items() if k != "ROS_DISCOVERY_SERVER"}
    listener = start_listener(procs, "listener-simple", "listen", simple)
    deadline = time.monotonic() + NEGATIVE_WINDOW
    while time.monotonic() < deadline:
        assert not listener.received(), f"found each other without a discovery server\n{procs.tails()}"
        time.sleep(0.2)
    assert talker.subscribers() == 0 and talker.popen.poll() is None and listener.popen.poll() is None, procs.tails()
    # The control's control: the same two processes meet as soon as multicast crosses the bridge again.
    lab.set_multicast_flood(True)
    try:
        seconds = procs.wait_until(lambda: listener.received(), DISCOVERY_TIMEOUT, "simple discovery failed even with multicast")
    finally:
        lab.set_multicast_flood(False)
    print(f"no discovery in {NEGATIVE_WINDOW:.0f} s without multicast; with multicast, the first message after {seconds:.1f} s")


def test_modules_meet_through_the_rendered_discovery_servers(procs, rendered):
    require_ros()
    start_servers(procs, rendered)
    talker = start_talker(procs, "talker", "talk", module_env(rendered, "fetch-controller-foxy", "fetch-1"))
    listener = start_listener(procs, "listener", "listen", module_env(rendered, "fetch-motion-planner", "fetch-1"))
    seconds = procs.wait_until(lambda: len(listener.received()) >= 3, DISCOVERY_TIMEOUT, "listener got no messages")
    assert talker.subscribers() == 1, procs.tails()
    print(f"listener received 3 messages {seconds:.1f} s after subscribing")


def test_a_new_listener_meets_the_talker_through_server_1_after_server_0_is_killed(procs, rendered):
    require_ros()
    servers = start_servers(procs, rendered)
    first, second = sorted(servers)
    start_talker(procs, "talker", "talk", module_env(rendered, "fetch-controller-foxy", "fetch-1"))
    listener = start_listener(procs, "listener", "listen", module_env(rendered, "fetch-motion-planner", "fetch-1"))
    procs.wait_until(lambda: listener.received(), DISCOVERY_TIMEOUT, "listener got no messages with both servers up")

    servers[first].kill(signal.SIGKILL)
    assert servers[first].popen.returncode is not None and servers[second].popen.poll() is None
    before = len(listener.received())
    late = start_listener(procs, "listener-late", "late", module_env(rendered, "fetch-motion-planner", "fetch-2"))
    seconds = procs.wait_until(lambda: late.received(), DISCOVERY_TIMEOUT, f"a new listener got no messages without {first}")
    procs.wait_until(lambda: len(listener.received()) > before, DISCOVERY_TIMEOUT, "the first listener stopped receiving")
    assert servers[second].popen.poll() is None, procs.tails()
    print(f"new listener received its first message {seconds:.1f} s after subscribing, with only {second} up")
