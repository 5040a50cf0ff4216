#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""What a deploy would change in the cluster, per object and per module of each robot."""

from __future__ import annotations

DOCUMENTATION = r"""
module: rosdeployment_diff
short_description: Show what applying rendered objects would change in the cluster, as kubectl diff does
version_added: 0.2.0
description:
  - For every object of O(objects), reads the live object and, when it exists, runs a server-side apply with
    C(dryRun=All) (field manager O(field_manager), conflicts forced, as the deploy applies), so that the result is
    what the cluster would hold after the apply. Objects that do not exist yet are shown as rendered. Nothing is
    written to the cluster, in check mode or not.
  - Objects of the deployments of O(placement) that the prune would delete (not in O(keep)) are shown as removed.
  - With C(--diff), returns one diff per object that changes, is new or would be removed, live against dry run,
    without C(status), C(metadata.managedFields) and the server's bookkeeping (resourceVersion, generation, uid,
    creationTimestamp); encoded blobs (C(binaryData), Secret data) show as their size and digest. The summary comes
    first.
  - The summary says which modules of which robots move (node A -> B), start, stop or change (version, image, launch,
    env, parameters, resources), from the placement in each deployment's live record and the new O(placement).
attributes:
  check_mode:
    support: full
  diff_mode:
    support: full
options:
  objects:
    description: The rendered objects, in apply order (C(objects) of P(kuberos.platform.rosdeployment_render#module)).
    type: list
    elements: dict
    required: true
  placement:
    description: The new placement (P(kuberos.platform.place_modules#filter)); its C(deployments) say whose objects to prune.
    type: dict
    required: true
  keep:
    description:
      - Objects the prune keeps besides O(objects), as C(apiVersion), C(kind), C(metadata.name) and C(metadata.namespace)
        (C(object_refs) of P(kuberos.platform.rosdeployment_render#module), which also names the bridges' TLS Secrets).
    type: list
    elements: dict
    default: []
  prune:
    description: Show the objects the prune would remove.
    type: bool
    default: true
  field_manager:
    description: The field manager of the dry-run applies (the deploy's).
    type: str
    default: kuberos
extends_documentation_fragment:
  - kuberos.platform.cluster
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Show what the deploy would change
  kuberos.platform.rosdeployment_diff:
    kubeconfig: ~/.cache/kuberos/cluster/kubeconfig
    objects: "{{ rendered.objects }}"
    keep: "{{ rendered.object_refs }}"
    placement: "{{ placement }}"
  register: what_changes
"""

RETURN = r"""
summary:
  description: The summary, for people (also the first entry of the diff).
  returned: always
  type: str
  sample: |-
    What the deploy would change (check mode: nothing written):
      pick-and-place/perception (fetch-1): moves edge-1 -> cloud-1
      pick-and-place/motion-planner (fetch-1, fetch-2): changes: image ghcr.io/x/planner:0.1 -> ghcr.io/x/planner:0.2
      record kuberos-test-fleet/kuberos-record-pick-and-place: updated, placement of 1 instance changed
      objects: 4 changed, 1 new, 0 removed, 18 unchanged
modules:
  description:
    - One entry per module of a robot that moves, starts, stops or changes, with C(deployment), C(module), C(robot),
      C(action) (move, start, stop, change), C(from) and C(to) (nodes) and C(details) (what changes, in words).
    - A fleet's discovery server that moves, starts or stops has an empty C(deployment) and C(robot) C(fleet <name>).
  returned: always
  type: list
  elements: dict
records:
  description: Per deployment record that changes, how many instances of its placement change.
  returned: always
  type: list
  elements: str
refused:
  description:
    - Objects whose dry run the cluster refused (invalid, or forbidden by an admission policy), as C(Kind namespace/name)
      to what the API server said. They show in the summary, not as diffs; the deploy's own dry run then stops the run.
  returned: always
  type: dict
objects:
  description: C(changed), C(new) and C(removed) (lists of C(Kind namespace/name)) and C(unchanged) (a count).
  returned: always
  type: dict
"""

from concurrent.futures import ThreadPoolExecutor

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.diff import (
    change_summary,
    object_diff,
    record_changes,
    summary_text,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace, object_key, object_label
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import record_name, record_placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.results import fail
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import managed_objects, stale_objects
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import (
    KUBECONFIG_ARG,
    REFUSALS,
    Kube,
    api_clients,
    refusal,
    status_of,
)

WORKERS = 4  # reads and dry runs side by side; the API server does the work


class Live:
    """Reads and server-side dry runs (the access layer's), and what the API server refused."""

    def __init__(self, clients, field_manager: str):
        self.kube = Kube(clients, field_manager)
        self.refused: dict[str, str] = {}  # object -> what the API server said, when its dry run was refused

    def read(self, obj: dict) -> dict | None:
        kind, namespace, name = object_key(obj)
        return self.kube.get(kind, name, namespace)

    def pair(self, obj: dict) -> tuple[dict | None, dict]:
        """(live, what the cluster would hold): the dry run's result when the object exists, else the object as rendered."""
        live = self.read(obj)
        if live is None:
            return None, obj
        try:
            return live, self.kube.apply(obj, dry_run=True)
        except Exception as exc:
            if status_of(exc) not in REFUSALS:
                raise
            # Said in the summary; a deploy (the rosdeployment module) stops at its own dry run, nothing applied.
            self.refused[object_label(obj)] = refusal(exc)
            return live, live


def prune_candidates(clients, placement: Placement, keep: list[dict]) -> list[dict]:
    """What rosdeployment_prune would delete after this apply (the same rule: cluster_state.stale_objects)."""
    deployments = [d["name"] for d in placement.deployments]
    found = []
    for fleet in sorted({d["fleet"] for d in placement.deployments}):
        live = managed_objects(clients, fleet_namespace(fleet))
        found.extend(stale_objects(live, keep, deployments, remove_discovery=True))
    return found


def previous_placements(live: Live, placement: Placement) -> dict[str, Placement | None]:
    """Each deployment's placement as its live record holds it (None: not deployed yet)."""
    out = {}
    for dep in placement.deployments:
        configmap = {"kind": "ConfigMap", "metadata": {"name": record_name(dep["name"]), "namespace": dep["namespace"]}}
        found = live.read(configmap)
        out[dep["name"]] = record_placement(found) if found is not None else None
    return out


def run(module: AnsibleModule) -> dict:
    params = module.params
    placement = Placement.from_dict(params["placement"])
    clients = api_clients(params["kubeconfig"])
    live = Live(clients, params["field_manager"])
    objects = params["objects"]
    namespaces = {o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"}
    existing = {n for n in namespaces if live.read({"kind": "Namespace", "metadata": {"name": n}}) is not None}

    def pair(obj):
        namespace = obj["metadata"].get("namespace")
        if namespace in namespaces and namespace not in existing:
            return None, obj  # its namespace is new: so is the object (a dry run there would be refused)
        return live.pair(obj)

    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        pairs = dict(zip([object_key(o) for o in objects], pool.map(pair, objects), strict=True))
        removed = []
        if params["prune"]:
            keep = [*objects, *params["keep"]]
            removed = list(pool.map(live.read, prune_candidates(clients, placement, keep)))
    removed = [o for o in removed if o is not None]
    for obj in removed:
        pairs[object_key(obj)] = (obj, None)
    diffs, counts, listed = [], {"changed": 0, "new": 0, "removed": 0, "unchanged": 0}, {"changed": [], "new": [], "removed": []}
    for before, after in pairs.values():
        entry = object_diff(before, after)
        if entry is None:
            counts["unchanged"] += 1
            continue
        which = "new" if before is None else "removed" if after is None else "changed"
        counts[which] += 1
        listed[which].append(object_label(after if after is not None else before))
        diffs.append(entry)
    rows = change_summary(previous_placements(live, placement), placement, pairs)
    records = record_changes(pairs)
    summary = summary_text(rows, records, counts, module.check_mode, refused=live.refused)
    result = {
        "changed": bool(diffs or live.refused),
        "refused": live.refused,
        "msg": summary,
        "summary": summary,
        "modules": rows,
        "records": records,
        "objects": {**listed, "unchanged": counts["unchanged"]},
    }
    if module._diff:
        result["diff"] = [{"prepared": summary + "\n\n"}, *diffs]
    return result


def main():
    module = AnsibleModule(
        argument_spec=dict(
            **KUBECONFIG_ARG,
            objects=dict(type="list", elements="dict", required=True),
            placement=dict(type="dict", required=True),
            keep=dict(type="list", elements="dict", default=[]),
            prune=dict(type="bool", default=True),
            field_manager=dict(type="str", default="kuberos"),
        ),
        supports_check_mode=True,
    )
    require_packages(module)
    try:
        module.exit_json(**run(module))
    except Exception as exc:  # a KubeROS error, or the cluster's: one clear line, no traceback
        fail(module, exc, module.params["kubeconfig"])


if __name__ == "__main__":
    main()
