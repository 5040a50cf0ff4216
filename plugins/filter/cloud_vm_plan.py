# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What to launch and release for a fleet's cloud VMs: a thin adapter over module_utils/kuberos_cluster/cloud.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cloud_vm_plan
short_description: What to launch, release and keep so that a fleet has the cloud VMs it asks for, within the budget
version_added: 0.3.0
description:
  - Takes the site's VMs as P(amazon.aws.ec2_instance_info#module) returns them and the settings of the
    C(cloud_vms) role, and returns the plan of C(kuberos_cluster/cloud.py) (docs/cloud.md).
  - A request beyond the budget (most VMs at the site, a type's own maximum, the price per hour) launches what fits
    and refuses the rest, naming the limit.
options:
  _input:
    description: The C(instances) of P(amazon.aws.ec2_instance_info#module), with their tags.
    type: list
    elements: dict
    required: true
  settings:
    description: The settings, as P(kuberos.platform.cloud_vm_settings#filter) takes them.
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Plan
  ansible.builtin.set_fact:
    plan: "{{ found.instances | kuberos.platform.cloud_vm_plan(settings) }}"
"""

RETURN = r"""
_value:
  description:
    - C(launch), a list of C(name), C(instance_type), C(tags) and C(vpn_address) of the VMs to launch.
    - C(release), a list of C(name), C(instance_id) and C(instance_type) of the VMs to release (drained first).
    - C(keep), the names of the fleet's VMs that stay; C(refused), what is not done (C(action), C(count),
      C(instance_type), C(name), C(reason)); C(changes), whether anything is launched or released; C(summary), one line.
  type: dict
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cloud import (
    load_settings,
    plan,
    vms_from_instances,
)
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def cloud_vm_plan(instances, settings):
    checked = load_settings(plain(settings))
    return plan(checked.request, vms_from_instances(plain(instances)), checked.budget).as_dict()


class FilterModule:
    def filters(self):
        return {"cloud_vm_plan": cloud_vm_plan}
