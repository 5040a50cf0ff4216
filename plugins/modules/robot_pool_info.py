#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Who holds which robot of the pool: every reservation of every fleet."""

from __future__ import annotations

DOCUMENTATION = r"""
module: robot_pool_info
short_description: Read every reservation of the robot pool
version_added: 0.4.0
description:
  - Reads the reservations of every fleet (ConfigMaps labelled C(kuberos.io/reservation)) as
    P(kuberos.platform.robot_pool#module) writes them, with C(active) false for one whose time has passed.
  - A reservation that cannot be read (a field missing, a time out of range, an owner or a reason the pool would not
    write) holds nothing; each one is a warning naming its ConfigMap and why, and is left out.
  - Ownership is advisory (C(ownership), docs/security.md).
options: {}
attributes:
  check_mode:
    support: full
  diff_mode:
    support: N/A
    details: Changes nothing.
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Who holds what
  kuberos.platform.robot_pool_info:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
"""

RETURN = r"""
reservations:
  description:
    - Every reservation that can be read (C(robot), C(fleet), C(owner), C(reason), C(until), C(since),
      C(identity)), with C(active) (false when its time has passed).
  returned: always
  type: list
  elements: dict
message:
  description: One line per reservation (who holds which robot until when), or that no robot is reserved.
  returned: always
  type: str
ignored:
  description: The reservations that cannot be read (they hold nothing), one warning each naming the ConfigMap and why.
  returned: always
  type: list
  elements: str
ownership:
  description: What the owner's name guarantees and what it does not (advisory), in one sentence.
  returned: always
  type: str
"""

import datetime

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.robot_pool import ADVISORY, listing
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, Kube, api_clients


def main():
    module = AnsibleModule(argument_spec=dict(**KUBECONFIG_ARG), supports_check_mode=True)
    require_packages(module)
    try:
        found = listing(Kube(api_clients(module.params["kubeconfig"]), "kuberos-pool"), datetime.datetime.now(datetime.UTC))
    except Exception as exc:  # the cluster's error: one clear line
        fail(module, exc, module.params["kubeconfig"])
    for warning in found["ignored"]:
        module.warn(warning)
    lines = [
        f"{r['robot']} ({r['fleet']}): {r['owner']} until {r['until']}{'' if r['active'] else ' (ended)'}"
        + (f" [Kubernetes user {r['identity']}]" if r.get("identity") else "") + (f": {r['reason']}" if r["reason"] else "")
        for r in sorted(found["reservations"], key=lambda r: (r["robot"], r["fleet"]))
    ]  # fmt: skip
    module.exit_json(changed=False, reservations=found["reservations"], ignored=found["ignored"], ownership=ADVISORY,
                     message="\n".join(lines) or "no robot is reserved")  # fmt: skip


if __name__ == "__main__":
    main()
