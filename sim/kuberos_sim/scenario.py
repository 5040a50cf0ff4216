"""One evaluation scenario: the site, the RosDeployment for a strategy, and rendering it the way deploy does.

- The site (`site_inventory`): `robots` simulated mobile manipulators of fleet `sim-fleet` (4 CPUs each), two
  edge servers (16 CPUs; 5 ms round trip from the robots) and one cloud VM (32 CPUs; 40 ms), the proportions
  of the paper's testbed. The runtime scales CPUs to cgroup quotas for this machine (cpu_scale).
- The RosDeployment (`strategy_spec`): examples/pick-and-place.yml, with perception and the motion planner
  placed by the strategy:
  - `onboard`: both on each robot's own computer (requirements.onboard);
  - `edge-dedicated`: both on the edge, one instance per robot;
  - `edge-shared`: both on the edge, one instance per 4 robots (strategy shared);
  - `cloud`: both on the cloud VM, one instance per robot;
  - `edge-scaled`: as edge-shared, but the motion planner starts as one instance for up to 8 robots and is scaled on
    its request queue between 1 and 8 instances
    (``PLANNER_SCALING``; the evaluation runs the controller's scaling step, kuberos_sim.scaler);
  - `edge-burst`: as edge-scaled on a site whose edge is capped (``BURST_EDGE_CPU``: one edge server with room for two
    planners, no cloud VM to begin with), the planner allowed in the cloud (max_latency 50 ms): the instances the
    edge cannot hold are what the fleet lacks, and cloud VMs are provisioned for them and released after the peak
    (kuberos_sim.cloud).
  The coordinator (shared, edge) and the controller (onboard) stay as the example has them; the workload
  rate, the number of pick cycles per robot, the seed (its IK restarts) and how long it waits for its robots'
  modules at start go into the coordinator's launch command, the seed also into the motion planner's
  parameters (its OMPL seeds).
- Rendering (`render`): `ansible-playbook playbooks/deploy.yml -e kuberos_apply=false`, the deploy path itself
  (validate, place with the scheduler filter, render with the rosdeployment_render module) without applying.
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLE = os.path.join(ROOT, "examples", "pick-and-place.yml")
FLEET = "sim-fleet"
STRATEGIES = ("onboard", "edge-dedicated", "edge-shared", "cloud", "edge-scaled", "edge-burst")
MATRIX = STRATEGIES[:4]  # the evaluation's matrix; edge-scaled and edge-burst are run apart (bench/bench_scaling.py)
SCALED = ("edge-scaled", "edge-burst")  # the planner scaled on its queue
# edge-burst's site: one edge server of 8 CPUs (the coordinators, perception and two planners fit; a third does not),
# no cloud node until one is provisioned; its planners may be 50 ms away (the cloud's 40 ms round trip).
BURST_EDGE_CPU = 8
BURST_MAX_LATENCY = "50 ms"
# edge-scaled: the planner shared (up to 8 robots each, so it starts with one) and scaled on its queue between 1 and 8
# instances (docs/scaling.md); perception stays shared by 4 as in edge-shared.
PLANNER_SCALING = {
    "minInstances": 1,
    "maxInstances": 8,
    "metric": "kuberos_planner_queue_depth",
    "target": 0.7,  # 70 % busy on average: queueing grows steeply above that
    "scaleUpWindow": "10s",
    "scaleDownWindow": "30s",
    "drainTime": "20s",
}
OFFLOADED = ("perception", "motion-planner")
EDGE_RTT_MS = 5
CLOUD_RTT_MS = 40


def robot_names(robots: int) -> list[str]:
    return [f"robot-{i}" for i in range(1, robots + 1)]


def site_inventory(robots: int, strategy: str = "") -> dict:
    """An Ansible YAML inventory (as data) of the simulated site (edge-burst's: its capped edge, no cloud)."""
    if strategy == "edge-burst":
        site = site_inventory(robots)
        children = site["all"]["children"]
        children["edge"] = {"vars": {"kuberos_cpu": BURST_EDGE_CPU, "kuberos_memory": "32Gi"}, "hosts": {"edge-1": {}}}
        children.pop("cloud")
        return site
    return {
        "all": {
            "vars": {
                "ansible_connection": "local",
                "kuberos_default_latency_ms": {"onboard": 0, "edge": EDGE_RTT_MS, "cloud": CLOUD_RTT_MS},
            },
            "children": {
                "robots": {
                    "vars": {"kuberos_cpu": 4, "kuberos_memory": "8Gi", "kuberos_arch": "amd64"},
                    "hosts": {
                        name: {"kuberos_fleet": FLEET, "kuberos_devices": ["camera", "gripper"]} for name in robot_names(robots)
                    },
                },
                "edge": {"vars": {"kuberos_cpu": 16, "kuberos_memory": "32Gi"}, "hosts": {"edge-1": {}, "edge-2": {}}},
                "cloud": {"vars": {"kuberos_cpu": 32, "kuberos_memory": "64Gi"}, "hosts": {"cloud-1": {}}},
            },
        }
    }


def strategy_spec(
    strategy: str,
    tasks_per_minute: float,
    cycles: int,
    example: str = EXAMPLE,
    *,
    seed: int = 1,
    startup_timeout: float | None = None,
) -> dict:
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; expected one of {', '.join(STRATEGIES)}")
    with open(example, encoding="utf-8") as handle:
        spec = copy.deepcopy(yaml.safe_load(handle))
    spec["metadata"]["targetFleet"] = FLEET
    for module in spec["rosModules"]:
        name = module["name"]
        if name in OFFLOADED:
            requirements = {k: v for k, v in module.get("requirements", {}).items() if k != "onboard"}
            module.pop("strategy", None)
            module.pop("robotsPerInstance", None)
            if strategy == "onboard":
                module["preference"] = "onboard"
                requirements = {"onboard": True}
            elif strategy.startswith("edge"):
                module["preference"] = "edge"
                requirements["max_latency"] = "20 ms"
                if strategy in ("edge-shared", *SCALED):
                    module["strategy"], module["robotsPerInstance"] = "shared", 4
                if strategy in SCALED and name == "motion-planner":
                    module["robotsPerInstance"] = 8  # one planner may serve every robot; the load decides how many
                    module["scaling"] = dict(PLANNER_SCALING)
                if strategy == "edge-burst" and name == "motion-planner":
                    requirements["max_latency"] = BURST_MAX_LATENCY
            else:
                module["preference"] = "cloud"
                requirements["max_latency"] = "200 ms"
            module["requirements"] = requirements
        if name == "motion-planner":
            module["rosParameters"] = {**module.get("rosParameters", {}), "seed": int(seed)}
            if strategy in SCALED:
                module["rosParameters"]["handover_s"] = 5.0
        if name == "task-coordinator":
            command = (
                f"python3 -m kuberos_pnp.coordinator --ros-args -p tasks_per_minute:={tasks_per_minute:g} -p max_cycles:={cycles}"
                f" -p seed:={int(seed)}"
            )
            if startup_timeout is not None:
                command += f" -p startup_timeout:={startup_timeout:g}"
            module["launch"] = [command]
    return spec


def write_yaml(path: str, data: dict) -> str:
    with open(path, "w", encoding="utf-8") as handle:
        yaml.safe_dump(data, handle, sort_keys=False)
    return path


def render(spec_file: str, inventory_file: str, render_dir: str, log_file: str) -> None:
    """Render with the deploy playbook (no cluster: kuberos_apply=false); raises with the log's tail on failure."""
    env = {
        **os.environ,
        "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"),
        "PATH": os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", "")]),
        "ANSIBLE_NOCOLOR": "1",
    }
    command = [
        os.path.join(os.path.dirname(sys.executable), "ansible-playbook"),
        os.path.join(ROOT, "playbooks", "deploy.yml"),
        "-i",
        inventory_file,
        "-e",
        f"rosdeployment_file={spec_file}",
        "-e",
        "kuberos_apply=false",
        "-e",
        f"kuberos_render_dir={render_dir}",
    ]
    with open(log_file, "w", encoding="utf-8") as log:
        done = subprocess.run(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, timeout=300)
    if done.returncode != 0:
        with open(log_file, encoding="utf-8") as log:
            tail = "".join(log.readlines()[-25:])
        raise RuntimeError(f"rendering {spec_file} failed (exit {done.returncode}); {log_file}:\n{tail}")
