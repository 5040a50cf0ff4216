#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Reserve a robot of the pool to develop on it, or give it back."""

from __future__ import annotations

DOCUMENTATION = r"""
module: robot_pool
short_description: Reserve a robot of the robot pool to develop on it, or give it back
version_added: 0.4.0
description:
  - With O(state=present), reserves O(robot) for O(owner) until O(until), with a O(reason), as a ConfigMap in the
    fleet's namespace (C(kuberos-reservation-<robot>), label C(kuberos.io/reservation)). Reserving a robot the owner
    holds already renews it (a new end, a new reason). A robot someone else holds is refused, naming who and until
    when; a reservation whose time has passed holds nothing and is replaced.
  - While it holds, production deployments (without C(metadata.developer)) leave the robot out - their next deploy
    or rollout places nothing for it and stops what they ran there; C(production) lists the ones that still run
    modules for it. A development deployment (C(metadata.developer) of the owner) may run on it.
  - With O(state=absent), gives the robot back (only its holder, unless O(force)); the fleet's production deployments
    return to it on their next pass.
  - C(passes) names the production deployments whose pass changes what runs for the robot now (their records say
    so), with their current revision; P(kuberos.platform.rosdeployment_rollout#module) at that revision is the pass,
    and C(playbooks/pool.yml) runs it at once.
  - P(kuberos.platform.robot_pool_info#module) reads every reservation of every fleet.
  - A reservation that cannot be read (a field missing, a time out of range, an owner or a reason the pool would not
    write) holds nothing; each one is a warning naming its ConfigMap and why, and is left out. Reserving the robot
    replaces it; giving the robot back removes it.
  - Ownership is advisory. The API server is asked who the caller is (a SelfSubjectReview, Kubernetes 1.28+), and the
    reservation records that Kubernetes user (C(identity)); a reservation that records one is renewed or given back
    (without O(force)) only by that user. O(owner) is a name the caller gives, not checked against that user, and
    whoever may write ConfigMaps in the fleet's namespace can change or remove a reservation. C(ownership) says so in
    every answer (docs/security.md).
  - Robots are the inventory's; the fleet is the robot's fleet there.
options:
  robot:
    description: The robot, as the inventory names it.
    type: str
    required: true
  owner:
    description:
      - Who holds it (the name a development deployment gives in C(metadata.developer)).
      - Letters and digits with C(-), C(_), C(.) and C(@) inside, at most 63 characters.
    type: str
    required: true
  reason:
    description: Why, for the others who see the reservation (status, dashboard); one printable line (no tab, line
      break or other control character), at most 200 characters.
    type: str
    default: ""
  until:
    description:
      - When the reservation ends - a duration from now (C(90m), C(4h), C(2d)) or a time (C(2026-11-28T18:00:00Z)).
      - At most 90 days ahead (C(90d), C(2160h)); a time is RFC 3339 with a zone. Anything else is refused, naming
        the option and the bound.
    type: str
    default: 8h
  state:
    description: C(present) reserves (or renews), C(absent) releases.
    type: str
    choices: [present, absent]
    default: present
  force:
    description: With O(state=absent), release a robot that someone else holds.
    type: bool
    default: false
  inventory:
    description:
      - The fleet inventory, as returned by the P(kuberos.platform.fleet_inventory#filter) filter.
    type: dict
    required: true
attributes:
  check_mode:
    support: full
    details: Reads the reservation and says what would change; writes nothing.
  diff_mode:
    support: full
    details: The reservation before and after.
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Reserve fetch-2 for an afternoon of testing
  kuberos.platform.robot_pool:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    robot: fetch-2
    owner: alice
    reason: testing the new grasp planner
    until: 4h

- name: Give it back
  kuberos.platform.robot_pool:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    robot: fetch-2
    owner: alice
    state: absent
"""

RETURN = r"""
reservation:
  description: The reservation after the task (C(robot), C(fleet), C(owner), C(reason), C(until), C(since)); empty when released.
  returned: always
  type: dict
previous:
  description: The reservation before the task, with C(active) (false when its time had passed); empty when there was none.
  returned: always
  type: dict
production:
  description: The production deployments that still run modules for the robot (their next deploy stops them).
  returned: always
  type: list
  elements: str
passes:
  description:
    - The production deployments whose pass stops what they run for the robot (reserved) or returns to it (given
      back), from their records - C(deployment), C(fleet), C(revision) (their current one) each.
    - In check mode, those a pass would change after the task.
  returned: always
  type: list
  elements: dict
message:
  description: One line saying what holds now.
  returned: always
  type: str
identity:
  description: The Kubernetes user the API server says the caller is (a SelfSubjectReview); empty when it cannot tell.
  returned: always
  type: str
ownership:
  description: What the owner's name guarantees and what it does not (advisory), in one sentence.
  returned: always
  type: str
ignored:
  description: The reservations that cannot be read (they hold nothing), one warning each naming the ConfigMap and why.
  returned: always
  type: list
  elements: str
"""

import datetime

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.robot_pool import (
    PoolRefused,
    release,
    reservations,
    reserve,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, Kube, api_clients


def _text(reservation) -> str:
    if reservation is None:
        return ""
    return "\n".join(f"{k}: {v}" for k, v in reservation.to_dict().items()) + "\n"


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            robot=dict(type="str", required=True),
            owner=dict(type="str", required=True),
            reason=dict(type="str", default=""),
            until=dict(type="str", default="8h"),
            state=dict(type="str", choices=["present", "absent"], default="present"),
            force=dict(type="bool", default=False),
            inventory=dict(type="dict", required=True),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    p = module.params
    ignored: list[str] = []
    try:
        kube = Kube(api_clients(p["kubeconfig"]), "kuberos-pool")
        inventory = load_inventory(p["inventory"])
        if p["robot"] not in inventory.robots:
            known = ", ".join(sorted(inventory.robots)[:20]) or "none"
            raise PoolRefused(f"{p['robot']} is not a robot of the inventory; its robots: {known}")
        fleet = inventory.robots[p["robot"]].fleet
        reservations(kube, fleet, warn=ignored.append)
        for warning in ignored:
            module.warn(warning)
        if p["state"] == "present":
            done = reserve(kube, fleet, p["robot"], p["owner"], p["reason"], p["until"], module.check_mode)
        else:
            done = release(kube, fleet, p["robot"], p["owner"], p["force"], module.check_mode)
    except Exception as exc:  # refused, a bad time, or the cluster's error: one clear line
        fail(module, exc, p["kubeconfig"])
    before, after = done["before"], done["after"]
    now = datetime.datetime.now(datetime.UTC)
    if after is not None:
        message = f"{p['robot']} (fleet {fleet}) is {after.describe()}"
        if done["production"]:
            message += f"; still running for production: {', '.join(done['production'])} (their next pass stops it there)"
    else:
        message = f"{p['robot']} (fleet {fleet}) is in the pool; the fleet's deployments return to it on their next pass"
    result = {
        "changed": done["changed"],
        "reservation": after.to_dict() if after else {},
        "previous": before.to_dict(now) if before else {},
        "production": done["production"],
        "passes": done["passes"],
        "message": message,
        "identity": done["identity"],
        "ownership": done["ownership"],
        "ignored": ignored,
    }
    if module._diff:
        result["diff"] = {"before": _text(before), "after": _text(after)}
    module.exit_json(**result)


if __name__ == "__main__":
    main()
