"""Reading and pruning what KubeROS runs in a cluster, with the Kubernetes Python client.

Used by the ``rosdeployment_prune`` and ``rosdeployment_info`` modules (and by tests); the pure
core stays free of Kubernetes imports.
"""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    COMPONENT,
    DEPLOYMENT,
    INSTANCE,
    MANAGED_BY,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import (
    IMAGE_PULL_REASONS,
    image_pull_problem,
    pod_note,
)

# The argument every module that talks to a cluster takes (documented by the kuberos.platform.cluster fragment).
KUBECONFIG_ARG = {"kubeconfig": {"type": "path", "required": True}}

# Kinds KubeROS renders inside fleet namespaces: (apiVersion, kind, list method, delete method, api).
MANAGED_KINDS = (
    ("apps/v1", "Deployment", "list_namespaced_deployment", "delete_namespaced_deployment", "apps"),
    ("v1", "Service", "list_namespaced_service", "delete_namespaced_service", "core"),
    ("v1", "ConfigMap", "list_namespaced_config_map", "delete_namespaced_config_map", "core"),
    ("v1", "Secret", "list_namespaced_secret", "delete_namespaced_secret", "core"),
    ("networking.k8s.io/v1", "NetworkPolicy", "list_namespaced_network_policy", "delete_namespaced_network_policy", "networking"),
)
# What a fleet shares between its deployments: removed with the fleet's last deployment, like its discovery servers.
FLEET_COMPONENTS = ("discovery-server", "bridge-server", "catalog", "network-policy")


START_HINT = "start the local cluster with `make cluster`, or set kuberos_kubeconfig to your cluster's kubeconfig"


class ClusterUnreachable(Exception):
    """The cluster cannot be reached; the message says which and what to do."""


def api_clients(kubeconfig: str):
    import os

    from kubernetes import client, config

    if not os.path.exists(kubeconfig):
        raise ClusterUnreachable(f"no kubeconfig at {kubeconfig}; {START_HINT}")
    api = config.new_client_from_config(config_file=kubeconfig)
    return {
        "core": client.CoreV1Api(api),
        "apps": client.AppsV1Api(api),
        "batch": client.BatchV1Api(api),
        "networking": client.NetworkingV1Api(api),
    }


def explain(exc: Exception, kubeconfig: str) -> str:
    """One line for a failure to talk to the cluster: unreachable, refused, or what the API server said."""
    from kubernetes.client.exceptions import ApiException
    from urllib3.exceptions import HTTPError

    if isinstance(exc, ClusterUnreachable):
        return str(exc)
    if isinstance(exc, ApiException):
        return f"the API server refused: {exc.status} {exc.reason}: {(exc.body or '')[:500]}"
    if isinstance(exc, (HTTPError, OSError)):
        reason = getattr(exc, "reason", None) or exc
        return f"the cluster of {kubeconfig} is not reachable ({reason}); {START_HINT}"
    return f"cannot use the cluster of {kubeconfig}: {exc}"


def _key(obj: dict) -> tuple:
    return (obj["apiVersion"], obj["kind"], obj["metadata"].get("namespace", ""), obj["metadata"]["name"])


def managed_objects(clients, namespace: str) -> list[dict]:
    """Every object KubeROS manages in a namespace, as {apiVersion, kind, metadata{name, namespace, labels}}."""
    from kubernetes.client.exceptions import ApiException

    found = []
    for api_version, kind, list_method, _delete, api in MANAGED_KINDS:
        try:
            items = getattr(clients[api], list_method)(namespace, label_selector=f"{MANAGED_BY}=kuberos").items
        except ApiException as exc:
            if exc.status == 404:
                return []
            raise
        for item in items:
            found.append(
                {
                    "apiVersion": api_version,
                    "kind": kind,
                    "metadata": {"name": item.metadata.name, "namespace": namespace, "labels": dict(item.metadata.labels or {})},
                }
            )
    return found


def stale_objects(live: list[dict], keep: list[dict], deployments: list[str], remove_discovery: bool) -> list[dict]:
    """Live objects of ``deployments`` (and discovery servers) that are not in ``keep``."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import REVISION_HISTORY, REVISION_LABEL

    wanted = {_key(o) for o in keep}
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
        if (ours or discovery) and _key(obj) not in wanted:
            stale.append(obj)
    return stale


def delete_object(clients, obj: dict) -> None:
    from kubernetes.client.exceptions import ApiException

    for api_version, kind, _list, delete_method, api in MANAGED_KINDS:
        if (api_version, kind) == (obj["apiVersion"], obj["kind"]):
            try:
                getattr(clients[api], delete_method)(
                    obj["metadata"]["name"], obj["metadata"]["namespace"], propagation_policy="Background"
                )
            except ApiException as exc:
                if exc.status != 404:
                    raise
            return
    raise ValueError(f"KubeROS does not manage {obj['kind']}")


def _items(response) -> list[dict]:
    """The items of a LIST answer read without building the client's model objects (much faster for many pods)."""
    import json

    return json.loads(response.data).get("items") or []


def _ready(pod: dict) -> bool:
    return any(c.get("type") == "Ready" and c.get("status") == "True" for c in (pod.get("status") or {}).get("conditions") or [])


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
        events = _items(
            clients["core"].list_namespaced_event(
                meta["namespace"], field_selector=f"involvedObject.uid={meta['uid']},reason=Failed", _preload_content=False
            )
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
        response = clients["core"].list_namespaced_pod(
            fleet_namespace(fleet), label_selector=f"{MANAGED_BY}=kuberos", _preload_content=False
        )
        for pod in _items(response):
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
                    "ready": _ready(pod),
                    "problem": problem,
                    "problem_final": final,
                    "note": "" if _ready(pod) else pod_note(pod),
                }
            )
    return rows


def node_allocations(clients, exclude_deployments: list[str], exclude_discovery_of_fleets: list[str]) -> dict[str, dict]:
    """Resources requested per node by every running pod except those about to be placed again (of
    ``exclude_deployments``, and the discovery servers of ``exclude_discovery_of_fleets``), in the form
    the scheduler's ``allocated`` takes."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities

    used: dict[str, dict] = {}
    response = clients["core"].list_pod_for_all_namespaces(
        field_selector="status.phase!=Succeeded,status.phase!=Failed", _preload_content=False
    )
    for pod in _items(response):
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
    return sorted(ns.metadata.name for ns in clients["core"].list_namespace().items)


def unavailable_nodes(clients, wanted: list[str]) -> dict[str, str]:
    """Of the ``wanted`` nodes (inventory names), those that are not Ready or not in the cluster, with why.
    A node's inventory name is its ``device.kuberos.io/hostname`` label, else its name."""
    found = {}
    for node in _items(clients["core"].list_node(_preload_content=False)):
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
    from kubernetes.client import ApiClient
    from kubernetes.client.exceptions import ApiException

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import discovery_from_deployments
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
        merge_previous,
        record_name,
        record_placement,
    )

    plain = ApiClient().sanitize_for_serialization
    placements, objects, revisions = [], [], {}
    for fleet in sorted({t["fleet"] for t in targets}):
        namespace = fleet_namespace(fleet)
        try:
            found = clients["apps"].list_namespaced_deployment(namespace, label_selector=f"{COMPONENT}=discovery-server")
        except ApiException as exc:
            if exc.status == 404:
                continue
            raise
        objects.extend(plain(d) for d in found.items)
        for target in (t for t in targets if t["fleet"] == fleet):
            try:
                configmap = clients["core"].read_namespaced_config_map(record_name(target["name"]), namespace)
            except ApiException as exc:
                if exc.status == 404:
                    continue
                raise
            data = configmap.data or {}
            if data.get("rollout.json"):
                from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError

                raise SpecError(
                    [
                        Problem(
                            f"ConfigMap {namespace}/{configmap.metadata.name}",
                            "data.rollout.json",
                            f"a rollout of {target['name']} is in progress ({data['rollout.json'][:200]}); wait for it to "
                            "end, or remove this key if its process died (docs/software.md)",
                        )
                    ],
                    title="a rollout is in progress",
                )
            placements.append(record_placement(plain(configmap)))
            revisions[target["name"]] = {"revision": int(data.get("revision") or 0), "hash": data.get("revision-hash", "")}
    return {**merge_previous(placements, discovery_from_deployments(objects)).to_dict(), "revisions": revisions}
