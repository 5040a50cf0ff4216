# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Kubernetes objects as one multi-document YAML file, written the way rendered manifests are written."""

from __future__ import annotations

DOCUMENTATION = r"""
name: manifest_yaml
short_description: Kubernetes objects as one multi-document YAML text, for people to read
version_added: 0.2.0
description:
  - Each object becomes a YAML document starting with C(---), keys in the order given, repeated values written
    in full and multi-line strings (scripts, embedded JSON) as literal blocks, as in the files
    P(kuberos.platform.rosdeployment_render#module) writes.
options:
  _input:
    description: Kubernetes objects.
    type: list
    elements: dict
    required: true
"""

EXAMPLES = r"""
- name: Write Calico's objects to one file
  ansible.builtin.copy:
    dest: rendered/calico/02-calico.yaml
    content: "{{ '10.244.0.0/16' | kuberos.platform.calico_manifests | kuberos.platform.manifest_yaml }}"
    mode: "0644"
"""

RETURN = r"""
_value:
  description: The objects as YAML documents, each starting with C(---).
  type: str
"""

import json

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifest_yaml import dump_object


def manifest_yaml(objects):
    # A JSON round trip turns Ansible's own str, dict and list types into the plain ones the dumper writes.
    return "".join("---\n" + dump_object(obj) for obj in json.loads(json.dumps(list(objects))))


class FilterModule:
    def filters(self):
        return {"manifest_yaml": manifest_yaml}
