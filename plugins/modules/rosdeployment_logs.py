#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What one module prints on one robot, without kubectl."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_logs
short_description: Read what one module of a RosDeployment prints on one robot
version_added: 0.4.0
description:
  - Finds the pod that runs O(module) of O(deployment) for O(robot) (a dedicated instance, or the shared one that
    serves the robot) and returns the last O(lines) lines of each of its containers; with several containers each
    line starts with C([container]).
  - With O(follow), keeps reading what the module prints for that many seconds before returning (an Ansible task
    returns once, so follow is a window and not a stream).
  - The values of the Secrets the pod's containers can read (environment and volumes) are taken out of the lines,
    as they are, each of their lines alone, and base64-, percent-, JSON- and hex-encoded; a Secret that cannot be
    read fails the task rather than show its values.
  - Private keys and PGP private key blocks are taken out whatever line the tail or a O(follow) poll starts at (each
    container's log is read as one stream); passwords in URLs, C(Authorization) headers, bearer tokens, JWTs, AWS
    access key ids and values named like credentials (C(*-key), C(*_token), C(password)...) by their shapes, which
    is best effort. The collection's docs/logs.md says exactly what is taken out and what is not.
options:
  deployment:
    description: The RosDeployment's name (its C(metadata.name)).
    type: str
    required: true
  module:
    description: The module's name in the spec (C(rosModules[].name)).
    type: str
    required: true
  robot:
    description: The robot the module runs for.
    type: str
    required: true
  fleet:
    description: The deployment's fleet; found from the cluster when the deployment runs in one fleet only.
    type: str
    default: ""
  container:
    description: One container of the module (a module with several launch lines has several); all when empty.
    type: str
    default: ""
  lines:
    description: Lines of the recent output to return, per container (1 to 10000).
    type: int
    default: 100
  follow:
    description: Seconds to keep reading new lines after the recent ones (0 to 600).
    type: float
    default: 0
  previous:
    description: The output of the container before its last restart (a crashed module's last words).
    type: bool
    default: false
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
- name: What does the motion planner of fetch-1 print?
  kuberos.platform.rosdeployment_logs:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    deployment: pick-and-place
    module: motion-planner
    robot: fetch-1
    lines: 50
  register: planner_log

- name: Show it
  ansible.builtin.debug:
    msg: "{{ planner_log.lines }}"
"""

RETURN = r"""
lines:
  description: The lines, oldest first; prefixed with C([container]) when the module has several containers.
  returned: always
  type: list
  elements: str
pod:
  description: The pod read.
  returned: always
  type: str
node:
  description: The node it runs on.
  returned: always
  type: str
instance:
  description: The module instance (its Deployment) that serves the robot.
  returned: always
  type: str
containers:
  description: The containers read.
  returned: always
  type: list
  elements: str
redacted:
  description: The Secret keys whose values were kept out of the lines (C(<secret>/<key>)).
  returned: always
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.module_log_reader import read_module_log
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import KUBECONFIG_ARG, Kube, api_clients


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            deployment=dict(type="str", required=True),
            module=dict(type="str", required=True),
            robot=dict(type="str", required=True),
            fleet=dict(type="str", default=""),
            container=dict(type="str", default=""),
            lines=dict(type="int", default=100),
            follow=dict(type="float", default=0.0),
            previous=dict(type="bool", default=False),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    p = module.params
    try:
        found = read_module_log(
            Kube(api_clients(p["kubeconfig"])), p["deployment"], p["module"], p["robot"], p["fleet"], p["container"],
            p["lines"], p["follow"], p["previous"],
        )  # fmt: skip
    except Exception as exc:  # a KubeROS error (no such module or robot), or the cluster's: one clear line
        fail(module, exc, p["kubeconfig"])
    module.exit_json(changed=False, **found)


if __name__ == "__main__":
    main()
