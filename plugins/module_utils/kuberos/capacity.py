"""Capacity a fleet lacks (pure): what the controller asks a cloud provisioner for (docs/cloud.md, burst).

The controller collects, each pass, the module instances that may run in the cloud but found no node with room: a
scaling step blocked (``ModuleScaleBlocked``) or an instance stranded by a fault. ``demand`` sums them per fleet;
``advance`` keeps when a fleet's demand began and since when it has had none, so that a provisioner releases VMs
only after a quiet period. The controller writes the result per fleet to the ConfigMap ``kuberos-capacity`` in the
fleet's namespace (``demand.json``).
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass

CONFIGMAP = "kuberos-capacity"
KEY = "demand.json"


@dataclass(frozen=True)
class Shortfall:
    """One instance with no node: what it needs."""

    fleet: str
    deployment: str
    module: str
    cpu_millis: int
    memory_bytes: int
    gpu: int
    why: str


def stamp(epoch: float) -> str:
    """The stamps of ``since`` and ``quiet_since`` (RFC 3339, UTC, whole seconds), as a provisioner reads them back."""
    return datetime.datetime.fromtimestamp(epoch, datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def shortfall(module, instance, why: str) -> Shortfall | None:
    """An instance like ``instance`` of ``module`` found no node: what its fleet lacks, if the module may run in the
    cloud (a VM could hold it); None otherwise."""
    if module is None or "cloud" not in module.tiers:
        return None
    return Shortfall(
        instance.fleet, instance.deployment, instance.module, instance.cpu_millis, instance.memory_bytes, instance.gpu, why
    )


def demand(shortfalls: list[Shortfall]) -> dict[str, dict]:
    """Per fleet: instances, cpu_millis, memory_bytes, gpu and the modules (``deployment/module``) lacking room."""
    fleets: dict[str, dict] = {}
    for item in shortfalls:
        entry = fleets.setdefault(item.fleet, {"instances": 0, "cpu_millis": 0, "memory_bytes": 0, "gpu": 0, "modules": []})
        entry["instances"] += 1
        entry["cpu_millis"] += item.cpu_millis
        entry["memory_bytes"] += item.memory_bytes
        entry["gpu"] += item.gpu
        name = f"{item.deployment}/{item.module}"
        if name not in entry["modules"]:
            entry["modules"].append(name)
    for entry in fleets.values():
        entry["modules"].sort()
    return dict(sorted(fleets.items()))


def advance(previous: dict | None, current: dict | None, now: str) -> dict:
    """One fleet's ``demand.json``: ``current`` (or none), ``since`` the demand began, ``quiet_since`` it ended."""
    previous = previous or {}
    if current and current.get("instances"):
        since = previous.get("since") if previous.get("instances") else now
        return {**current, "since": since or now, "quiet_since": ""}
    quiet = previous.get("quiet_since") or now
    return {"instances": 0, "cpu_millis": 0, "memory_bytes": 0, "gpu": 0, "modules": [], "since": "", "quiet_since": quiet}
