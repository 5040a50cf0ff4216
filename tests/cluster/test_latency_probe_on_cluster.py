"""The latency probe measures a real round trip and writes it on the robot's node, where the controller reads it.

Two network namespaces made here, "robot" and "edge", are joined by a veth pair; the playbook runs for the
robot fetch-2 (a node of the test cluster) with `ansible_connection: local`, and its pings run inside the
robot namespace (`latency_probe_ping_command: [ip, netns, exec, <robot ns>, ping]`), so every ICMP packet
crosses the veth pair. edge-1 answers from the edge namespace; cloud-1's address is on the same link with no
host behind it, so it never answers. Needs root, `ip netns` and `ping` (skipped otherwise). Traffic stays in
the namespaces this module creates; ping counts and waits are bounded.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil

import pytest
import yaml
from helpers import playbook
from sshlab import run

pytestmark = [pytest.mark.cluster, pytest.mark.host]

SUBNET = "10.213.8"  # exists only inside the two namespaces this module creates
ROBOT_ADDRESS, EDGE_ADDRESS, NOBODY_ADDRESS = f"{SUBNET}.1", f"{SUBNET}.2", f"{SUBNET}.3"
ANNOTATION = "kuberos.io/rtt-ms"
ROBOT = "fetch-2"  # a robot node of the test cluster (inventories/local)


@pytest.fixture
def namespaces():
    """{"robot": ns, "edge": ns}, joined by a veth pair with ROBOT_ADDRESS and EDGE_ADDRESS; removed afterwards."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if not shutil.which("ip") or not shutil.which("ping"):
        pytest.skip("`ip` (iproute2) and `ping` (iputils-ping) are needed")
    suffix = secrets.token_hex(2)
    names = {"robot": f"kr-lp-robot-{suffix}", "edge": f"kr-lp-edge-{suffix}"}
    created = []
    try:
        for namespace in names.values():
            run("ip", "netns", "add", namespace)
            created.append(namespace)
        robot_end, edge_end = f"krlpr{suffix}", f"krlpe{suffix}"
        run(
            "ip", "-n", names["robot"], "link", "add", robot_end, "type", "veth", "peer", "name", edge_end, "netns", names["edge"]
        )
        for role, device, address in (("robot", robot_end, ROBOT_ADDRESS), ("edge", edge_end, EDGE_ADDRESS)):
            run("ip", "-n", names[role], "addr", "add", f"{address}/24", "dev", device)
            run("ip", "-n", names[role], "link", "set", device, "up")
    except RuntimeError as error:
        for namespace in created:
            run("ip", "netns", "delete", namespace, check=False)
        pytest.skip(f"`ip netns` is not usable here: {error}")
    try:
        yield names
    finally:
        for namespace in created:
            run("ip", "netns", "delete", namespace, check=False)  # also removes the veth pair


def inventory(path) -> str:
    hosts = {
        "all": {
            "vars": {"ansible_python_interpreter": "{{ ansible_playbook_python }}"},
            "children": {
                "robots": {
                    "hosts": {
                        ROBOT: {
                            "ansible_connection": "local",
                            "kuberos_fleet": "test-fleet",
                            "kuberos_cpu": 4,
                            "kuberos_memory": "8Gi",
                        }
                    }
                },
                "edge": {"hosts": {"edge-1": {"kuberos_cpu": 16, "kuberos_memory": "32Gi", "kuberos_address": EDGE_ADDRESS}}},
                "cloud": {"hosts": {"cloud-1": {"kuberos_cpu": 32, "kuberos_memory": "64Gi", "kuberos_address": NOBODY_ADDRESS}}},
            },
        }
    }
    path.write_text(yaml.safe_dump(hosts), encoding="utf-8")
    return str(path)


def test_round_trip_time_measured_across_namespaces_lands_on_the_robot_node(cluster, namespaces, tmp_path):
    core, _apps, _discovery = cluster.clients()

    def probe(*extra):
        settings = {
            "kuberos_kubeconfig": cluster.kubeconfig,
            "latency_probe_ping_command": ["ip", "netns", "exec", namespaces["robot"], "ping"],
            "latency_probe_count": 3,
            "latency_probe_timeout": 1,
        }
        result = playbook(
            "latency_probe.yml", "-e", json.dumps(settings), *extra, inventory=inventory(tmp_path / "hosts.yml"), timeout=300
        )
        assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-3000:]
        return result

    def annotation():
        return (core.read_node(ROBOT).metadata.annotations or {}).get(ANNOTATION)

    before = annotation()
    try:
        checked = probe("--check", "--diff")
        assert annotation() == before  # check mode pings, shows, and writes nothing
        assert ANNOTATION in checked.stdout

        done = probe()
        measured = json.loads(annotation())
        assert set(measured) == {"edge-1"}, measured  # cloud-1 never answered: absent, not 0
        assert isinstance(measured["edge-1"], float) and 0 < measured["edge-1"] < 50, measured
        table = done.stdout[done.stdout.index("ROBOT ") :]
        edge_row = next(line for line in table.splitlines() if " edge-1 " in line)
        assert edge_row.split()[:4] == [ROBOT, "edge-1", "edge", EDGE_ADDRESS] and edge_row.rstrip().endswith(" ms")
        cloud_row = next(line for line in table.splitlines() if " cloud-1 " in line)
        assert "missing (lost: 100% packet loss, 3 sent)" in cloud_row, table
        assert "1 target(s) without a reply, left out of kuberos.io/rtt-ms" in table

        managers = {(m.manager, m.operation) for m in core.read_node(ROBOT).metadata.managed_fields}
        assert ("kuberos-latency-probe", "Apply") in managers
        assert core.read_node(ROBOT).metadata.labels["robot.kuberos.io/name"] == ROBOT  # labels untouched
    finally:
        # Other tests share the cluster and the controller acts on this annotation: leave none behind.
        core.patch_node(ROBOT, {"metadata": {"annotations": {ANNOTATION: None}}})
    assert annotation() is None
