# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Names and fleets of the RosDeployments in a spec file."""

from __future__ import annotations

DOCUMENTATION = r"""
name: rosdeployment_targets
short_description: The name and target fleet of each RosDeployment in a spec file
version_added: 0.1.0
description:
  - Reads and validates a RosDeployment file (or spec data) and returns C({name, fleet}) for each document
    (C(metadata.name) and C(metadata.targetFleet)).
  - Fails with every validation problem (file, line, field path, reason).
options:
  _input:
    description: Path of a RosDeployment file, or one spec or a list of specs as data.
    type: raw
    required: true
  catalog:
    description: The software catalog that C(module) references resolve against (a directory or one file).
    type: path
    required: false
"""

EXAMPLES = r"""
- name: Which deployments does this file hold?
  ansible.builtin.debug:
    msg: "{{ 'examples/two-fleets.yml' | kuberos.platform.rosdeployment_targets }}"
"""

RETURN = r"""
_value:
  description: One C({name, fleet}) per deployment, in file order.
  type: list
  elements: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def rosdeployment_targets(spec, catalog=None):
    loaded = load_catalog(catalog) if catalog else None
    return [{"name": deployment.name, "fleet": deployment.fleet} for deployment in load_specs(spec, catalog=loaded)]


class FilterModule:
    def filters(self):
        return {"rosdeployment_targets": rosdeployment_targets}
