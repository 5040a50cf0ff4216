"""The short evaluation scenario, end to end: one robot, two pick cycles, perception and the motion planner
offloaded to the cloud VM.

The cloud strategy's RosDeployment is rendered by the deploy playbook (kuberos_apply=false) and run by the
simulation runtime: the discovery servers on edge-1 and edge-2, the coordinator on edge-1, perception and the
planner on cloud-1 (40 ms round trip from the robot), the controller and the robot's physics on robot-1.
Asserted: every pick cycle succeeded, as the coordinator saw it through perception and as the physics' ground
truth says; every planning request was answered by the planner on cloud-1, another host than the coordinator;
the hosts found each other only through the discovery servers (every module is their client, the fabric forwards
no multicast, and cloud-1 exchanged packets with edge-2, where nothing but discovery server 1 runs).

Needs root, `ip netns`, cgroups and the ROS and simulator wheels (skipped without root or namespaces).
"""

from __future__ import annotations

import json
import os

import pytest
from kuberos_sim import evaluate
from kuberos_sim.runtime import environment_problem

pytestmark = [pytest.mark.sim, pytest.mark.ros]

CYCLES = 2


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    problem = environment_problem()
    if problem:
        pytest.skip(problem)
    out = tmp_path_factory.mktemp("evaluation")
    row = evaluate.run_one("cloud", robots=1, rate=12, cycles=CYCLES, out=str(out), seed=1, time_limit=240, cpu_scale=0.125)
    (name,) = os.listdir(out / "runs")
    with open(out / "runs" / name / "records.json", encoding="utf-8") as handle:
        data = json.load(handle)
    return row, data["records"], data["fabric"], out / "runs" / name


def details(records, directory) -> str:
    lines = [json.dumps(r, sort_keys=True) for r in records if r["kind"] in ("plan", "cycle", "sim", "idle")]
    return f"run directory {directory}\n" + "\n".join(lines[-40:])


def test_every_pick_cycle_succeeds(run):
    row, records, _fabric, directory = run
    cycles = [r for r in records if r["kind"] == "cycle"]
    assert row["finished"], f"the cycles did not finish within the time limit\n{details(records, directory)}"
    assert len(cycles) == CYCLES and all(c["outcome"] == "success" for c in cycles), details(records, directory)
    physics = [r for r in records if r["kind"] == "sim"]
    assert physics and physics[-1]["on_platform"] == CYCLES, f"ground truth disagrees\n{details(records, directory)}"


def test_planning_requests_crossed_hosts(run):
    _row, records, _fabric, directory = run
    plans = [r for r in records if r["kind"] == "plan"]
    assert plans, details(records, directory)
    assert all(r["ok"] and r["planner_node"] == "cloud-1" and r["node"] == "edge-1" for r in plans), details(records, directory)
    # Each answer took at least the emulated round trip edge-1 <-> cloud-1 (40 ms) on top of planning.
    assert all(r["latency_ms"] >= 40 + r["planning_ms"] * 0.9 for r in plans), details(records, directory)


def test_discovery_only_through_the_discovery_servers(run):
    """Every module was a client of the fleet's two discovery servers (its rendered ROS_DISCOVERY_SERVER), the
    fabric forwards no multicast (test_runtime's negative control shows participants never meet without the
    servers), and every host that ran a participant exchanged packets with edge-2, where nothing but discovery
    server 1 runs in this scenario."""
    _row, _records, fabric, directory = run
    rendered = os.path.join(directory, "rendered", "manifests", "kuberos-sim-fleet")
    servers = ";".join(f"$(KUBEROS_DISCOVERY_{i}_SERVICE_HOST):11811" for i in (0, 1))  # the Services' addresses
    modules = [f for f in os.listdir(rendered) if f.startswith("deployment-pick-and-place-")]
    assert len(modules) == 4
    for name in modules:
        with open(os.path.join(rendered, name), encoding="utf-8") as handle:
            assert f"value: {servers}" in handle.read(), name
    pairs = fabric["pairs"]
    for pair in ("cloud-1->edge-2", "edge-2->cloud-1", "robot-1->edge-2", "edge-2->robot-1", "edge-1->edge-2"):
        assert pairs.get(pair, {}).get("packets", 0) > 0, f"no packets {pair}: {sorted(pairs)}"
    assert fabric["dropped"] == fabric["drops"]["multicast"], fabric["drops"]  # nothing else was lost
