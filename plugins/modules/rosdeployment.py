#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Deploy (or remove) a RosDeployment in one pass."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment
short_description: Deploy a RosDeployment in one pass, or remove it
version_added: 0.3.0
description:
  - With O(state=present), in one pass - reads and validates the spec file once; reads the cluster once (what runs on
    each node, which nodes are not Ready, what this deployment runs now, every object in the fleets' namespaces);
    places every module of every robot (sticky - what still fits where it runs stays there); renders the manifests
    into O(dest); creates the fleets' namespaces that are new; dry-runs every object server-side (C(dryRun=All),
    field manager O(field_manager), conflicts forced); and only when the cluster took every object, applies the
    objects whose dry run differs from the live object, one server-side-apply PATCH per object from O(workers)
    threads; removes the deployment's objects that are no longer rendered; waits until every module runs, Ready, on
    the node it was placed on.
  - If the cluster refuses any object in the dry run, the namespaces this pass created are removed, nothing is
    applied, and the task fails with what the cluster said about each refused object.
  - Modules placed in third-party clusters are dry-run and applied there through O(clusters), after the dry run of
    this cluster's objects and before any object is written anywhere.
  - With O(state=absent), removes every object of the spec's deployments, here and in third-party clusters; a
    fleet's discovery servers, bridge server and catalog go with its last deployment.
  - With O(apply=false), renders only (no cluster is read).
  - The same pieces are public for users who compose their own plays - the
    P(kuberos.platform.place_modules#filter) filter and the P(kuberos.platform.rosdeployment_render#module),
    P(kuberos.platform.rosdeployment_diff#module), P(kuberos.platform.rosdeployment_prune#module) and
    P(kuberos.platform.rosdeployment_info#module) modules.
options:
  src:
    description: Path of the RosDeployment file (one or more YAML documents).
    type: path
    required: true
  inventory:
    description: The fleet inventory, as returned by the P(kuberos.platform.fleet_inventory#filter) filter.
    type: dict
    required: true
  dest:
    description: Directory the manifests, C(placement.json), C(placement.txt) and C(placement.svg) are rendered into.
    type: path
    required: true
  state:
    description: C(present) deploys, C(absent) removes the spec's deployments.
    type: str
    choices: [present, absent]
    default: present
  apply:
    description: Apply to the cluster; C(false) renders only.
    type: bool
    default: true
  catalog:
    description: The software catalog that C(module) references of the spec resolve against (a directory, or one file).
    type: path
  field_manager:
    description: Field manager of the server-side applies.
    type: str
    default: kuberos
  allocated:
    description: "Resources used per node by workloads the cluster does not show, as C({node: {cpu, memory, gpu, pods}})."
    type: dict
    default: {}
  workers:
    description: Requests sent side by side (dry runs, applies, deletes, reads).
    type: int
    default: 8
  wait_timeout:
    description: Seconds to wait for every module to be Running and Ready on its placed node; 0 does not wait.
    type: int
    default: 180
  clusters:
    description:
      - How to reach each third-party cluster, by its inventory name - C(api_server), C(token) (keep it in
        ansible-vault) and C(ca_cert) (a path). Needed only for the clusters the placement uses.
    type: dict
    default: {}
  kubeconfig:
    description: Kubeconfig of the cluster; required unless O(apply=false).
    type: path
extends_documentation_fragment:
  - kuberos.platform.render
  - kuberos.platform.graph_check
  - kuberos.platform.attributes
attributes:
  check_mode:
    support: full
    details: Reads the cluster and dry-runs every object; writes nothing, neither to the cluster nor to O(dest).
  diff_mode:
    support: full
    details:
      - A summary of which modules of which robots move, start, stop or change, then one diff per object, live against
        the server-side dry run. With O(apply=false), the render directory's diff.
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Deploy the pick-and-place application
  kuberos.platform.rosdeployment:
    src: examples/pick-and-place.yml
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    dest: rendered/pick-and-place
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
  register: deployed

- name: Show where every module of every robot runs
  ansible.builtin.debug:
    msg: "{{ deployed.table }}"

- name: Remove it
  kuberos.platform.rosdeployment:
    src: examples/pick-and-place.yml
    inventory: "{{ groups | kuberos.platform.fleet_inventory(hostvars) }}"
    dest: rendered/pick-and-place
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    state: absent
"""

RETURN = r"""
notes:
  description: >-
    What the translation of a spec in the reference format (kind ApplicationDeployment) ignored or chose, each with
    the file, line and field (docs/rosdeployment.md, "The reference format"); empty for a RosDeployment.
  returned: when state is present
  type: list
  elements: str
  sample: ["app.yml:12: rosModules[0].requirements.dynamicRescheduling: False (bool) is accepted and not used: ..."]
table:
  description: Where every module of every robot runs, read back from the cluster (the placement when not applied).
  returned: when state is present
  type: str
summary:
  description: Which modules of which robots move, start, stop or change, the records, and the objects' counts.
  returned: when applying
  type: str
placement:
  description: The placement, as the P(kuberos.platform.place_modules#filter) filter returns it.
  returned: when state is present
  type: dict
objects:
  description: Counts of objects C(changed), C(new), C(removed) and C(unchanged) (live against the dry run).
  returned: when applying
  type: dict
applied:
  description: The objects applied (or that would be, in check mode), as C(Kind namespace/name).
  returned: when applying
  type: list
  elements: str
removed:
  description: The objects deleted (or that would be, in check mode), as C(Kind/namespace/name).
  returned: when applying or removing
  type: list
  elements: str
rows:
  description:
    - One entry per robot and module with C(placed_node), C(node), C(phase), C(ready), C(problem) (why its pod
      cannot start because of its image, empty if not), and C(note) (why a pod that is not ready is not, in the
      cluster's words - the scheduler's reason, an eviction, a container in CrashLoopBackOff; empty if nothing says).
  returned: when applying, not in check mode
  type: list
  elements: dict
ready:
  description: Every module runs, Ready, on the node it was placed on.
  returned: when applying, not in check mode
  type: bool
problems:
  description:
    - Images that cannot be pulled, one sentence each naming the image, its registry and why (refused credentials,
      no such image, an untrusted certificate, no route). The wait ends when one lasts past the kubelet's next try
      (15 s), since waiting longer does not help.
  returned: when waiting
  type: list
  elements: str
dest:
  description: The render directory.
  returned: when state is present
  type: str
files:
  description: The files of the render directory C(created), C(updated) and C(removed).
  returned: when state is present
  type: dict
left_out:
  description: Per production deployment, the robots it left out because the robot pool holds them, and why.
  returned: when state is present
  type: dict
graph:
  description: Per deployment whose modules declare topics, the live graph check's verdict (C(ok), C(problems), C(seconds)).
  returned: when the graph check ran
  type: dict
timings:
  description: Seconds each step took (validate, read the cluster, place, render, read the objects, dry run, apply, ...).
  returned: always
  type: dict
"""


from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.deploy_pass import DeployPass, NotReady
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import RENDER_ARGS
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import GRAPH_CHECK_ARGS

ARGUMENT_SPEC = dict(
    src=dict(type="path", required=True),
    inventory=dict(type="dict", required=True),
    dest=dict(type="path", required=True),
    state=dict(type="str", choices=["present", "absent"], default="present"),
    apply=dict(type="bool", default=True),
    catalog=dict(type="path"),
    field_manager=dict(type="str", default="kuberos"),
    allocated=dict(type="dict", default={}),
    workers=dict(type="int", default=8),
    wait_timeout=dict(type="int", default=180),
    clusters=dict(type="dict", default={}, no_log=True),
    kubeconfig=dict(type="path"),
    **RENDER_ARGS,
    **GRAPH_CHECK_ARGS,
)


def main():
    module = AnsibleModule(
        argument_spec=ARGUMENT_SPEC,
        required_if=[("apply", True, ("kubeconfig",))],
        supports_check_mode=True,
    )
    require_packages(module)
    try:
        module.exit_json(**DeployPass(module.params, module.check_mode, module._diff).run())
    except NotReady as exc:  # applied, but not every module Ready in time: what was done, and why not
        module.fail_json(msg=str(exc), **exc.result)
    except Exception as exc:  # a KubeROS error (its headline, its problems below), or the cluster's: no traceback
        fail(module, exc, module.params["kubeconfig"])


if __name__ == "__main__":
    main()
