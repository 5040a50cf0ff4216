# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The edge servers and cloud VMs a robot measures its round-trip time to, with their addresses."""

from __future__ import annotations

DOCUMENTATION = r"""
name: rtt_targets
short_description: The robot of an inventory host and the edge and cloud nodes to measure its round-trip time to
version_added: 0.1.0
description:
  - For one robot host of the inventory, returns the robot's name, fleet and node name, and the edge and cloud
    hosts to ping from it, each with its node name (the key of the C(kuberos.io/rtt-ms) annotation) and address.
  - By default the targets are every host of the C(edge) and C(cloud) groups that the robot's fleet may use
    (shared, or listing the fleet in C(kuberos_fleets)); O(targets) picks some of them by inventory name.
  - A target's address is its C(kuberos_address) host variable, else C(ansible_host), else its inventory name.
options:
  _input:
    description: The fleet inventory, as returned by P(kuberos.platform.fleet_inventory#filter).
    type: dict
    required: true
  hostvars:
    description: The C(hostvars) magic variable (for C(kuberos_address) and C(ansible_host)).
    type: raw
    required: true
  robot_host:
    description: The inventory name of the robot host (C(inventory_hostname) in a play on the C(robots) group).
    type: str
    required: true
  targets:
    description: Inventory names of edge or cloud hosts to measure; empty for every one the robot's fleet may use.
    type: list
    elements: str
    default: []
"""

EXAMPLES = r"""
- name: What this robot measures
  ansible.builtin.set_fact:
    probe: >-
      {{ groups | kuberos.platform.fleet_inventory(hostvars) | kuberos.platform.rtt_targets(hostvars, inventory_hostname) }}
"""

RETURN = r"""
_value:
  description: The robot and its targets.
  type: dict
  contains:
    robot:
      description:
        - The robot's name (C(kuberos_robot), else the inventory name); its node carries it in the label
          C(robot.kuberos.io/name).
      type: str
    fleet:
      description: The robot's fleet.
      type: str
    node:
      description: The node name of the robot's own computer in the resource model.
      type: str
    targets:
      description: One C({name, host, tier, address}) per target, by node name; C(name) is the node name the scheduler uses.
      type: list
      elements: dict
"""

from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import did_you_mean
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import host_address


def _node_name(raw: dict, host: str) -> str:
    return str(raw["hosts"][host].get("kuberos_node_name", host))


@reports_kuberos_errors
def rtt_targets(raw, hostvars, robot_host, targets=None):
    inventory = load_inventory(raw)
    robots = raw["groups"].get("robots", [])
    if robot_host not in robots:
        raise AnsibleFilterError(f"rtt_targets: {robot_host} is not a host of the robots group{did_you_mean(robot_host, robots)}")
    own = inventory.nodes[_node_name(raw, robot_host)]
    candidates = {host: group for group in ("edge", "cloud") for host in raw["groups"].get(group, [])}
    wanted = list(targets or [])
    unknown = [t for t in wanted if t not in candidates]
    if unknown:
        problems = [f"'{t}' is not a host of the edge or cloud groups{did_you_mean(t, candidates)}" for t in unknown]
        raise AnsibleFilterError("rtt_targets: " + "; ".join(problems))
    chosen = []
    for host in wanted or sorted(candidates):
        node = inventory.nodes[_node_name(raw, host)]
        if not wanted and not node.serves_fleet(own.fleet):
            continue
        chosen.append({"name": node.name, "host": host, "tier": node.tier, "address": host_address(hostvars[host], host)})
    return {"robot": own.robot, "fleet": own.fleet, "node": own.name, "targets": sorted(chosen, key=lambda t: t["name"])}


class FilterModule:
    def filters(self):
        return {"rtt_targets": rtt_targets}
