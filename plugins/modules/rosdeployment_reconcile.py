#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""One pass of the KubeROS controller, on demand."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_reconcile
short_description: One pass of the KubeROS controller, on demand
version_added: 0.2.0
description:
  - Reads every deployment record, the nodes and the KubeROS pods once and does what the controller does in one
    pass, with the same code - move module instances off nodes that have been NotReady for at least O(grace)
    seconds (from the Ready condition's last transition) or that left the cluster, off nodes their pod keeps
    failing on, and off nodes whose measured round-trip time (the robot node's C(kuberos.io/rtt-ms) annotation)
    breaks the module's C(max_latency); re-pin their Deployments; delete pods left on nodes that are down;
    write Events and the status ConfigMaps.
  - Onboard modules of a robot whose computer is down are not moved; they are reported as stranded.
  - In check mode nothing is written; the result says what would move.
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
options:
  grace:
    description: Seconds a node must have been NotReady before its modules move.
    type: float
    default: 5.0
  restart_threshold:
    description: Container restarts at which a pod counts as failing.
    type: int
    default: 3
attributes:
  check_mode:
    support: full
  diff_mode:
    support: none
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: One reconcile pass
  kuberos.platform.rosdeployment_reconcile:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
  register: pass
"""

RETURN = r"""
deployments:
  description: Per deployment record - namespace, deployment, moves (instance, from, to, why), stranded, waiting,
    applied (Deployments re-pinned) and table (the status table).
  returned: success
  type: list
  elements: dict
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, ClusterUnreachable

ARGUMENT_SPEC = dict(
    **KUBECONFIG_ARG,
    grace=dict(type="float", default=5.0),
    restart_threshold=dict(type="int", default=3),
)


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    require_packages(module)
    params = module.params
    try:
        import os

        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import Settings
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.cli import build_api_client
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.controller import Controller

        if not os.path.exists(params["kubeconfig"]):
            raise ClusterUnreachable(f"no kubeconfig at {params['kubeconfig']}")
        controller = Controller(
            build_api_client(params["kubeconfig"]),
            Settings(grace_s=params["grace"], restart_threshold=params["restart_threshold"]),
            dry_run=module.check_mode,
        )
        controller.run_once()
    except ImportError as exc:
        module.fail_json(msg=f"the kubernetes Python client is required: {exc}")
    except Exception as exc:  # a KubeROS error, or the cluster's: one clear line, no traceback
        fail(module, exc, params["kubeconfig"])
    changed = any(d["moves"] or d["applied"] for d in controller.last_pass)
    module.exit_json(changed=changed, deployments=controller.last_pass)


if __name__ == "__main__":
    main()
