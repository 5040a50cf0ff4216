"""Network namespaces on a bridge that floods no multicast, and the processes the DDS tests run in them.

Shared by the discovery tests (tests/integration/test_discovery_netns.py: Fast DDS with discovery servers,
test_cyclonedds_netns.py: Cyclone DDS with unicast peer lists), test_bridge.py and bench/bench_bridge.py.

- `Lab`: namespaces kr-<role>-<suffix>, each with an eth0 on one bridge whose ports flood no multicast
  (snooping off, mcast_flood off), so participants meet only by unicast; /etc/netns/<ns>/hosts stands in
  for cluster DNS (`ip netns exec` bind-mounts it over /etc/hosts).
- `Processes`: programs started in a role's namespace, each in a session of its own, with a private
  /dev/shm (as pods on different nodes have), logged to a file; every wait is bounded.
- `Process`: one of them, and what it printed. The talkers and listeners of these tests (ros/talker.py,
  ros/listener.py, ros/cyclone_chatter.py) print the same lines: "published kuberos N subscribers=K" and
  "received kuberos N".

Traffic stays inside the namespaces a Lab creates: the bridge has no address and no uplink.
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
from sshlab import run

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import PRIVATE_SHM, ros_environment

ROS_PROGRAMS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "integration", "ros")
TALKER, LISTENER = os.path.join(ROS_PROGRAMS, "talker.py"), os.path.join(ROS_PROGRAMS, "listener.py")
CHATTER = "/kuberos_chatter"
STARTUP_TIMEOUT = 20.0  # a process printing that it is up
SUBNET = "10.213.7"  # a /24 that exists only inside the namespaces and on the bridge a Lab creates
STOP_TIMEOUT = 5.0


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

    def set_connected(self, role: str, on: bool) -> None:
        """Cut a namespace off the bridge (its port down: every packet to and from it dropped), or connect it again,
        as a robot's wireless link drops and comes back. Its processes keep running."""
        port = self.ports[list(self.namespaces).index(role)]
        run("ip", "link", "set", port, "up" if on else "down")

    def set_multicast_flood(self, on: bool) -> None:
        for port in self.ports:
            run("bridge", "link", "set", "dev", port, "mcast_flood", "on" if on else "off")

    def write_hosts(self, names: dict[str, str]) -> None:
        """/etc/netns/<ns>/hosts, which `ip netns exec` bind-mounts over /etc/hosts: host name -> address.

        Rewritten in place, so that processes already running see the new file, as they would a DNS change.
        """
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


@dataclass
class Process:
    name: str
    popen: subprocess.Popen
    log: str

    def output(self) -> str:
        with open(self.log, encoding="utf-8", errors="replace") as handle:
            return handle.read()

    def numbers(self, pattern: str) -> list[int]:
        """The integers the first group of ``pattern`` (a multi-line regex) captures in the output."""
        return [int(n) for n in re.findall(pattern, self.output(), re.MULTILINE)]

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


def spawn(name: str, command: list[str], env: dict[str, str], directory: str, cwd: str | None = None) -> Process:
    """``command`` in a session of its own (so that killing its group kills nothing else), output to <name>.log
    (appended: a process started again under its name, as a restarted container, keeps one log)."""
    log = os.path.join(directory, f"{name}.log")
    with open(log, "ab") as out:
        popen = subprocess.Popen(
            command, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, cwd=cwd
        )
    return Process(name, popen, log)


class Processes:
    def __init__(self, lab: Lab, directory: str):
        self.lab, self.directory, self.started = lab, directory, []
        self.base_env = ros_environment(log_dir=os.path.join(directory, "ros-log"))

    def start(
        self, name: str, role: str, command: list[str], env: dict[str, str] | None = None, cwd: str | None = None
    ) -> Process:
        """Run command in the role's namespace with a private /dev/shm and the venv's environment plus env."""
        wrapped = [shutil.which("ip"), "netns", "exec", self.lab.namespaces[role], "sh", "-c", PRIVATE_SHM, "sh", *command]
        process = spawn(name, wrapped, {**self.base_env, **(env or {})}, self.directory, cwd)
        self.started.append(process)
        return process

    def tails(self) -> str:
        return "\n".join(p.tail() for p in self.started)

    def wait_until(self, condition, timeout: float, what: str, poll: float = 0.2) -> float:
        """Seconds until condition() held (checked every poll seconds); fails with every process's last lines after timeout."""
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            if condition():
                return time.monotonic() - start
            time.sleep(poll)
        pytest.fail(f"{what}: not within {timeout:.0f} s\n{self.tails()}", pytrace=False)

    def close(self) -> None:
        for process in reversed(self.started):
            process.kill()

    def start_talker(self, name: str, role: str, env: dict[str, str], topic: str = CHATTER, period: str = "") -> Process:
        """ros/talker.py on ``topic`` (every ``period`` seconds; its default 0.2 s), once it has published twice."""
        talker = self.start(name, role, [sys.executable, TALKER, topic, *([period] if period else [])], env)
        self.wait_until(lambda: len(talker.published()) >= 2, STARTUP_TIMEOUT, f"{name} did not start publishing")
        return talker

    def start_listener(self, name: str, role: str, env: dict[str, str], topic: str = CHATTER, wait: bool = True) -> Process:
        """ros/listener.py on ``topic``; with ``wait``, once it has subscribed."""
        listener = self.start(name, role, [sys.executable, LISTENER, topic], env)
        if wait:
            self.wait_until(lambda: "ready" in listener.output().split(), STARTUP_TIMEOUT, f"{name} did not subscribe")
        return listener
