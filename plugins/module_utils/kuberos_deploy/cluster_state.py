"""Reading and pruning what KubeROS runs in a cluster, with the Kubernetes Python client.

Used by the ``rosdeployment_prune`` and ``rosdeployment_info`` modules (and by tests); the pure
core stays free of Kubernetes imports.
"""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT, DEPLOYMENT, INSTANCE, MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import (
    IMAGE_PULL_REASONS,
    image_pull_problem,
    is_ready,
    pod_note,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import MANAGED_KINDS, Kube, object_key

# What a fleet shares between its deployments: removed with the fleet's last deployment, like its discovery servers.
FLEET_COMPONENTS = ("discovery-server", "bridge-server", "catalog", "network-policy")


def kube_of(clients) -> Kube:
    """The access layer over ``clients`` (the typed clients by name), or ``clients`` when it is one already."""
    return clients if isinstance(clients, Kube) else Kube(clients)


def managed_objects(clients, namespace: str) -> list[dict]:
    """Every object KubeROS manages in a namespace, as {apiVersion, kind, metadata{name, namespace, labels}}."""
    kube = kube_of(clients)
    found = []
    for kind in MANAGED_KINDS:
        for item in kube.list(kind, namespace, selector=f"{MANAGED_BY}=kuberos"):
            meta = item["metadata"]
            found.append(
                {
                    "apiVersion": item["apiVersion"],
                    "kind": kind,
                    "metadata": {"name": meta["name"], "namespace": namespace, "labels": dict(meta.get("labels") or {})},
                }
            )
    return found


def stale_objects(live: list[dict], keep: list[dict], deployments: list[str], remove_discovery: bool) -> list[dict]:
    """Live objects of ``deployments`` (and discovery servers) that are not in ``keep``."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import REVISION_HISTORY, REVISION_LABEL

    wanted = {object_key(o) for o in keep}
    newest: dict[str, int] = {}
    for obj in live:
        number = obj["metadata"]["labels"].get(REVISION_LABEL, "")
        if number.isdigit():
            owner = obj["metadata"]["labels"].get(DEPLOYMENT, "")
            newest[owner] = max(newest.get(owner, 0), int(number))
    stale = []
    for obj in live:
        obj_labels = obj["metadata"]["labels"]
        number = obj_labels.get(REVISION_LABEL, "")
        if keep and number.isdigit() and int(number) > newest[obj_labels.get(DEPLOYMENT, "")] - REVISION_HISTORY:
            continue  # a kept revision (rollback.yml returns to it); the oldest beyond the history go
        ours = obj_labels.get(DEPLOYMENT) in deployments
        discovery = obj_labels.get(COMPONENT) in FLEET_COMPONENTS and remove_discovery
        if (ours or discovery) and object_key(obj) not in wanted:
            stale.append(obj)
    return stale


def delete_object(clients, obj: dict) -> None:
    if obj["kind"] not in MANAGED_KINDS:
        raise ValueError(f"KubeROS does not manage {obj['kind']}")
    kube_of(clients).delete_object(obj)


# Waiting reasons the kubelet tries again (with back-off): one failed try is not yet the answer.
RETRIED_PULL_REASONS = ("ErrImagePull", "ImagePullBackOff")


def _image_problem(clients, pod: dict) -> tuple[str, bool]:
    """(why a container of the pod cannot start because of its image, whether that is final); ("", False) when none
    is stuck on its image. The cause is the pod's latest "Failed to pull image" event (while the kubelet backs off,
    the container says only "Back-off pulling image"). A failed pull is final once the kubelet has failed it twice:
    its first try can predate what a deploy created just before (a pull secret not yet in the kubelet's cache), and
    while it tries again the container still shows the first failure, for as long as that second pull takes."""
    status = pod.get("status") or {}
    for container in (status.get("initContainerStatuses") or []) + (status.get("containerStatuses") or []):
        waiting = (container.get("state") or {}).get("waiting") or {}
        if waiting.get("reason") not in IMAGE_PULL_REASONS:
            continue
        message = waiting.get("message", "")
        if waiting["reason"] not in RETRIED_PULL_REASONS:
            return image_pull_problem(container.get("image", ""), waiting["reason"], message), True
        meta = pod["metadata"]
        events = kube_of(clients).list(
            "Event", meta["namespace"], field_selector=f"involvedObject.uid={meta['uid']},reason=Failed"
        )
        failed = [e for e in events if "pull" in (e.get("message") or "").lower()]
        # The kubelet also records "Error: ErrImagePull" and "Error: ImagePullBackOff" as Failed events, often
        # in the same second as the one that says why ("Failed to pull image ...: <cause>"): that one wins.
        causes = [e for e in failed if not e["message"].startswith("Error: ")]
        if waiting["reason"] == "ImagePullBackOff" and (causes or failed):
            latest = max(causes or failed, key=lambda e: e.get("lastTimestamp") or e.get("eventTime") or "")
            message = latest["message"]
        tries = sum(int(e.get("count") or 1) for e in causes)
        return image_pull_problem(container.get("image", ""), waiting["reason"], message), tries >= 2
    return "", False


def running_modules(clients, fleets: list[str], deployments: list[str]) -> list[dict]:
    """Pods of the deployments' modules and of the fleets' discovery servers as the cluster reports
    them: instance, node, phase, ready, the problem of a container stuck on its image ("" if none), and why a pod
    that is not ready is not (``status.pod_note``)."""
    rows = []
    for fleet in sorted(set(fleets)):
        for pod in kube_of(clients).list("Pod", fleet_namespace(fleet), selector=f"{MANAGED_BY}=kuberos"):
            meta = pod["metadata"]
            pod_labels = meta.get("labels") or {}
            discovery = pod_labels.get(COMPONENT) in FLEET_COMPONENTS
            if not (discovery or pod_labels.get(DEPLOYMENT) in deployments) or meta.get("deletionTimestamp"):
                continue
            problem, final = _image_problem(clients, pod)
            rows.append(
                {
                    "fleet": fleet,
                    "deployment": pod_labels.get(DEPLOYMENT),
                    "instance": pod_labels.get(INSTANCE),
                    "robot_label": pod_labels.get(node_labels.ROBOT),
                    "pod": meta["name"],
                    "node": (pod.get("spec") or {}).get("nodeName"),
                    "phase": (pod.get("status") or {}).get("phase"),
                    "ready": is_ready(pod),
                    "problem": problem,
                    "problem_final": final,
                    "note": "" if is_ready(pod) else pod_note(pod),
                }
            )
    return rows


def node_allocations(clients, exclude_deployments: list[str], exclude_discovery_of_fleets: list[str]) -> dict[str, dict]:
    """Resources requested per node by every running pod except those about to be placed again (of
    ``exclude_deployments``, and the discovery servers of ``exclude_discovery_of_fleets``), in the form
    the scheduler's ``allocated`` takes."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities

    used: dict[str, dict] = {}
    for pod in kube_of(clients).list("Pod", field_selector="status.phase!=Succeeded,status.phase!=Failed"):
        spec = pod.get("spec") or {}
        node = spec.get("nodeName")
        pod_labels = pod["metadata"].get("labels") or {}
        replaced = pod_labels.get(DEPLOYMENT) in exclude_deployments or (
            pod_labels.get(COMPONENT) in FLEET_COMPONENTS and pod_labels.get(node_labels.FLEET) in exclude_discovery_of_fleets
        )
        if not node or replaced:
            continue
        entry = used.setdefault(node, {"cpu": 0, "memory": 0, "gpu": 0, "pods": 0})
        entry["pods"] += 1
        sidecars = [c for c in spec.get("initContainers") or [] if c.get("restartPolicy") == "Always"]
        for container in (spec.get("containers") or []) + sidecars:  # native sidecars run beside the containers
            requests = (container.get("resources") or {}).get("requests") or {}
            entry["cpu"] += quantities.parse_cpu(requests.get("cpu", "0"))
            entry["memory"] += quantities.parse_memory(requests.get("memory", "0"))
            entry["gpu"] += int(requests.get("nvidia.com/gpu", "0"))
    return {node: {**e, "cpu": f"{e['cpu']}m"} for node, e in sorted(used.items())}


def namespace_names(clients) -> list[str]:
    """Names of the namespaces that exist in the cluster, sorted."""
    return sorted(ns["metadata"]["name"] for ns in kube_of(clients).list("Namespace"))


def unavailable_nodes(clients, wanted: list[str]) -> dict[str, str]:
    """Of the ``wanted`` nodes (inventory names), those that are not Ready or not in the cluster, with why.
    A node's inventory name is its ``device.kuberos.io/hostname`` label, else its name."""
    found = {}
    for node in kube_of(clients).list("Node"):
        name = (node["metadata"].get("labels") or {}).get(node_labels.HOSTNAME, node["metadata"]["name"])
        conditions = (node.get("status") or {}).get("conditions") or []
        ready = next((c for c in conditions if c.get("type") == "Ready"), None)
        found[name] = None if ready is not None and ready.get("status") == "True" else (
            f"node {name} is NotReady (Ready={ready.get('status') if ready else 'missing'}"
            f"{' (' + ready['reason'] + ')' if ready is not None and ready.get('reason') else ''})"
        )  # fmt: skip
    out = {}
    for name in wanted:
        if name not in found:
            out[name] = f"node {name} is not in the cluster"
        elif found[name]:
            out[name] = found[name]
    return out


def previous_placement(clients, targets: list[dict]) -> dict:
    """What runs now for sticky placement, as placement data: the instances of the targets' records
    (``[{name, fleet}]``) and the live discovery servers of their fleets."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import discovery_from_deployments
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
        merge_previous,
        record_name,
        record_placement,
    )

    kube = kube_of(clients)
    placements, objects, revisions = [], [], {}
    for fleet in sorted({t["fleet"] for t in targets}):
        namespace = fleet_namespace(fleet)
        objects.extend(kube.list("Deployment", namespace, selector=f"{COMPONENT}=discovery-server"))
        for target in (t for t in targets if t["fleet"] == fleet):
            configmap = kube.get("ConfigMap", record_name(target["name"]), namespace)
            if configmap is None:
                continue
            data = configmap.get("data") or {}
            if data.get("rollout.json"):
                from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError

                raise SpecError(
                    [
                        Problem(
                            f"ConfigMap {namespace}/{configmap['metadata']['name']}",
                            "data.rollout.json",
                            f"a rollout of {target['name']} is in progress ({data['rollout.json'][:200]}); wait for it to "
                            "end, or remove this key if its process died (docs/software.md)",
                        )
                    ],
                    title="a rollout is in progress",
                )
            placements.append(record_placement(configmap))
            revisions[target["name"]] = {"revision": int(data.get("revision") or 0), "hash": data.get("revision-hash", "")}
    return {**merge_previous(placements, discovery_from_deployments(objects)).to_dict(), "revisions": revisions}
