# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The scheduler as a filter: a thin adapter over module_utils/kuberos/scheduler.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: place_modules
short_description: Place every module of every robot of a RosDeployment
version_added: 0.1.0
description:
  - Reads and validates a RosDeployment (a file path, or the spec as data) and places every module
    instance of every selected robot, and the fleet's discovery servers, on nodes of the inventory.
  - Hard requirements first (onboard, max_latency, cpu/memory/gpu against remaining capacity, arch,
    devices), then the preference order, then the node left with the most free capacity.
  - Fails with every validation problem (file, line, field path, reason), or with a per-node account of
    why each candidate node was rejected for a module that cannot be placed.
options:
  _input:
    description: Path of a RosDeployment file (one or more YAML documents), or one spec or a list of specs as data.
    type: raw
    required: true
  inventory:
    description: The fleet inventory, as returned by the P(kuberos.platform.fleet_inventory#filter) filter.
    type: dict
    required: true
  allocated:
    description: "Resources already used per node by other workloads, as C({node: {cpu, memory, gpu, pods}})."
    type: dict
    required: false
  unavailable:
    description:
      - "Nodes that must take nothing, with why, as C({node: reason}): e.g. nodes that are NotReady or missing in the
        cluster (P(kuberos.platform.node_allocations#module) returns them)."
    type: dict
    required: false
  previous:
    description:
      - What runs now (C(previous) of P(kuberos.platform.node_allocations#module)). Instances that still fit where
        they run stay there, and the fleets' discovery servers stay on their nodes (sticky placement).
    type: dict
    required: false
  catalog:
    description: The software catalog (a directory of catalog files, or one file) that C(module) references resolve against.
    type: path
    required: false
"""

EXAMPLES = r"""
- name: Collect the resource model
  ansible.builtin.set_fact:
    fleet: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"

- name: Place the modules of the paper's Listing 1
  ansible.builtin.set_fact:
    placement: "{{ 'examples/listing1.yml' | kuberos.platform.place_modules(fleet) }}"
"""

RETURN = r"""
_value:
  description:
    - The placement. C(placements) has one entry per robot and module with C(robot), C(module), C(node),
      C(tier) (onboard, edge or cloud), C(reason), C(instance) and C(robots) (every robot that instance serves).
    - C(instances) has one entry per module instance, C(discovery) the discovery servers of each fleet.
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def place_modules(spec, inventory, allocated=None, unavailable=None, previous=None, catalog=None):
    loaded = load_catalog(catalog) if catalog else None
    _deployments, placement = load_and_place(spec, inventory, allocated, unavailable, previous=previous, catalog=loaded)
    return placement.to_dict()


class FilterModule:
    def filters(self):
        return {"place_modules": place_modules}
