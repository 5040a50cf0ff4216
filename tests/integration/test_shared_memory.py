"""Fast DDS shared memory between pods, proven with real processes: fastdds.TRANSPORT_ENV never loses a message.

Pods are modelled as Kubernetes runs them: a pod is a sandbox process in a network namespace of its own with a /dev/shm
of its own (tmpfs, `PRIVATE_SHM`); its containers join the sandbox's network and mount namespaces (nsenter), so the
containers of one pod share its /dev/shm and addresses. A hostNetwork pod is a sandbox in a network namespace that
another sandbox uses too. The discovery server Deployment's argv (its args) and a module container's environment are the
rendered ones (examples/listing1.yml), ROS_DISCOVERY_SERVER pointing at the one server started here.

A talker (50 Hz, reliable) and a listener (tests/integration/ros) meet through the server; once the talker counts the
listener, the next N messages must all arrive. Layouts: A two pods; A' two pods whose addresses give the same Fast DDS
host id (fastdds.host_id); B two hostNetwork pods; C two containers of one pod. With fastdds.TRANSPORT_ENV every layout
delivers all N and no Fast DDS file appears in any /dev/shm. The control, default transports, shows what the setting
avoids: in A' and B the talker counts the listener and not one message arrives (deterministic; fastdds.py has the
numbers).

Needs root, `ip netns` and nsenter (skipped otherwise) and requirements-ros.txt in the venv (fails otherwise). Traffic
stays on the bridge and namespaces this module creates; every wait is bounded.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import sys
import time
from dataclasses import dataclass

import pytest
from helpers import ROOT
from netlab import Process, spawn
from sshlab import run

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import fastdds, labels, manifests, naming, scheduler, spec
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import (
    PRIVATE_SHM,
    ros_environment,
    ros_problem,
)

pytestmark = pytest.mark.ros

HERE = os.path.dirname(os.path.abspath(__file__))
TALKER = os.path.join(HERE, "ros", "talker.py")
LISTENER = os.path.join(HERE, "ros", "listener.py")
SUBNET = "10.213.9"  # a /24 that exists only inside the namespaces and on the bridge this module creates
TOPIC = "/kuberos_shm"
N = 100
PERIOD = "0.02"  # the talker's: N messages in 2 s
SLACK = 150  # messages published after the N before the listener's count is final (3 s)
STARTUP_TIMEOUT = 20.0
MATCH_TIMEOUT = 20.0  # the talker counting the listener; 1.2-1.4 s measured
DELIVERY_TIMEOUT = 30.0  # the N messages and the slack being published
STOP_TIMEOUT = 5.0
SANDBOX_SECONDS = "600"  # a sandbox outlives its test, and is killed with it


def colliding_pair(candidates: list[str], taken: set[int]) -> tuple[str, str]:
    """The first two addresses with the same host id, neither sharing it with a taken one."""
    seen: dict[int, str] = {}
    for address in candidates:
        host = fastdds.host_id([address])
        if host in seen and host not in taken:
            return seen[host], address
        seen.setdefault(host, address)
    raise AssertionError(f"no two addresses of {SUBNET}.0/24 share a host id")


SERVER, POD1, POD2 = f"{SUBNET}.10", f"{SUBNET}.11", f"{SUBNET}.12"
SAME_ID = colliding_pair([f"{SUBNET}.{n}" for n in range(20, 255)], {fastdds.host_id([a]) for a in (SERVER, POD1, POD2)})
ADDRESSES = {"server": SERVER, "pod1": POD1, "pod2": POD2, "same1": SAME_ID[0], "same2": SAME_ID[1]}
# layout -> (talker's network namespace, listener's, whether the listener is a container of the talker's pod)
LAYOUTS = {
    "A-two-pods": ("pod1", "pod2", False),
    "A'-two-pods-same-host-id": ("same1", "same2", False),
    "B-host-network-pods": ("pod1", "pod1", False),
    "C-containers-of-one-pod": ("pod1", "pod1", True),
}


# --- what the project renders -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Rendered:
    server: list[str]  # discovery server 0's container args (its argv: the wheels' program is on PATH here)
    server_env: dict[str, str]  # its container's environment (the Fast DDS profile it serves with)
    module_env: dict[str, str]  # a module container's environment, ROS_DISCOVERY_SERVER naming only server 0 here


@pytest.fixture(scope="module")
def rendered(local_inventory) -> Rendered:
    deployments = spec.load_rosdeployment_file(os.path.join(ROOT, "examples", "listing1.yml"), "examples/listing1.yml")
    objects = manifests.render_deployment(
        deployments, scheduler.place_modules(deployments, local_inventory), manifests.RenderOptions()
    )
    by_component: dict[str, list[dict]] = {}
    for obj in objects:
        if obj["kind"] == "Deployment":
            by_component.setdefault(obj["metadata"]["labels"][labels.COMPONENT], []).append(obj)
    (server,) = [d for d in by_component["discovery-server"] if d["metadata"]["labels"][labels.DISCOVERY_ID] == "0"]
    server_container = server["spec"]["template"]["spec"]["containers"][0]
    command = server_container["args"]  # the image's entrypoint runs it: here, PATH
    link = {naming.service_host_variable(server["metadata"]["name"]): SERVER}  # its Service's address: its own here
    server_env = {e["name"]: manifests.expand_references(e["value"], link) for e in server_container["env"]}
    container = by_component["ros-module"][0]["spec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e["value"] for e in container["env"] if "value" in e}
    port = command[command.index("-p") + 1]
    return Rendered(server=command, server_env=server_env, module_env={**env, "ROS_DISCOVERY_SERVER": f"{SERVER}:{port}"})


def with_transport_env(env: dict[str, str]) -> dict[str, str]:
    return {**env, **dict(fastdds.TRANSPORT_ENV)}


def without_transport_env(env: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k not in dict(fastdds.TRANSPORT_ENV)}


# --- network namespaces on one bridge ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def namespaces(request) -> dict[str, str]:
    """role -> namespace, each with an eth0 on one bridge (ADDRESSES)."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if not (shutil.which("ip") and shutil.which("nsenter")) or run("ip", "netns", "list", check=False).returncode != 0:
        pytest.skip("`ip netns` (iproute2) or nsenter is not available")
    suffix = secrets.token_hex(2)
    bridge, created = f"krsb{suffix}", {}

    def close():
        for namespace in created.values():
            run("ip", "netns", "delete", namespace, check=False)  # also removes both ends of its veth pair
        run("ip", "link", "delete", bridge, check=False)

    request.addfinalizer(close)
    try:
        run("ip", "link", "add", bridge, "type", "bridge")
        run("ip", "link", "set", bridge, "up")
        for index, (role, address) in enumerate(ADDRESSES.items()):
            namespace, port = f"krs-{role}-{suffix}", f"krs{suffix}{index}"
            run("ip", "netns", "add", namespace)
            created[role] = namespace
            run("ip", "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", namespace)
            run("ip", "link", "set", port, "master", bridge, "up")
            run("ip", "-n", namespace, "addr", "add", f"{address}/24", "dev", "eth0")
            run("ip", "-n", namespace, "link", "set", "eth0", "up")
            run("ip", "-n", namespace, "link", "set", "lo", "up")
    except RuntimeError as error:
        pytest.skip(f"`ip netns` is not usable here: {error}")
    return created


# --- pods and containers ----------------------------------------------------------------------------------


class Pods:
    def __init__(self, namespaces: dict[str, str], directory: str):
        self.namespaces, self.directory, self.started = namespaces, directory, []
        self.env = ros_environment(log_dir=os.path.join(directory, "ros-log"))

    def _popen(self, name: str, command: list[str], env: dict[str, str]) -> Process:
        process = spawn(name, command, {**self.env, **env}, self.directory)
        self.started.append(process)
        return process

    def pod(self, name: str, role: str) -> int:
        """A sandbox in the role's network namespace with a /dev/shm of its own; its pid."""
        sandbox = self._popen(
            name, ["ip", "netns", "exec", self.namespaces[role], "sh", "-c", PRIVATE_SHM, "sh", "sleep", SANDBOX_SECONDS], {}
        )
        self.wait_until(lambda: self.has_private_shm(sandbox.popen.pid), STARTUP_TIMEOUT, f"{name} did not mount its /dev/shm")
        return sandbox.popen.pid

    @staticmethod
    def has_private_shm(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/mountinfo", encoding="utf-8") as handle:
                return any(line.split()[4] == "/dev/shm" and "kuberos-shm" in line for line in handle)
        except OSError:
            return False

    def container(self, name: str, pod: int, command: list[str], env: dict[str, str]) -> Process:
        """command in the pod's network and mount namespaces (its addresses and its /dev/shm)."""
        return self._popen(name, ["nsenter", f"--net=/proc/{pod}/ns/net", f"--mount=/proc/{pod}/ns/mnt", "--", *command], env)

    @staticmethod
    def fastdds_files(pod: int) -> list[str]:
        return sorted(f for f in os.listdir(f"/proc/{pod}/root/dev/shm") if "fastrtps" in f)

    def tails(self) -> str:
        return "\n".join(
            f"--- {p.name} (exit {p.popen.poll()}) ---\n" + "\n".join(p.output().splitlines()[-8:]) for p in self.started
        )

    def wait_until(self, condition, timeout: float, what: str) -> float:
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
def pods(namespaces, tmp_path):
    problem = ros_problem()
    if problem:
        pytest.fail(
            f"rclpy with Fast DDS is not usable from {sys.prefix}: `pip install -r requirements-ros.txt`.\n{problem}",
            pytrace=False,
        )
    started = Pods(namespaces, str(tmp_path))
    yield started
    started.close()


@dataclass
class Exchange:
    matched_after: float  # seconds from the talker's start until it counted the listener
    received: int  # of the N messages published after that
    published: int  # messages the talker published in all
    shm_files: dict[str, list[str]]  # pod -> Fast DDS files in its /dev/shm


def exchange(pods: Pods, rendered: Rendered, layout: str, env: dict[str, str]) -> Exchange:
    """The discovery server, then a listener and a talker placed as the layout says, all with env; N messages."""
    talker_role, listener_role, one_pod = LAYOUTS[layout]
    server = pods.container("discovery-server", pods.pod("server-pod", "server"), rendered.server, {**env, **rendered.server_env})
    pods.wait_until(
        lambda: re.search(r"Server ID:\s+0\b", server.output()), STARTUP_TIMEOUT, "the discovery server did not start"
    )
    talker_pod = pods.pod("talker-pod", talker_role)
    listener_pod = talker_pod if one_pod else pods.pod("listener-pod", listener_role)
    listener = pods.container("listener", listener_pod, [sys.executable, LISTENER, TOPIC], env)
    pods.wait_until(lambda: "ready" in listener.output().split(), STARTUP_TIMEOUT, "the listener did not subscribe")
    talker = pods.container("talker", talker_pod, [sys.executable, TALKER, TOPIC, PERIOD], env)
    matched_after = pods.wait_until(
        lambda: talker.numbers(r"^published kuberos (\d+) subscribers=[1-9]\d*$"),
        MATCH_TIMEOUT,
        "the talker never counted the listener",
    )
    first = talker.numbers(r"^published kuberos (\d+) subscribers=[1-9]\d*$")[0] + 1  # published once the match was known
    wanted = set(range(first, first + N))

    def settled() -> bool:
        received = set(listener.numbers(r"^received kuberos (\d+)$"))
        published = talker.numbers(r"^published kuberos (\d+) ")
        return wanted <= received or (bool(published) and published[-1] >= first + N + SLACK)

    pods.wait_until(settled, DELIVERY_TIMEOUT, "the talker stopped publishing")
    assert talker.popen.poll() is None and listener.popen.poll() is None, pods.tails()
    pod_names = {"talker's pod": talker_pod, "listener's pod": listener_pod}
    return Exchange(
        matched_after=matched_after,
        received=len(wanted & set(listener.numbers(r"^received kuberos (\d+)$"))),
        published=len(talker.numbers(r"^published kuberos (\d+) ")),
        shm_files={name: pods.fastdds_files(pid) for name, pid in pod_names.items()},
    )


# --- tests ------------------------------------------------------------------------------------------------


def test_the_collision_is_real():
    """A' uses two addresses that Fast DDS gives one host id, and A's and the server's are all different."""
    assert fastdds.host_id(["10.214.9.77"]) == 2841  # read from a real participant's GUID (bytes 2-3) at that address
    ids = {role: fastdds.host_id([address]) for role, address in ADDRESSES.items()}
    assert ids["same1"] == ids["same2"] and len({ids["server"], ids["pod1"], ids["pod2"], ids["same1"]}) == 4, ids


@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_transport_env_delivers_every_message_and_uses_no_shared_memory(pods, rendered, layout):
    result = exchange(pods, rendered, layout, with_transport_env(rendered.module_env))
    assert result.received == N, f"{result}\n{pods.tails()}"
    assert not any(result.shm_files.values()), f"Fast DDS used /dev/shm despite {fastdds.TRANSPORT_ENV}: {result.shm_files}"
    print(f"{layout}, {fastdds.TRANSPORT_ENV}: matched after {result.matched_after:.1f} s, {result.received} of {N} received")


@pytest.mark.parametrize("layout", ["A'-two-pods-same-host-id", "B-host-network-pods"])
def test_control_default_transports_match_and_lose_every_message(pods, rendered, layout):
    """What the setting avoids: the talker counts the listener, publishes on, and nothing arrives, nothing is logged."""
    result = exchange(pods, rendered, layout, without_transport_env(rendered.module_env))
    assert result.received == 0 and result.published >= N + SLACK, f"{result}\n{pods.tails()}"
    assert all(result.shm_files.values()), f"default transports created no Fast DDS files in /dev/shm: {result.shm_files}"
    print(
        f"{layout}, default transports: matched after {result.matched_after:.1f} s, "
        f"0 of {N} received ({result.published} published)"
    )
