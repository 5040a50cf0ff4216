#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Roll a deployed RosDeployment out to a new state across its fleet, in waves with health gates."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_rollout
short_description: Roll a deployed RosDeployment out to new module versions in waves, with canaries, gates and rollback
version_added: 0.2.0
description:
  - Moves one deployed RosDeployment to a new state (a changed spec, typically new catalog versions of its modules), or
    back to a kept revision (O(revision)), robot by robot. Only the robots whose modules change are touched; placement
    is sticky (what still fits where it runs stays there) and the fleet's discovery servers are never touched.
  - A canary set of robots goes first, then waves of O(wave_size) robots. After each wave a health gate, where every replaced
    instance runs exactly one pod of its new state, Running and Ready on its placed node, within O(gate_timeout), no
    restart, crash loop or failed pod during the O(soak) window; then, when given, the O(ros_probe) command exits 0.
  - A failed gate stops the rollout and gives every robot touched so far its previous objects back (objects created
    for the rollout are removed); robots not yet reached are never touched, and the deployment stays at its revision.
  - Per robot, a module with upgrade C(surge) keeps its old pod until the new one is Ready; one with C(recreate)
    (a module that must never run twice) stops first, and the seconds it had no Ready pod are its downtime.
  - Before anything is written every object is dry-run server-side. While it runs, the deployment record carries a
    rollout marker and the controller moves none of the deployment's modules. Success writes the record and a new
    numbered revision (the last 10 are kept).
options:
  src:
    description: The RosDeployment file of the new state. Required unless O(revision) is given.
    type: path
  deployment:
    description: The deployment to roll out, when O(src) holds several; required with O(revision).
    type: str
  fleet:
    description: The deployment's fleet; required with O(revision).
    type: str
  revision:
    description: Roll back (or forward) to this kept revision of O(deployment) instead of O(src).
    type: int
  catalog:
    description: The software catalog that C(module) references of O(src) resolve against.
    type: path
  inventory:
    description: The fleet resource model (P(kuberos.platform.fleet_inventory#filter)).
    type: dict
    required: true
  canary:
    description: How many robots form the canary wave (the first robots of the fleet with a change); 0 to 10000.
    type: int
    default: 1
  canary_robots:
    description: The canary robots by name, instead of the first O(canary) ones.
    type: list
    elements: str
    default: []
  wave_size:
    description: Robots per wave after the canary; 1 to 10000.
    type: int
    default: 10
  soak:
    description: Seconds each wave's new pods must stay Ready without a restart; 0 to 3600.
    type: float
    default: 5
  gate_timeout:
    description: Seconds a wave's pods have to be Running and Ready on their placed nodes; above 0, at most 3600.
    type: float
    default: 120
  ros_probe:
    description:
      - A command (argv list) run after each wave's soak, with C(KUBEROS_NAMESPACE), C(KUBEROS_ROBOTS),
        C(KUBEROS_INSTANCES) and C(KUBEROS_MODULES) in its environment; a non-zero exit fails the gate. The collection
        ships one that looks for the wave's ROS 2 nodes through the fleet's discovery servers (docs/software.md).
    type: list
    elements: str
    default: []
  update_lock:
    description:
      - A command (argv list) run before each wave with C(KUBEROS_ROBOTS) (the wave's robots) in its environment, which
        waits (at most O(update_lock_wait) seconds) until no robot of the wave holds its update lock. Exit 0, every
        robot is free; exit 1 with a line C(held:) and the robot's name per robot that still holds it, those robots are left
        pending (none of their modules is touched; the next rollout run finishes them). A command that cannot say
        (another exit, or still running O(update_lock_wait) + 30 s later) leaves the whole wave pending. The collection
        ships one, the ROS graph probe with C(--absent '/{robot}/kuberos_update_lock') (docs/software.md).
    type: list
    elements: str
    default: []
  update_lock_wait:
    description:
      - Seconds the O(update_lock) command may wait for the robots' locks (it is given no more than this + 30 s); above 0,
        at most 3600.
    type: float
    default: 120
  prestage:
    description:
      - Before the first wave, pull each robot's new images onto the robot (a short-lived pod per robot computer that
        only pulls), so that no robot's downtime includes pulling an image over its link. Robots that are offline
        are left out (they are pending). A failed pull is reported and the waves go on (their gates see it).
    type: bool
    default: true
  prestage_timeout:
    description:
      - Seconds the pre-pulls may take in all; robots still pulling then are reported and the waves go on. Above 0, at
        most 86400.
    type: float
    default: 600
  prestage_parallel:
    description: Robots pulling at the same time; 1 to 1000.
    type: int
    default: 10
attributes:
  check_mode:
    support: full
    details: Plans the waves and reports, per robot, what would change; writes nothing.
  diff_mode:
    support: full
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.render
  - kuberos.platform.graph_check
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Upgrade the pick-and-place modules, canary first, then 10 robots at a time
  kuberos.platform.rosdeployment_rollout:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    src: examples/pick-and-place-catalog.yml
    catalog: inventories/local/catalog
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    wave_size: 10

- name: Back to revision 3
  kuberos.platform.rosdeployment_rollout:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    deployment: pick-and-place
    fleet: test-fleet
    revision: 3
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
"""

RETURN = r"""
revision:
  description: The deployment's revision afterwards (unchanged when the rollout failed or in check mode, the planned one).
  returned: always
  type: int
from_revision:
  description: The revision before.
  returned: always
  type: int
per_robot:
  description: Per robot, one line per module that changes (C((fleet)) for objects of no single robot).
  returned: always
  type: dict
plan:
  description: C(prepare), C(waves) (number, canary, robots, changes) and C(removals), and the C(untouched) robots.
  returned: always
  type: dict
waves:
  description: The waves that passed their gate, with the seconds each took.
  returned: when not in check mode
  type: list
downtime_s:
  description: Per replaced instance, the seconds it had no Ready pod.
  returned: when not in check mode
  type: dict
max_module_downtime_s:
  description: The longest of RV(downtime_s).
  returned: when not in check mode
  type: float
left_out:
  description: The robots the rollout left out because the robot pool holds them, and why.
  returned: always
  type: dict
summary:
  description: What changed (or would change), per robot and per wave, as lines of text.
  returned: always
  type: str
locked_robots:
  description: Robots left pending because they held their update lock (or it could not be checked), and why.
  returned: when a robot was left pending for its lock
  type: dict
prestage:
  description:
    - The pre-pulls before the first wave (O(prestage)) - robots, images, seconds in all, seconds until each robot
      had its images (done_after_s), problems.
  returned: when images were pre-pulled
  type: dict
prestage_plan:
  description: Per robot computer, the new images its waves need (what O(prestage) pulls).
  returned: always
  type: dict
pending_robots:
  description:
    - Robots that were offline (their computer's node not Ready). None of their modules was touched and nothing waited
      for them. The next rollout run (the same spec again) finishes them once they are back.
  returned: always
  type: list
  elements: str
rolled_back_robots:
  description: The robots given their previous state after a failed gate.
  returned: when a gate failed
  type: list
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.rollout import option_problem
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import RENDER_ARGS
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.rollout_runner import execute
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, api_clients
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import GRAPH_CHECK_ARGS

ARGUMENT_SPEC = dict(
    **KUBECONFIG_ARG,
    src=dict(type="path"),
    deployment=dict(type="str"),
    fleet=dict(type="str"),
    revision=dict(type="int"),
    catalog=dict(type="path"),
    inventory=dict(type="dict", required=True),
    canary=dict(type="int", default=1),
    canary_robots=dict(type="list", elements="str", default=[]),
    wave_size=dict(type="int", default=10),
    soak=dict(type="float", default=5.0),
    gate_timeout=dict(type="float", default=120.0),
    ros_probe=dict(type="list", elements="str", default=[]),
    update_lock=dict(type="list", elements="str", default=[]),
    update_lock_wait=dict(type="float", default=120.0),
    prestage=dict(type="bool", default=True),
    prestage_timeout=dict(type="float", default=600.0),
    prestage_parallel=dict(type="int", default=10),
    **RENDER_ARGS,
    **GRAPH_CHECK_ARGS,
)


def diff_of(result: dict) -> dict:
    before = [f"revision {result['from_revision']}"] + [f"  {m}: {v}" for m, v in sorted(result["versions"]["before"].items())]
    after = [f"revision {result['revision']}"] + [f"  {m}: {v}" for m, v in sorted(result["versions"]["after"].items())]
    for robot, lines in result["per_robot"].items():
        after.append(f"{robot}:")
        after.extend(f"  {line}" for line in lines)
    return {
        "before_header": "deployed",
        "after_header": "rollout",
        "before": "\n".join(before) + "\n",
        "after": "\n".join(after) + "\n",
    }


def summary_of(result: dict, check_mode: bool) -> str:
    """What the rollout changed (or would change), for people."""
    lines = [
        f"{result['deployment']}: revision {result['from_revision']} -> {result['revision']}"
        + (" (check mode: nothing written)" if check_mode else "")
    ]
    lines += [f"{robot}: {'; '.join(changes)}" for robot, changes in result["per_robot"].items()] or ["nothing to change"]
    locked = result.get("locked_robots") or {}
    offline = [r for r in result.get("pending_robots", []) if r not in locked]
    if offline:
        lines.append(f"pending, offline (the next rollout run finishes them): {', '.join(offline)}")
    if result.get("left_out"):
        reserved = "; ".join(f"{r} ({why})" for r, why in sorted(result["left_out"].items()))
        lines.append(f"left out, reserved in the robot pool: {reserved}")
    if locked:
        lines.append(
            "pending, update lock (the next rollout run finishes them): " + ", ".join(f"{r} ({why})" for r, why in locked.items())
        )
    if check_mode and result.get("prestage_plan"):
        lines.append(f"would pre-pull onto {len(result['prestage_plan'])} robot(s) before the first wave")
    if result.get("prestage"):
        staged = result["prestage"]
        lines.append(
            f"pre-pulled {len(staged['images'])} image(s) onto {len(staged['done_after_s'])}/{staged['robots']} robot(s) "
            f"in {staged['seconds']} s" + (f"; problems: {'; '.join(staged['problems'])}" if staged["problems"] else "")
        )
    for wave in result.get("waves", []):
        label = "canary" if wave["canary"] else f"wave {wave['number']}"
        lines.append(f"{label}: {len(wave['robots'])} robot(s) in {wave['seconds']} s")
    if "max_module_downtime_s" in result:
        lines.append(f"longest time a module had no Ready pod: {result['max_module_downtime_s']} s; total {result['total_s']} s")
    return "\n".join(lines)


def main():
    module = AnsibleModule(
        argument_spec=ARGUMENT_SPEC,
        required_one_of=[("src", "revision")],
        mutually_exclusive=[("src", "revision")],
        required_by={"revision": ("deployment", "fleet")},
        supports_check_mode=True,
    )
    require_packages(module)
    why = option_problem(module.params)
    if why:
        module.fail_json(msg=why)
    progress = []
    try:
        result = execute(api_clients(module.params["kubeconfig"]), module.params, module.check_mode, progress.append)
    except KuberosError as exc:  # the spec's, a rollout in progress
        fail(module, exc)
    except Exception as exc:  # the cluster's: one clear line, no traceback
        fail(module, exc, module.params["kubeconfig"], progress=progress)
    result["progress"] = progress
    result["summary"] = summary_of(result, module.check_mode)
    if module._diff:
        result["diff"] = diff_of(result)
    if result.get("ok") is False:
        where = "the canary" if result["failed_canary"] else f"wave {result['failed_wave']}"
        module.fail_json(
            msg=(
                f"rollout of {result['deployment']} stopped at {where}: "
                f"{result['why']}; rolled back robots {', '.join(result['rolled_back_robots'])}"
                + (f"; not back yet: {', '.join(result['not_back'])}" if result["not_back"] else "")
            ),
            **{k: v for k, v in result.items() if k != "changed"},
            changed=True,
        )
    module.exit_json(**result)


if __name__ == "__main__":
    main()
