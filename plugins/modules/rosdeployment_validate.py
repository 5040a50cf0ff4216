#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Validate a RosDeployment file before anything reads the cluster or renders (documentation; the action plugin of
the same name does the work, on the controller, like the filters that read spec files)."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_validate
short_description: Validate a RosDeployment file against the schema, the catalog and the inventory
version_added: 0.2.0
description:
  - Reads and validates a RosDeployment file (every document), resolves its catalog references against O(catalog),
    checks it against O(inventory) (fleets, robots, third-party clusters) and that its modules could be placed on
    the inventory's nodes with nothing else running.
  - On failure, C(msg) is one line that says what failed and C(problems) lists every problem, one line each, with
    the file, the line, the field and the reason, so that a failing spec is reported once, by this task.
  - Reads nothing but the files; changes nothing. Runs on the controller (an action plugin), where the spec file is,
    as the P(kuberos.platform.place_modules#filter) filter does; a relative O(src) is relative to the current directory.
attributes:
  action:
    support: full
  check_mode:
    support: full
  diff_mode:
    support: none
options:
  src:
    description: Path of the RosDeployment file.
    type: path
    required: true
  catalog:
    description: The software catalog (a directory of catalog files, or one file) that C(module) references resolve against.
    type: path
  inventory:
    description: The fleet resource model (P(kuberos.platform.fleet_inventory#filter)). Without it, only the file is checked.
    type: dict
extends_documentation_fragment:
  - kuberos.platform.attributes
  - kuberos.platform.attributes.action
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Validate the RosDeployment
  kuberos.platform.rosdeployment_validate:
    src: examples/pick-and-place.yml
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
  register: validated
"""

RETURN = r"""
deployments:
  description: One C({name, fleet}) per RosDeployment of the file, in file order.
  returned: success
  type: list
  elements: dict
placement:
  description:
    - With O(inventory), the placement on the inventory's nodes with nothing else running (for steps that need the
      deployments' fleets and bridges only; the deploy places again with what runs in the cluster).
  returned: success and O(inventory) given
  type: dict
problems:
  description: Every problem, one line each (file:line, field, reason).
  returned: failure
  type: str
"""
