#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Remove the cluster objects of a RosDeployment that are no longer rendered."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_prune
short_description: Remove the objects of RosDeployments that are no longer rendered
version_added: 0.1.0
description:
  - Lists the objects KubeROS manages (Deployments, Services, ConfigMaps) in the namespaces of O(fleets),
    and deletes those that belong to one of O(deployments) but are not in O(keep). A module removed from
    the spec loses its Deployment and ConfigMap; nothing of other deployments is touched.
  - Discovery servers of a fleet are pruned to those in O(keep); with O(keep) empty (undeploy) they are
    removed only when no other deployment runs in the fleet. Namespaces are never removed.
options:
  deployments:
    description: Names of the RosDeployments concerned.
    type: list
    elements: str
    required: true
  fleets:
    description: Fleets of those deployments.
    type: list
    elements: str
    required: true
  keep:
    description: Objects to keep (the rendered objects); empty removes the deployments.
    type: list
    elements: dict
    default: []
attributes:
  check_mode:
    support: full
  diff_mode:
    support: full
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Remove what the spec no longer renders
  kuberos.platform.rosdeployment_prune:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    deployments: [pick-and-place]
    fleets: [test-fleet]
    keep: "{{ rendered.objects }}"
"""

RETURN = r"""
removed:
  description: The objects deleted (or that would be, in check mode), as C(Kind/namespace/name).
  returned: always
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import (
    delete_object,
    managed_objects,
    stale_objects,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, api_clients


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            deployments=dict(type="list", elements="str", required=True),
            fleets=dict(type="list", elements="str", required=True),
            keep=dict(type="list", elements="dict", default=[]),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    params = module.params
    removed = []
    try:
        clients = api_clients(params["kubeconfig"])
        for fleet in sorted(set(params["fleets"])):
            namespace = fleet_namespace(fleet)
            live = managed_objects(clients, namespace)
            others = [
                o
                for o in live
                if o["metadata"]["labels"].get(COMPONENT) == "ros-module"
                and o["metadata"]["labels"].get("kuberos.io/deployment") not in params["deployments"]
            ]
            undeploy = not params["keep"]
            stale = stale_objects(live, params["keep"], params["deployments"], remove_discovery=not (undeploy and others))
            for obj in stale:
                removed.append(f"{obj['kind']}/{namespace}/{obj['metadata']['name']}")
                if not module.check_mode:
                    delete_object(clients, obj)
    except Exception as exc:  # a KubeROS error, or the cluster's: one clear line, no traceback
        fail(module, exc, module.params["kubeconfig"], removed=removed)
    result = {"changed": bool(removed), "removed": removed}
    if module._diff:
        result["diff"] = {"before": "\n".join(removed) + ("\n" if removed else ""), "after": ""}
    module.exit_json(**result)


if __name__ == "__main__":
    main()
