"""What removing a node from the site asks of the deployments: the node as the cluster has it, and the pass (a
rollout at the current revision, without the node's host in the inventory) of every deployment whose record places
something there. ``playbooks/remove_node.yml`` runs the passes before it drains the node, as the robot pool does
for a reserved robot, so that a robot's modules are stopped and an edge worker's modules move by the deployments'
own rules rather than by eviction."""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import RECORD_LABEL, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import is_ready
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube

DAEMON_KINDS = ("DaemonSet",)


def _node_state(found: dict | None) -> dict:
    if found is None:
        return {"exists": False, "ready": False, "unschedulable": False}
    return {"exists": True, "ready": is_ready(found), "unschedulable": bool((found.get("spec") or {}).get("unschedulable"))}


def _pods_on(kube: Kube, node: str) -> list[str]:
    """The pods bound to ``node`` that a drain evicts (not its DaemonSets', not the mirror pods of static ones)."""
    names = []
    for pod in kube.list("Pod", "", field_selector=f"spec.nodeName={node}"):
        meta = pod.get("metadata") or {}
        owners = [o.get("kind") for o in meta.get("ownerReferences") or []]
        if any(kind in DAEMON_KINDS for kind in owners) or "kubernetes.io/config.mirror" in (meta.get("annotations") or {}):
            continue
        names.append(f"{meta.get('namespace', '')}/{meta.get('name', '')}")
    return sorted(names)


def removal_plan(kube: Kube, node: str) -> dict:
    """The node (``exists``, ``ready``, ``unschedulable``), the pods a drain would evict (``pods``), the passes to run
    first (``passes``: deployment, fleet, revision and what it runs there) and the records that cannot be read
    (``unreadable``: each one's deployment still needs its own pass, which says what is wrong with it)."""
    passes, unreadable = [], []
    for configmap in kube.list("ConfigMap", "", selector=f"{RECORD_LABEL}=true"):
        meta = configmap.get("metadata") or {}
        try:
            record = parse_record(configmap)
        except SpecError as exc:
            unreadable.append(f"ConfigMap {meta.get('namespace', '?')}/{meta.get('name', '?')}: {exc}")
            continue
        there = record.placement.on_node(node)
        if there:
            passes.append({"deployment": record.deployment, "fleet": record.spec.fleet, "revision": record.revision,
                           "namespace": record.namespace, "on_node": there})  # fmt: skip
    return {
        "node": {"name": node, **_node_state(kube.get("Node", node))},
        "pods": _pods_on(kube, node),
        "passes": sorted(passes, key=lambda p: (p["fleet"], p["deployment"])),
        "unreadable": unreadable,
    }
