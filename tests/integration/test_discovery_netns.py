"""The rendered Fast DDS discovery configuration, proven with real processes in network namespaces.

listing1 is rendered with the project's own code, and what it renders is used unchanged: each discovery
server Deployment's container args (`fast-discovery-server -i <id> -l 0.0.0.0 -p 11811`, the program
from the ros-fastrtps wheel) runs in a network namespace of its own, and rclpy talker and listener
processes run in others with a module container's environment (ROS_DISCOVERY_SERVER, RMW_IMPLEMENTATION,
ROS_DOMAIN_ID, ...), its references to the servers' Services (``$(KUBEROS_DISCOVERY_0_SERVICE_HOST)``) expanded
to the namespaces' addresses as the kubelet expands them to the Services' cluster IPs, and every process gets a
private /dev/shm, as pods on different nodes would, so that all traffic crosses the bridge.

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
import signal
import sys
import time
from dataclasses import dataclass

import pytest
from helpers import ROOT

# test_bridge.py and bench/bench_bridge.py import Lab, Process, Processes and open_lab from here
from netlab import STARTUP_TIMEOUT, Lab, Process, Processes, open_lab

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels, manifests, naming, scheduler, spec
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import ros_problem

pytestmark = pytest.mark.ros

DISCOVERY_TIMEOUT = 30.0  # a listener receiving its first message
NEGATIVE_WINDOW = 8.0  # simple discovery gets this long to fail; with multicast it succeeds in under a second


# --- ROS 2 from PyPI wheels (plugins/module_utils/kuberos_lab/ros_wheels.py) ------------------------------------------


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
    servers: dict[str, list[str]]  # discovery server Deployment name -> its container args
    server_env: dict[str, dict[str, str]]  # discovery server Deployment name -> its container's environment
    addresses: dict[str, str]  # service link in ROS_DISCOVERY_SERVER -> the discovery server Deployment it names
    module_env: dict[str, dict[str, str]]  # module Deployment name -> its container's environment (as rendered)


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
            by_component.setdefault(obj["metadata"]["labels"][labels.COMPONENT], []).append(obj)
    servers = {
        d["metadata"]["name"]: d["spec"]["template"]["spec"]["containers"][0]["args"] for d in by_component["discovery-server"]
    }
    server_env = {d["metadata"]["name"]: container_env(d) for d in by_component["discovery-server"]}
    links = {naming.service_host_variable(d["metadata"]["name"]): d["metadata"]["name"] for d in by_component["discovery-server"]}
    module_env = {d["metadata"]["name"]: container_env(d) for d in by_component["ros-module"]}
    # onboard modules also list their robot's own server, last (docs/connectivity.md); the fleet's part is shared
    values = {manifests.fleet_discovery_part(env["ROS_DISCOVERY_SERVER"]) for env in module_env.values()}
    assert len(values) == 1, f"modules of one fleet disagree on ROS_DISCOVERY_SERVER: {values}"
    assert all(env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp" for env in module_env.values())
    addresses = {}
    for slot in values.pop().split(";"):
        host, _port = slot.rsplit(":", 1)
        variable = host.removeprefix("$(").removesuffix(")")
        assert host == f"$({variable})" and variable in links, f"{host} in ROS_DISCOVERY_SERVER names no discovery Service"
        addresses[variable] = links[variable]
    assert len(servers) == 2 and set(addresses.values()) == set(servers), (servers, addresses)
    return Rendered(servers=servers, server_env=server_env, addresses=addresses, module_env=module_env)


def service_links(rendered: Rendered, lab: Lab) -> dict[str, str]:
    """The discovery Services' links as the kubelet sets them, each the address of the namespace running its server."""
    return {variable: lab.addresses[server_role(rendered, server)] for variable, server in rendered.addresses.items()}


def module_env(rendered: Rendered, lab: Lab, module: str, robot: str) -> dict[str, str]:
    """A module container's environment as the kubelet sets it: the discovery Services' links expanded to the
    addresses of the namespaces that run their servers."""
    (name,) = [n for n, env in rendered.module_env.items() if n.endswith(f"-{module}-{robot}")]
    links = service_links(rendered, lab)
    env = dict(rendered.module_env[name])
    # the fleet's servers only: these tests are about them (the robot's own server: tests/sim/test_runtime.py)
    env["ROS_DISCOVERY_SERVER"] = manifests.fleet_discovery_part(env["ROS_DISCOVERY_SERVER"])
    return {k: manifests.expand_references(v, links) for k, v in env.items()}


def without_discovery(env: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k != "ROS_DISCOVERY_SERVER"}


# --- network namespaces (tests/netlab.py) -----------------------------------------------------------------


@pytest.fixture(scope="module")
def lab(request, rendered) -> Lab:
    lab = open_lab(request, "ds0")
    for role in ("ds1", "talk", "listen", "late"):
        lab.add(role)
    return lab


def server_role(rendered: Rendered, server: str) -> str:
    return f"ds{sorted(rendered.servers).index(server)}"


# --- processes (tests/netlab.py) --------------------------------------------------------------------------


@pytest.fixture
def procs(lab, tmp_path):
    processes = Processes(lab, str(tmp_path))
    yield processes
    processes.close()


def start_servers(procs: Processes, rendered: Rendered) -> dict[str, Process]:
    """Each discovery server Deployment's command and environment, exactly as rendered (the other servers' Service
    links expanded to their namespaces' addresses), in its own namespace."""
    servers = {}
    links = service_links(rendered, procs.lab)
    for name, command in sorted(rendered.servers.items()):
        env = {k: manifests.expand_references(v, links) for k, v in rendered.server_env[name].items()}
        servers[name] = procs.start(name, server_role(rendered, name), command, env)
    for name, process in servers.items():
        server_id = rendered.servers[name][rendered.servers[name].index("-i") + 1]
        procs.wait_until(
            lambda p=process, i=server_id: re.search(rf"Server ID:\s+{i}\b", p.output()) is not None,
            STARTUP_TIMEOUT,
            f"{name} did not report itself running as server {server_id}",
        )
    return servers


# --- tests ------------------------------------------------------------------------------------------------


def test_negative_control_without_ros_discovery_server_modules_never_meet(procs, lab, rendered):
    """Multicast is really blocked: simple discovery fails, and succeeds once the bridge floods multicast."""
    require_ros()
    simple = without_discovery(module_env(rendered, lab, "fetch-controller-foxy", "fetch-1"))
    talker = procs.start_talker("talker-simple", "talk", simple)
    simple = without_discovery(module_env(rendered, lab, "fetch-motion-planner", "fetch-1"))
    listener = procs.start_listener("listener-simple", "listen", simple)
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


def test_modules_meet_through_the_rendered_discovery_servers(procs, lab, rendered):
    require_ros()
    start_servers(procs, rendered)
    talker = procs.start_talker("talker", "talk", module_env(rendered, lab, "fetch-controller-foxy", "fetch-1"))
    listener = procs.start_listener("listener", "listen", module_env(rendered, lab, "fetch-motion-planner", "fetch-1"))
    seconds = procs.wait_until(lambda: len(listener.received()) >= 3, DISCOVERY_TIMEOUT, "listener got no messages")
    assert talker.subscribers() == 1, procs.tails()
    print(f"listener received 3 messages {seconds:.1f} s after subscribing")


def test_a_new_listener_meets_the_talker_through_server_1_after_server_0_is_killed(procs, lab, rendered):
    require_ros()
    servers = start_servers(procs, rendered)
    first, second = sorted(servers)
    procs.start_talker("talker", "talk", module_env(rendered, lab, "fetch-controller-foxy", "fetch-1"))
    listener = procs.start_listener("listener", "listen", module_env(rendered, lab, "fetch-motion-planner", "fetch-1"))
    procs.wait_until(lambda: listener.received(), DISCOVERY_TIMEOUT, "listener got no messages with both servers up")

    servers[first].kill(signal.SIGKILL)
    assert servers[first].popen.returncode is not None and servers[second].popen.poll() is None
    before = len(listener.received())
    late = procs.start_listener("listener-late", "late", module_env(rendered, lab, "fetch-motion-planner", "fetch-2"))
    seconds = procs.wait_until(lambda: late.received(), DISCOVERY_TIMEOUT, f"a new listener got no messages without {first}")
    procs.wait_until(lambda: len(listener.received()) > before, DISCOVERY_TIMEOUT, "the first listener stopped receiving")
    assert servers[second].popen.poll() is None, procs.tails()
    print(f"new listener received its first message {seconds:.1f} s after subscribing, with only {second} up")
