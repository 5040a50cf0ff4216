#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Import a site described in the reference KubeROS format (ClusterInventory, Fleets) as an inventory file."""

from __future__ import annotations

DOCUMENTATION = r"""
module: reference_inventory_import
short_description: Import a reference KubeROS ClusterInventory and its Fleets as an inventory file
version_added: 0.3.0
description:
  - Reads a site described in the format of the reference KubeROS implementation (kuberos-io), one C(ClusterInventory)
    file and C(Fleet) files (C(apiVersion v1alpha)), and writes the Ansible inventory this collection reads (groups
    C(robots), C(edge), C(cloud), C(control_plane); C(kuberos_*) host variables) to O(dest). The mapping, field by
    field, is in C(docs/inventory.md) ("Importing a reference KubeROS site").
  - The reference format gives no CPU or memory; each host gets placeholders from O(default_cpu) and O(default_memory)
    (per C(kuberosRole)), marked as such in the file and listed in RV(notes).
  - The device parameters of C(peripheralDevices) go to C(kuberos_device_parameters) (device name to parameter name to
    value), beside C(kuberos_devices) (the device names).
  - A robot with several onboard computers (several hosts C(locatedInRobot) the same robot) keeps the first the
    ClusterInventory lists; the others are left out, with a note. A robot that no Fleet lists is left out, with a note,
    unless O(default_fleet) is given.
  - Every problem of the input (not a mapping, wrong kind, a missing or unknown field, a wrong type, an invalid name,
    a Fleet naming a robot the ClusterInventory does not have) fails the task, naming the file, the line and the
    field (C(hosts[2].peripheralDevices[0].deviceName)), all problems at once; nothing is written then.
  - The file is written only when its content changes, atomically. An existing O(dest) that this module did not write
    is replaced only with O(force).
options:
  cluster_inventory:
    description: The reference C(ClusterInventory) file (one YAML document of C(kind ClusterInventory)).
    type: path
    required: true
  fleets:
    description:
      - The reference C(Fleet) files; a file may hold several C(Fleet) documents. Each robot is in one fleet.
    type: list
    elements: path
    required: true
  dest:
    description: The inventory file to write (its directory is created when missing).
    type: path
    required: true
  default_cpu:
    description:
      - The C(kuberos_cpu) placeholder per C(kuberosRole) (C(onboard), C(control-plane), C(edge), C(cloud)); roles not
        given keep the built-in placeholders, 2 (onboard), 4 (control-plane), 8 (edge) and 8 (cloud).
    type: dict
    default: {}
  default_memory:
    description:
      - The C(kuberos_memory) placeholder per C(kuberosRole); roles not given keep the built-in placeholders, C(4Gi)
        (onboard), C(8Gi) (control-plane), C(16Gi) (edge) and C(32Gi) (cloud).
    type: dict
    default: {}
  default_shared:
    description:
      - C(kuberos_shared) of an edge, control-plane or cloud host that has no C(shared) field. The reference's default
        is false (such a host then serves no fleet until C(kuberos_fleets) lists some).
    type: bool
    default: false
  default_fleet:
    description:
      - The fleet of robots that no Fleet file lists. Unset, such robots are left out of the inventory, with a note.
    type: str
  force:
    description: Replace O(dest) also when it exists and was not written by this module.
    type: bool
    default: false
attributes:
  check_mode:
    support: full
  diff_mode:
    support: full
requirements:
  - PyYAML
extends_documentation_fragment:
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Import the reference site description of hall B
  kuberos.platform.reference_inventory_import:
    cluster_inventory: examples/reference/site/cluster_inventory.yml
    fleets:
      - examples/reference/site/fleet.yml
    dest: inventories/hall-b/hosts.yml
    default_cpu:
      onboard: 4
    default_memory:
      onboard: 8Gi
  register: imported

- name: Show what to fill in
  ansible.builtin.debug:
    var: imported.notes
"""

RETURN = r"""
dest:
  description: The inventory file written (or, in check mode, that would be written).
  returned: success
  type: str
notes:
  description:
    - What the user should check or fill in, one sentence each; the file's header lists them too.
    - The placeholders of C(kuberos_cpu) and C(kuberos_memory), hosts left out (second onboard computers, robots in no
      fleet), reference fields without an inventory variable, hosts that serve no fleet.
  returned: success
  type: list
  elements: str
  sample: ["kuberos_cpu and kuberos_memory are placeholders, as the reference format has no CPU or memory ..."]
groups:
  description: The members of each group written, in the order of the ClusterInventory.
  returned: success
  type: dict
  sample: {"robots": ["mir-1", "mir-2"], "edge": ["hall-b-master", "hall-b-edge-1"], "control_plane": ["hall-b-master"]}
inventory:
  description: The inventory written, as Ansible's YAML inventory structure (C(all.children.<group>.hosts)).
  returned: success
  type: dict
"""

import os
import tempfile

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reference_inventory import HEADER, import_files
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail

ARGUMENT_SPEC = dict(
    cluster_inventory=dict(type="path", required=True),
    fleets=dict(type="list", elements="path", required=True),
    dest=dict(type="path", required=True),
    default_cpu=dict(type="dict", default={}),
    default_memory=dict(type="dict", default={}),
    default_shared=dict(type="bool", default=False),
    default_fleet=dict(type="str"),
    force=dict(type="bool", default=False),
)


class DestError(KuberosError):
    """O(dest) cannot be read or may not be replaced."""


def existing_text(dest: str, force: bool) -> str | None:
    """The current content of ``dest`` (None when missing); ``DestError`` when it is not a file this module wrote."""
    if not os.path.lexists(dest):
        return None
    if not os.path.isfile(dest):
        raise DestError(f"dest {dest} exists and is not a regular file; expected the path of an inventory file")
    try:
        with open(dest, "rb") as handle:
            raw = handle.read()
    except OSError as exc:
        raise DestError(f"cannot read dest {dest}: {exc.strerror or exc}") from None
    text = raw.decode("utf-8", errors="replace")
    if HEADER not in text.split("\n")[:3] and not force:
        raise DestError(
            f"dest {dest} exists and was not written by this module (its header is missing): it is left as it is; "
            "choose another dest, or set force: true to replace it"
        )
    return text


def write(module: AnsibleModule, dest: str, text: str) -> None:
    """Write ``text`` to ``dest`` through a temporary file beside it and Ansible's atomic move."""
    directory = os.path.dirname(os.path.abspath(dest))
    os.makedirs(directory, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{os.path.basename(dest)}.", dir=directory)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
        module.atomic_move(temporary, dest)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def run(module: AnsibleModule) -> dict:
    params = module.params
    site = import_files(
        params["cluster_inventory"],
        params["fleets"],
        default_cpu=params["default_cpu"],
        default_memory=params["default_memory"],
        default_shared=params["default_shared"],
        default_fleet=params["default_fleet"],
    )
    text = site.text()
    dest = params["dest"]
    before = existing_text(dest, params["force"])
    changed = before != text
    result = {
        "changed": changed,
        "dest": dest,
        "notes": site.notes,
        "groups": site.groups,
        "inventory": site.inventory,
    }
    if module._diff:
        result["diff"] = {"before_header": dest, "after_header": dest, "before": before or "", "after": text}
    if changed and not module.check_mode:
        write(module, dest, text)
    return result


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    require_packages(module, ["PyYAML"])
    try:
        module.exit_json(**run(module))
    except KuberosError as exc:  # the reference files', or O(dest) that may not be replaced
        fail(module, exc)
    except OSError as exc:
        module.fail_json(msg=f"cannot write {module.params['dest']}: {exc.strerror or exc}")


if __name__ == "__main__":
    main()
