"""The rollout gate's ROS-level check (plugins/module_utils/kuberos_deploy/ros_graph_probe.py) with real rclpy and Fast DDS.

A fast-discovery-server and a module's node (``/fetch_1/motion_planner``) run as processes on loopback with
``ROS_DISCOVERY_SERVER`` pointing at the server, as rendered modules have it; the probe, a third process, finds the
node through the server (exit 0), reports a node that is not there (exit 1), and sees nothing once the server is gone.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe import (
    expected_nodes,
    graph_names,
    holders,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import ros_environment, ros_problem

PROBE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe"
NODE = os.path.join(ROOT, "tests", "integration", "ros", "named_node.py")
LOCK_EXAMPLE = os.path.join(ROOT, "examples", "ros", "update_lock.py")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_expected_names_expand_per_robot_as_ros_names():
    assert expected_nodes(["/{robot}/planner", "/fleet_monitor"], ["fetch-1", "fetch-2"]) == [
        "/fetch_1/planner", "/fetch_2/planner", "/fleet_monitor",
    ]  # fmt: skip
    with pytest.raises(ValueError, match="not a fully qualified ROS node name"):
        expected_nodes(["planner; rm -rf /"], [])
    assert graph_names([("planner", "/fetch_1"), ("probe", "/")]) == {"/fetch_1/planner", "/probe"}
    present = {"/fetch_1/kuberos_update_lock", "/r_7x/kuberos_update_lock"}
    assert holders(["/{robot}/kuberos_update_lock"], ["fetch-1", "fetch-2", "7x"], present) == ["fetch-1", "7x"]


PYTHON = os.path.join(sys.prefix, "bin", "python3")


@pytest.fixture
def graph(tmp_path):
    """A discovery server on a free loopback port and the environment of a module that uses it: (env, server)."""
    problem = ros_problem()
    if problem:
        pytest.fail(f"rclpy with Fast DDS is not usable from {sys.prefix}: {problem}", pytrace=False)
    port = _free_udp_port()
    env = {
        **ros_environment(log_dir=str(tmp_path / "ros-log")),
        "ROS_DISCOVERY_SERVER": f"127.0.0.1:{port}",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_DOMAIN_ID": str(17 + port % 100),
        "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, ".collections"), os.path.dirname(NODE)]),
    }
    server = subprocess.Popen(["fast-discovery-server", "-i", "0", "-l", "127.0.0.1", "-p", str(port)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)  # fmt: skip
    try:
        yield env, server
    finally:
        server.kill()
        server.wait(10)


@pytest.mark.ros
def test_the_probe_finds_a_modules_node_through_the_discovery_server(graph):
    env, server = graph
    python = PYTHON
    node = subprocess.Popen([python, NODE, "motion_planner", "/fetch_1"], env=env, stdout=subprocess.PIPE, text=True)
    try:
        assert node.stdout.readline().strip() == "up"

        def probe(*expect, timeout="15"):
            args = [a for e in expect for a in ("--expect", e)]
            return subprocess.run([python, "-m", PROBE, *args, "--timeout", timeout], env={**env, "KUBEROS_ROBOTS": "fetch-1"},
                                  capture_output=True, text=True, timeout=60)  # fmt: skip

        found = probe("/{robot}/motion_planner")
        assert found.returncode == 0, found.stdout + found.stderr
        assert "all 1 node(s) present: /fetch_1/motion_planner" in found.stdout
        missing = probe("/{robot}/motion_planner", "/{robot}/perception", timeout="3")
        assert missing.returncode == 1
        assert "missing after 3 s: /fetch_1/perception" in missing.stderr and "/fetch_1/motion_planner" in missing.stderr
        server.kill()
        server.wait(10)
        alone = probe("/{robot}/motion_planner", timeout="3")
        assert alone.returncode == 1, "without the discovery server the probe meets nobody"
    finally:
        node.kill()
        node.wait(10)


@pytest.mark.ros
def test_the_update_lock_example_holds_and_releases_the_lock_the_probe_waits_for(graph):
    """examples/ros/update_lock.py holds fetch-1's update lock: the probe with --absent (as a rollout's update_lock
    command) names fetch-1, not fetch-2, as holding it, and exits 1; released, the probe exits 0."""
    env, _server = graph
    python = PYTHON
    holder = subprocess.Popen([python, LOCK_EXAMPLE, "fetch-1"], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)  # fmt: skip

    def probe(timeout):
        return subprocess.run(
            [python, "-m", PROBE, "--absent", "/{robot}/kuberos_update_lock", "--timeout", timeout, "--settle", "2"],
            env={**env, "KUBEROS_ROBOTS": "fetch-1,fetch-2"}, capture_output=True, text=True, timeout=90,
        )  # fmt: skip

    try:
        assert holder.stdout.readline().strip() == "held /fetch_1/kuberos_update_lock"
        held = probe("4")
        assert held.returncode == 1, held.stdout + held.stderr
        assert held.stdout.splitlines() == ["held: fetch-1"], held.stdout
        holder.stdin.close()
        assert holder.stdout.readline().strip() == "released"
        free = probe("30")
        assert free.returncode == 0, free.stdout + free.stderr
        assert "none of 2 node(s) present" in free.stdout
    finally:
        holder.kill()
        holder.wait(10)
