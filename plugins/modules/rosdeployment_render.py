#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Render a placed RosDeployment into Kubernetes manifests."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_render
short_description: Render a placed RosDeployment into Kubernetes manifests
version_added: 0.1.0
description:
  - Turns a RosDeployment and its placement (from the P(kuberos.platform.place_modules#filter) filter) into
    Kubernetes objects, one YAML file per object under O(dest)/manifests, plus C(placement.json), a
    human-readable C(placement.txt) and a picture of the placement, C(placement.svg).
  - Per fleet a namespace and redundant Fast DDS discovery servers; per module instance a Deployment
    pinned to its node, with ROS_DISCOVERY_SERVER, RMW_IMPLEMENTATION and ROS_DOMAIN_ID set.
  - Files are written only when their content changes; manifests no longer rendered are removed.
  - Modules placed in a third-party cluster (C(cluster) in the spec) are rendered for that cluster into
    O(dest)/clusters/<cluster>/ (namespace, a discovery server, the bridge client, the modules); the bridge server
    is one of this cluster's objects. The bridge's certificates (a CA, server and client keys) are generated once
    into O(dest)/tls/ (mode 0600) and turned into Secret manifests there; the result names those files only and
    never holds a key.
options:
  src:
    description: Path of the RosDeployment file the placement was made from.
    type: path
    required: true
  placement:
    description: The placement returned by the P(kuberos.platform.place_modules#filter) filter.
    type: dict
    required: true
  dest:
    description:
      - Directory to render into. Created if missing. An existing non-empty directory must have been
        written by this module before (it carries a C(.kuberos-render) marker).
    type: path
    required: true
  inventory:
    description:
      - The fleet resource model (P(kuberos.platform.fleet_inventory#filter)). When given, one record
        ConfigMap per RosDeployment (C(kuberos-record-<name>) in the fleet namespace) is rendered too, with that
        deployment's own document of the spec, the inventory and the placement (gzip-compressed) and the render
        options, which the KubeROS controller reads to move modules when nodes fail or links degrade.
      - A spec whose record or revision would not fit in a ConfigMap (more than 768 KiB) fails the task before
        anything is written, naming the file, the document's line and the deployment.
    type: dict
  field_manager:
    description: The server-side apply field manager the objects are applied with; the controller applies with it too.
    type: str
    default: kuberos
  catalog:
    description:
      - The software catalog (a directory of catalog files, or one file) that C(module) references of the spec
        resolve against. The entries used are kept in the deployment record and its revision, and the whole catalog
        in the ConfigMap C(kuberos-catalog) of each fleet namespace (for the controller and the dashboard).
    type: path
  revisions:
    description:
      - Each deployment's current revision in the cluster, as C(name) to C(revision) and C(hash) (C(previous.revisions) of
        P(kuberos.platform.node_allocations#module)). A deployment whose spec asks for something new gets the next
        revision number; one whose spec is unchanged keeps its number. Without it, revisions start at 1.
    type: dict
    default: {}
attributes:
  check_mode:
    support: full
  diff_mode:
    support: full
extends_documentation_fragment:
  - kuberos.platform.render
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Render the placed deployment
  kuberos.platform.rosdeployment_render:
    src: examples/listing1.yml
    placement: "{{ placement }}"
    dest: rendered/listing1
"""

RETURN = r"""
objects:
  description: The rendered Kubernetes objects, in apply order (namespaces first).
  returned: success
  type: list
  elements: dict
namespaces:
  description: The Namespace objects, to create first.
  returned: success
  type: list
  elements: dict
apply_objects:
  description: The other objects, in apply order (after the namespaces).
  returned: success
  type: list
  elements: dict
object_refs:
  description: C(apiVersion), C(kind), C(metadata.name) and C(metadata.namespace) of every object other than namespaces.
  returned: success
  type: list
  elements: dict
remote:
  description: Per third-party cluster, C(namespaces) and C(apply_objects) to apply there.
  returned: success
  type: dict
secret_files:
  description: Secret manifests of the bridges' TLS keys, as C({cluster, path}); C(cluster) is empty for this cluster.
  returned: success
  type: list
  elements: dict
table:
  description: Where every module of every robot runs, as a fixed-width table.
  returned: success
  type: str
files:
  description: Files created, updated and removed (relative to O(dest)).
  returned: success
  type: dict
  sample: {"created": ["manifests/kuberos-test-fleet/deployment-kuberos-discovery-0.yaml"], "updated": [], "removed": []}
"""

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import RENDER_ARGS
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_pass import render_to_dir

ARGUMENT_SPEC = dict(
    src=dict(type="path", required=True),
    placement=dict(type="dict", required=True),
    dest=dict(type="path", required=True),
    inventory=dict(type="dict"),
    field_manager=dict(type="str", default="kuberos"),
    **RENDER_ARGS,
    catalog=dict(type="path"),
    revisions=dict(type="dict", default={}),
)


def run(module: AnsibleModule) -> dict:
    params = module.params
    catalog = load_catalog(params["catalog"]) if params["catalog"] else None
    deployments = load_specs(params["src"], catalog=catalog)
    placement = Placement.from_dict(params["placement"])
    clusters = load_inventory(params["inventory"]).clusters if params["inventory"] is not None else None
    rendered = render_to_dir(params, deployments, placement, catalog, module.check_mode, params["revisions"], clusters=clusters)
    plan = rendered.pop("plan")
    if module._diff:
        rendered["diff"] = plan.diff()
    return rendered


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    require_packages(module)
    try:
        module.exit_json(**run(module))
    except KuberosError as exc:  # the spec's, the inventory's, the render directory's
        fail(module, exc)
    except OSError as exc:
        module.fail_json(msg=f"cannot write the render directory: {exc}")


if __name__ == "__main__":
    main()
