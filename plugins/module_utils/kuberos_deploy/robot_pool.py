"""The robot pool's reads and writes: a reservation's ConfigMap in the fleet's namespace, created, renewed or
removed; what the fleet's production deployments still run for a robot. The rules are ``kuberos.pool``'s."""

from __future__ import annotations

import datetime

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import RECORD_LABEL, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube

MANAGER = "kuberos-pool"


class PoolRefused(KuberosError):
    """The robot is held by someone else, or is not a robot of the inventory."""


def now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def reservations(kube: Kube, fleet: str = "") -> list[robot_pool.Reservation]:
    """Every reservation of ``fleet`` (every fleet's when ''), expired ones included."""
    found = kube.list("ConfigMap", fleet_namespace(fleet) if fleet else "", selector=f"{robot_pool.LABEL}=true")
    return sorted(robot_pool.readable(found), key=lambda r: (r.fleet, r.robot))


def current(kube: Kube, fleet: str, robot: str) -> robot_pool.Reservation | None:
    found = kube.get("ConfigMap", robot_pool.configmap_name(robot), fleet_namespace(fleet))
    return robot_pool.reservation_of(found) if found else None


def production_on(kube: Kube, fleet: str, robot: str) -> list[str]:
    """The deployments without a developer that still run modules for ``robot`` (its dedicated instances)."""
    found = kube.list("Deployment", fleet_namespace(fleet), selector=f"{labels.ROBOT}={robot},{labels.COMPONENT}=ros-module")
    production = [d for d in found if not (d["metadata"].get("annotations") or {}).get(labels.DEVELOPER_ANNOTATION)]
    return sorted({d["metadata"]["labels"].get(labels.DEPLOYMENT, "") for d in production})


def passes(kube: Kube, fleet: str, robot: str, reserving: bool) -> list[dict]:
    """The fleet's production deployments whose pass (a rollout at their current revision) stops what they run for
    ``robot`` now it is reserved, or returns to it now it is given back: deployment, fleet and revision each. A
    record that cannot be read is left to its deployment's own next deploy, which says what is wrong with it."""
    found = []
    for configmap in kube.list("ConfigMap", fleet_namespace(fleet), selector=f"{RECORD_LABEL}=true"):
        try:
            record = parse_record(configmap)
        except SpecError:
            continue
        if record.deployment in robot_pool.passes(record.placement.deployments, robot, reserving):
            found.append({"deployment": record.deployment, "fleet": fleet, "revision": record.revision})
    return sorted(found, key=lambda p: p["deployment"])


def reserve(kube: Kube, fleet: str, robot: str, owner: str, reason: str, until: str, check_mode: bool) -> dict:
    """Reserve ``robot`` for ``owner`` (or renew the owner's reservation); refused while another holds it."""
    moment = now()
    try:
        ends = robot_pool.parse_until(until, moment)
    except ValueError as exc:
        raise KuberosError(f"until: {exc}") from None
    for field, why in (("owner", robot_pool.owner_problem(owner)), ("reason", robot_pool.reason_problem(reason))):
        if why:
            raise KuberosError(f"{field}: {why}")
    before = current(kube, fleet, robot)
    if before is not None and before.active(moment) and before.owner != owner:
        raise PoolRefused(f"robot {robot} is {before.describe()}; ask {before.owner} to release it, or wait")
    since = before.since if before is not None and before.active(moment) else moment
    after = robot_pool.Reservation(robot, fleet, owner, reason, ends, since)
    changed = before is None or not before.active(moment) or (before.owner, before.reason, before.until) != (owner, reason, ends)
    if changed and not check_mode:
        namespace = fleet_namespace(fleet)
        if kube.get("Namespace", namespace) is None:
            kube.apply({"apiVersion": "v1", "kind": "Namespace",
                        "metadata": {"name": namespace, "labels": {labels.MANAGED_BY: "kuberos", labels.FLEET: fleet}}},
                       manager=MANAGER)  # fmt: skip
        kube.apply(robot_pool.reservation_configmap(after), manager=MANAGER)
    return {"changed": changed, "before": before, "after": after, "production": production_on(kube, fleet, robot),
            "passes": passes(kube, fleet, robot, reserving=True)}  # fmt: skip


def release(kube: Kube, fleet: str, robot: str, owner: str, force: bool, check_mode: bool) -> dict:
    """Give ``robot`` back; only its holder may, unless ``force`` (or the reservation has ended)."""
    before = current(kube, fleet, robot)
    if before is None:
        return {"changed": False, "before": None, "after": None, "production": [], "passes": passes(kube, fleet, robot, False)}
    if before.active(now()) and before.owner != owner and not force:
        raise PoolRefused(f"robot {robot} is {before.describe()}; only {before.owner} releases it (or force: true)")
    if not check_mode:
        kube.delete("ConfigMap", robot_pool.configmap_name(robot), fleet_namespace(fleet))
    return {"changed": True, "before": before, "after": None, "production": [], "passes": passes(kube, fleet, robot, False)}
