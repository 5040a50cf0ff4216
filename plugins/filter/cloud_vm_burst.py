# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""How many VMs a fleet should have for the capacity the controller says it lacks: a thin adapter over
module_utils/kuberos_cluster/cloud.py (``burst``)."""

from __future__ import annotations

DOCUMENTATION = r"""
name: cloud_vm_burst
short_description: The VM count and the idle VMs to release, from the controller's capacity demand
version_added: 0.3.0
description:
  - Takes the site's VMs as P(amazon.aws.ec2_instance_info#module) returns them, the settings of the C(cloud_vms)
    role, the fleet's C(kuberos-capacity) ConfigMap (as P(kubernetes.core.k8s_info#module) returns it; none when
    absent) and the KubeROS pods of the cluster, and returns how many VMs the fleet should have and which idle VMs
    to release (docs/cloud.md, burst).
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
  configmaps:
    description: The C(resources) of P(kubernetes.core.k8s_info#module) for the ConfigMap C(kuberos-capacity).
    type: list
    elements: dict
    required: true
  pods:
    description: The C(resources) of P(kubernetes.core.k8s_info#module) for the KubeROS pods (their C(spec.nodeName)).
    type: list
    elements: dict
    required: true
  release_after:
    description: Seconds without demand before an idle VM is released.
    type: float
    required: true
  now:
    description: The time now, seconds since the epoch.
    type: float
    required: true
"""

EXAMPLES = r"""
- name: Size the fleet's VMs for the demand
  ansible.builtin.set_fact:
    burst: "{{ found.instances | kuberos.platform.cloud_vm_burst(settings, demand.resources, pods.resources, 300, now) }}"
"""

RETURN = r"""
_value:
  description: C(count), the VMs the fleet should have; C(release), the idle VMs to release; C(why), one line.
  type: dict
"""

import json

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cloud import (
    burst,
    load_settings,
    vms_from_instances,
)
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain


@reports_kuberos_errors
def cloud_vm_burst(instances, settings, configmaps, pods, release_after, now):
    checked = load_settings(plain({**settings, "count": 0, "release": []}))
    demand = None
    for configmap in plain(configmaps) or []:
        try:
            demand = json.loads(((configmap or {}).get("data") or {}).get("demand.json") or "null")
        except ValueError:
            demand = None
    busy = {((pod or {}).get("spec") or {}).get("nodeName") for pod in plain(pods) or []}
    return burst(
        demand, vms_from_instances(plain(instances)), busy, checked.request, checked.budget, float(now), float(release_after)
    ).as_dict()


class FilterModule:
    def filters(self):
        return {"cloud_vm_burst": cloud_vm_burst}
