# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Names of the RosDeployments in a spec file."""

from __future__ import annotations

DOCUMENTATION = r"""
name: rosdeployment_names
short_description: The names of the RosDeployments in a spec file
version_added: 0.1.0
description:
  - Reads and validates a RosDeployment file (or spec data) and returns the C(metadata.name) of each document.
  - Fails with every validation problem (file, line, field path, reason).
options:
  _input:
    description: Path of a RosDeployment file, or one spec or a list of specs as data.
    type: raw
    required: true
"""

EXAMPLES = r"""
- name: Which deployments does this file hold?
  ansible.builtin.debug:
    msg: "{{ 'examples/two-fleets.yml' | kuberos.platform.rosdeployment_names }}"
"""

RETURN = r"""
_value:
  description: The deployment names, in file order.
  type: list
  elements: str
"""

from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs


def rosdeployment_names(spec):
    try:
        return [deployment.name for deployment in load_specs(spec)]
    except KuberosError as exc:
        raise AnsibleFilterError(str(exc)) from None


class FilterModule:
    def filters(self):
        return {"rosdeployment_names": rosdeployment_names}
