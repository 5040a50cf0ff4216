"""The controller's scaling step run against the simulator's runtime (``kuberos_sim.scaler``), with real
processes: a shared worker module on the edge reads its robots from the file ``KUBEROS_ROBOTS_FILE`` names and
writes its load gauge where ``KUBEROS_METRICS_FILE`` says. The test sets the load; the scaler must add an
instance (a new process on an edge host), hand a robot over once that process reports, never restart the
instance that stays, and on the way down move the robot back before it stops the drained instance's process.

With a capped edge and a cloud (``kuberos_sim.cloud``), the instance the edge cannot hold is what the fleet lacks: a
VM is launched within the budget, becomes a host of the run, the blocked instance starts there as a real process and
serves a robot; after the peak the cloud instance leaves first, and once the fleet has been quiet the idle VM is
released and its host removed.

Needs root, ``ip netns``, TUN and cgroup v1 (skipped otherwise, as the runtime's own tests).
"""

from __future__ import annotations

import os
import sys
import time
from types import SimpleNamespace

import pytest
from helpers import ROOT

sys.path[:0] = [os.path.join(ROOT, "sim")]

from kuberos_sim.cloud import SimCloud  # noqa: E402
from kuberos_sim.runtime import Runtime, environment_problem  # noqa: E402
from kuberos_sim.scaler import SimScaler  # noqa: E402
from test_runtime import render  # noqa: E402

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import service  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.ansible_inventory import read_inventory  # noqa: E402

pytestmark = pytest.mark.sim

# A module that prints its robots whenever its file changes and exposes the load the test writes to LOAD_FILE.
WORKER = (
    'python3 -c "import os, time\n'
    "robots = os.environ['KUBEROS_ROBOTS_FILE']; metrics = os.environ['KUBEROS_METRICS_FILE']; seen = None\n"
    "while True:\n"
    "    now = open(robots).read()\n"
    "    if now != seen: print('ROBOTS=' + now, flush=True); seen = now\n"
    "    load = open(os.environ['LOAD_FILE']).read().strip() or '0'\n"
    "    open(metrics + '.new', 'w').write('# TYPE work_queue gauge\\\\nwork_queue ' + load + '\\\\n')\n"
    "    os.replace(metrics + '.new', metrics)\n"
    '    time.sleep(0.1)"'
)


def spec(load_file: str) -> dict:
    return {
        "metadata": {"name": "sim-scaled", "targetFleet": "test-fleet"},
        "rosModules": [
            {
                "name": "worker",
                "image": "worker",
                "launch": [WORKER],
                "preference": "edge",
                "resources": {"cpu": "100m", "memory": "64Mi"},
                "strategy": "shared",
                "robotsPerInstance": 2,
                "env": {"LOAD_FILE": load_file},
                "scaling": {"maxInstances": 2, "metric": "work_queue", "target": 1, "scaleDownWindow": "3s", "drainTime": "2s"},
            }
        ],
    }


def wait_until(condition, timeout: float, what: str, runtime, scaler) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.2)
    tails = "\n".join(p.tail(5) for p in runtime.processes.values())
    pytest.fail(f"{what}: not within {timeout:.0f} s\n{scaler.timeline[-3:]}\n{scaler.errors}\n{tails}", pytrace=False)


def workers(runtime) -> list[str]:
    return sorted(name for name in runtime.processes if "-worker-" in name)


def robots_seen(process) -> list[str]:
    return [line[len("ROBOTS=") :] for line in process.output().splitlines() if line.startswith("ROBOTS=")]


def test_the_sim_scaler_adds_hands_over_and_drains_real_processes(tmp_path, local_raw, local_inventory):
    problem = environment_problem()
    if problem:
        pytest.skip(f"the simulator cannot run here: {problem}")
    load = tmp_path / "load"
    load.write_text("0.5")
    raw = spec(str(load))
    rendered = render(raw, local_raw, str(tmp_path / "rendered"))
    deployments, placement = service.load_and_place(raw, local_raw)
    record = SimpleNamespace(
        spec=deployments[0], deployments=deployments, placement=placement, inventory=local_inventory, options=RenderOptions()
    )
    first, second = "sim-scaled-worker-shared-0", "sim-scaled-worker-shared-1"
    with Runtime(rendered, local_inventory, str(tmp_path / "run"), extra_hosts=("edge-2", "edge-3")) as runtime:
        runtime.start()
        scaler = SimScaler(runtime, record, period=0.5).start()
        try:
            kept = runtime.processes[first]
            wait_until(lambda: robots_seen(kept) == ["fetch-1,fetch-2"], 20, "the first instance's robots", runtime, scaler)
            time.sleep(2)
            assert workers(runtime) == [first], "half the target: one instance"

            load.write_text("3")  # three times the target asks for 3 instances; the policy allows 2
            wait_until(lambda: second in runtime.processes, 20, "a second instance started", runtime, scaler)
            added = runtime.processes[second]
            wait_until(lambda: robots_seen(kept)[-1:] == ["fetch-1"], 20, "fetch-2 handed over", runtime, scaler)
            assert robots_seen(added)[-1] == "fetch-2"
            assert runtime.processes[first] is kept and kept.running, "the instance that stays runs on"

            load.write_text("0")
            wait_until(lambda: robots_seen(kept)[-1:] == ["fetch-1,fetch-2"], 20, "fetch-2 moved back", runtime, scaler)
            moved = time.monotonic()
            assert added.running, "the drained instance still runs when its robot has left"
            wait_until(lambda: second not in runtime.processes, 20, "the drained instance stopped", runtime, scaler)
            assert time.monotonic() - moved >= 1.0 and not added.running
            assert robots_seen(added)[-1] == "", "it served nobody before it stopped"
            assert kept.running and robots_seen(kept)[0] == "fetch-1,fetch-2"
            steps = [e.split(":")[0] for t in scaler.timeline for e in t["events"]]
            assert steps == ["ModuleScaledUp", "ModuleScaledDown", "ModuleInstanceStopped"], steps
            assert scaler.errors == []
        finally:
            scaler.stop()


# A site whose one edge server holds the discovery servers and one worker (200m of 250m), and no cloud node until
# one is launched.
CAPPED_SITE = """
all:
  vars: {ansible_connection: local, kuberos_default_latency_ms: {onboard: 0, edge: 5, cloud: 40}}
  children:
    robots:
      vars: {kuberos_cpu: 4, kuberos_memory: 8Gi}
      hosts:
        fetch-1: {kuberos_fleet: test-fleet}
        fetch-2: {kuberos_fleet: test-fleet}
    edge:
      hosts:
        edge-1: {kuberos_cpu: 250m, kuberos_memory: 1Gi}
"""
BUDGET = {"max_vms": 2, "instance_types": {"t3.small": {"cpu": 1, "memory": "2Gi", "hourly_price": 0.02}}}


def test_a_blocked_step_bursts_to_a_vm_that_serves_a_robot_and_is_released_after_the_peak(tmp_path):
    problem = environment_problem()
    if problem:
        pytest.skip(f"the simulator cannot run here: {problem}")
    site = tmp_path / "site.yml"
    site.write_text(CAPPED_SITE)
    site_raw = read_inventory(str(site))
    load = tmp_path / "load"
    load.write_text("0.5")
    raw = spec(str(load))
    module = raw["rosModules"][0]
    module["requirements"] = {"max_latency": "50 ms"}  # the cloud's 40 ms will do
    module["scaling"].update({"scaleDownWindow": "2s", "drainTime": "1s"})
    rendered = render(raw, site_raw, str(tmp_path / "rendered"))
    inventory = load_inventory(site_raw)
    deployments, placement = service.load_and_place(raw, site_raw)
    record = SimpleNamespace(
        spec=deployments[0], deployments=deployments, placement=placement, inventory=inventory, options=RenderOptions()
    )
    first, second = "sim-scaled-worker-shared-0", "sim-scaled-worker-shared-1"
    with Runtime(rendered, inventory, str(tmp_path / "run"), extra_hosts=("fetch-2",)) as runtime:
        runtime.start()
        cloud = SimCloud(runtime, "test-fleet", budget=BUDGET, latency_ms=40, boot_s=1.0, release_after_s=2.0)
        scaler = SimScaler(runtime, record, period=0.5, cloud=cloud).start()
        try:
            kept = runtime.processes[first]
            wait_until(lambda: robots_seen(kept) == ["fetch-1,fetch-2"], 20, "the first instance's robots", runtime, scaler)
            assert sorted(runtime.hosts) == ["edge-1", "fetch-1", "fetch-2"] and cloud.vms == {}

            load.write_text("3")  # asks for 2 instances; edge-1 has room for one
            wait_until(lambda: second in runtime.processes, 30, "the second instance started on a VM", runtime, scaler)
            vm = next(iter(cloud.vms))
            assert list(cloud.vms) == [vm] and vm.startswith("sim-test-fleet-cloud-"), cloud.log
            added = runtime.processes[second]
            assert added.host == vm and vm in runtime.hosts and runtime.hosts[vm].tier == "cloud"
            wait_until(lambda: robots_seen(added)[-1:] == ["fetch-2"], 20, "fetch-2 served from the VM", runtime, scaler)
            events = [e for t in scaler.timeline for e in t["events"]]
            blocked = [e for e in events if e.startswith("ModuleScaleBlocked")]
            assert blocked and "edge-1" in blocked[0], events  # the edge was full: why it burst
            assert scaler.demand["instances"] == 0 and scaler.demand["since"] == "", "placed: nothing lacks any more"

            load.write_text("0")
            wait_until(lambda: robots_seen(kept)[-1:] == ["fetch-1,fetch-2"], 20, "fetch-2 moved back", runtime, scaler)
            wait_until(lambda: not cloud.live(), 30, "the idle VM released", runtime, scaler)
            assert not added.running and vm not in runtime.hosts, "its instance stopped and its host removed"
            assert not os.path.exists("/var/run/netns/" + f"krs-{runtime.suffix}-{vm}"[:60])
            assert kept.running and runtime.processes[first] is kept, "the edge instance ran on throughout"
            summary = cloud.summary()
            assert (summary["vms_provisioned"], summary["vms_released"], summary["vms_left_at_end"]) == (1, 1, 0), summary
            assert [e["event"] for e in summary["log"]] == ["launched", "node", "released"], summary["log"]
            assert (vm, "node") in runtime.cpu_seconds(), "the VM's CPU stays counted after it is gone"
            assert scaler.errors == []
        finally:
            scaler.stop()
    assert not runtime.leftovers() and not runtime.close_problems, (runtime.leftovers(), runtime.close_problems)
