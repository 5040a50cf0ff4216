"""Kubernetes Node objects from the inventory: labels and taints for real nodes (the resource
manager), and whole simulated nodes with capacity for the local cluster (kwok)."""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import Inventory, Node
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.quantities import format_cpu, format_memory

from .link_delays import link_losses, link_rates_bps, one_way_delays_ms

KWOK_ANNOTATION = labels.KWOK_NODE


def node_label_patch(node: Node) -> dict:
    """What the resource manager owns on a real node through server-side apply: its labels.

    Taints are not in it: ``spec.taints`` is an atomic list for server-side apply, so owning it would
    wipe the taints the node lifecycle controller sets; they are merged separately (``node_taints``).
    """
    return {"apiVersion": "v1", "kind": "Node", "metadata": {"name": node.name, "labels": labels.node_labels(node)}}


def simulated_node(node: Node) -> dict:
    """A kwok-managed node carrying the same labels and taints, and the inventory's capacity."""
    capacity = {
        "cpu": format_cpu(node.cpu_millis),
        "memory": format_memory(node.memory_bytes),
        "pods": str(node.pods),
    }
    if node.gpu:
        capacity["nvidia.com/gpu"] = str(node.gpu)
    obj = node_label_patch(node)
    if node.tier == "onboard":
        obj["spec"] = {"taints": labels.node_taints(node)}
    obj["metadata"]["labels"] = {
        **obj["metadata"]["labels"],
        "kubernetes.io/hostname": node.name,
        "kubernetes.io/arch": node.arch,
        "kubernetes.io/os": "linux",
        "type": "kwok",
    }
    obj["metadata"]["annotations"] = {KWOK_ANNOTATION: "fake"}
    obj["status"] = {
        "capacity": capacity,
        "allocatable": dict(capacity),
        "nodeInfo": {"architecture": node.arch, "operatingSystem": "linux", "kubeletVersion": "fake"},
        "phase": "Running",
    }
    return obj


def cluster_nodes(inventory: Inventory, simulated: bool, exclude=()) -> list[dict]:
    """One object per inventory node, sorted by name; ``exclude``: node names left out (the local cluster's
    real nodes, which their kubelets register)."""
    build = simulated_node if simulated else node_label_patch
    return [build(node) for node in inventory.nodes.values() if node.name not in set(exclude)]


LOCAL_NODE_VAR = "kuberos_local_node"
LOCAL_NODE_KINDS = ("simulated", "real")


def real_node_names(raw: dict, hostvars: dict, source: str = "inventory") -> list[str]:
    """Node names of the hosts whose ``kuberos_local_node`` is ``real`` (the local cluster runs a kubelet for
    each, in a network namespace); every other host is a kwok node. ``raw``: the fleet inventory's hosts."""
    problems, names = [], []
    for host, hv in sorted((raw.get("hosts") or {}).items()):
        kind = (hostvars.get(host) or {}).get(LOCAL_NODE_VAR, "simulated")
        if kind not in LOCAL_NODE_KINDS:
            problems.append(
                Problem(source, f"hosts.{host}.{LOCAL_NODE_VAR}", f"{describe(kind)} is not valid; expected real or simulated")
            )
        elif kind == "real":
            names.append((hv or {}).get("kuberos_node_name", host))
    if problems:
        raise SpecError(problems)
    return sorted(names)


def real_nodes(inventory: Inventory, names: list[str]) -> dict:
    """What the local cluster needs to run real nodes: each node's labels and taints (its kubelet registers with
    them, so no pod lands before they exist), the one-way delay between every two of them, and the bandwidth and loss
    of the links that have them (link_delays)."""
    nodes = [inventory.nodes[name] for name in sorted(names)]
    return {
        "nodes": [
            {
                "name": node.name,
                "tier": node.tier,
                "labels": labels.node_labels(node),
                "taints": labels.node_taints(node),
            }
            for node in nodes
        ],
        "delay_ms": one_way_delays_ms(inventory, [node.name for node in nodes]),
        "link_bps": link_rates_bps(inventory, [node.name for node in nodes]),
        "link_loss": link_losses(inventory, [node.name for node in nodes]),
    }


def robot_taints(inventory: Inventory) -> list[dict]:
    """``{name, taints}`` for every robot node: the taints to merge into real nodes."""
    return [{"name": n.name, "taints": labels.node_taints(n)} for n in inventory.nodes.values() if n.tier == "onboard"]


def not_joined(inventory: Inventory, existing) -> dict[str, list[str]]:
    """The inventory's nodes the cluster has no Node for (``existing``: the Node names it has): ``robots`` (powered
    off or never joined: left for a later run) and ``others`` (edge servers and cloud VMs: a site needs them)."""
    have = set(existing)
    missing = [node for node in inventory.nodes.values() if node.name not in have]
    return {
        "robots": sorted(n.name for n in missing if n.tier == "onboard"),
        "others": sorted(n.name for n in missing if n.tier != "onboard"),
    }


def _condition(obj: dict, kind: str) -> str | None:
    for condition in (obj.get("status") or {}).get("conditions") or ():
        if condition.get("type") == kind:
            return condition.get("status")
    return None


def agents_waiting(pods, nodes) -> list[str]:
    """The nodes still waiting for a node agent (a CNI's DaemonSet pod): every node whose kubelet reports (its Ready
    condition True or False, or none yet) and that has no Ready agent pod. A node whose kubelet stopped reporting
    (Ready Unknown: a robot powered off) is not waited for; it runs its agent when it is back."""
    ready_on = {
        (pod.get("spec") or {}).get("nodeName")
        for pod in pods or ()
        if not (pod.get("metadata") or {}).get("deletionTimestamp") and _condition(pod, "Ready") == "True"
    }
    return sorted(
        node["metadata"]["name"]
        for node in nodes or ()
        if _condition(node, "Ready") != "Unknown" and node["metadata"]["name"] not in ready_on
    )
