"""Kubernetes Node objects from the inventory: labels and taints for real nodes (the resource
manager), and whole simulated nodes with capacity for the local cluster (kwok)."""

from __future__ import annotations

from . import labels
from .inventory import Inventory, Node
from .quantities import format_cpu, format_memory

KWOK_ANNOTATION = "kwok.x-k8s.io/node"


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


def cluster_nodes(inventory: Inventory, simulated: bool) -> list[dict]:
    """One object per inventory node, sorted by name."""
    build = simulated_node if simulated else node_label_patch
    return [build(node) for node in inventory.nodes.values()]


def robot_taints(inventory: Inventory) -> list[dict]:
    """``{name, taints}`` for every robot node: the taints to merge into real nodes."""
    return [{"name": n.name, "taints": labels.node_taints(n)} for n in inventory.nodes.values() if n.tier == "onboard"]
