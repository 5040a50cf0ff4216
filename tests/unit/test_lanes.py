"""make test's two lanes (tests/lanes.py, docs/testing.md): each lane runs in one pytest-xdist worker, and every test
module that changes this machine is in the host lane."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from helpers import ROOT

# What a test module uses when it changes this machine: lab hosts, network namespaces, real nodes, DDS processes.
HOST_SIGNS = re.compile(
    r"^from (sshlab|netlab|real_tier) import|kuberos_lab import machines\b|\"netns\", \"add\"|^import rclpy|snapshot_host", re.M
)


def _pytest(*args: str, **env: str) -> subprocess.CompletedProcess:
    environment = {**os.environ, **env}
    environment.pop("PYTEST_XDIST_WORKER", None)
    command = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-o", "addopts=", *args]
    return subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True, timeout=300, check=False)


def test_each_lane_runs_in_one_worker():
    # two files of the api lane and one of the host lane, pure tests of seconds
    done = _pytest(
        "-n", "2", "--dist", "loadgroup", "-v", "tests/unit/test_vpn.py", "tests/unit/test_calico.py", "tests/sim/test_world.py"
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    workers: dict[str, set[str]] = {}
    for worker, folder in re.findall(r"^\[(gw\d)\] .*?PASSED (tests/\w+)/", done.stdout, re.M):
        workers.setdefault(folder, set()).add(worker)
    assert set(workers) == {"tests/unit", "tests/sim"}, done.stdout[-3000:]
    assert len(workers["tests/unit"]) == len(workers["tests/sim"]) == 1, workers
    assert workers["tests/unit"] != workers["tests/sim"], workers


def test_every_module_that_changes_this_machine_is_in_the_host_lane():
    done = _pytest("--collect-only", "-q", "tests", KUBEROS_LANES_REPORT="1")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    lanes: dict[str, set[str]] = {}
    for path, lane in re.findall(r"^lane (\S+) (\S+)$", done.stdout, re.M):
        lanes.setdefault(path, set()).add(lane)
    changers = set()
    for path in set(lanes) - {"tests/unit/test_lanes.py"}:
        with open(os.path.join(ROOT, path), encoding="utf-8") as handle:
            if HOST_SIGNS.search(handle.read()):
                changers.add(path)
    assert {
        "tests/site/test_site_chain.py",
        "tests/cluster/test_real_nodes.py",
        "tests/molecule/test_molecule_scenarios.py",
    } <= changers
    wrong = {path: sorted(lanes[path]) for path in sorted(changers) if lanes[path] != {"host"}}
    assert not wrong, f"modules that change this machine with tests outside the host lane (mark them host): {wrong}"
    assert {"api"} == lanes["tests/unit/test_vpn.py"], lanes["tests/unit/test_vpn.py"]
