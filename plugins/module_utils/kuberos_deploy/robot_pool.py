"""The robot pool's reads and writes: a reservation's ConfigMap in the fleet's namespace, created, renewed or
removed; what the fleet's production deployments still run for a robot. The rules are ``kuberos.pool``'s.

Who writes: the API server is asked who the caller is (a SelfSubjectReview, Kubernetes 1.28+), and the reservation
records that Kubernetes user (``identity``). A reservation that records one is renewed or given back (without
``force``) only by that user; ``owner`` stays a name the caller gives. This is advisory, as ``ownership`` says in
every answer: whoever may write ConfigMaps in the fleet's namespace can change a reservation (docs/security.md).
"""

from __future__ import annotations

import datetime

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import RECORD_LABEL, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, status_of

MANAGER = "kuberos-pool"


class PoolRefused(KuberosError):
    """The robot is held by someone else, or is not a robot of the inventory."""


def now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def reservations(kube: Kube, fleet: str = "", warn=None) -> list[robot_pool.Reservation]:
    """Every reservation of ``fleet`` (every fleet's when ''), expired ones included; each one that cannot be read
    is left out, and ``warn`` (when given) hears why."""
    found = kube.list("ConfigMap", fleet_namespace(fleet) if fleet else "", selector=f"{robot_pool.LABEL}=true")
    readable, warnings = robot_pool.read(found)
    for warning in warnings:
        if warn is not None:
            warn(warning)
    return sorted(readable, key=lambda r: (r.fleet, r.robot))


ADVISORY = ("ownership is advisory: owner is a name; a reservation records the Kubernetes user who wrote it, and whoever "
            "may write ConfigMaps in a fleet's namespace can change or remove it (docs/security.md)")  # fmt: skip


def listing(kube: Kube, moment: datetime.datetime) -> dict:
    """The pool as ``playbooks/pool.yml`` and ``status.yml`` show it: every reservation with ``active``, and the
    warnings of those that cannot be read (``ignored``)."""
    ignored: list[str] = []
    found = reservations(kube, warn=ignored.append)
    return {"reservations": [r.to_dict(moment) for r in found], "ignored": ignored}


def caller(kube: Kube) -> str:
    """The Kubernetes user the API server says the caller is (a SelfSubjectReview); '' when it cannot tell (before
    Kubernetes 1.28, or the review refused)."""
    try:
        review = kube.create({"apiVersion": "authentication.k8s.io/v1", "kind": "SelfSubjectReview"})
    except Exception as exc:  # pylint: disable=broad-exception-caught
        if status_of(exc) in (403, 404, 405):
            return ""
        raise
    user = ((review or {}).get("status") or {}).get("userInfo") or {}
    name = user.get("username", "")
    return name if isinstance(name, str) and name.isprintable() and len(name) <= 256 else ""


def ownership(identity: str, fleet: str) -> str:
    """What the owner's name means, said with every answer of the pool."""
    where = f"whoever may write ConfigMaps in {fleet_namespace(fleet)} can change or remove a reservation"
    if identity:
        return (f"ownership is advisory: the reservation records the Kubernetes user {identity}, and only that user "
                f"renews it or gives it back without force; the owner is a name, not checked against it; {where} "
                "(docs/security.md)")  # fmt: skip
    return (f"ownership is advisory: the cluster cannot tell who you are (no SelfSubjectReview), so the owner is a "
            f"name anyone can give; {where} (docs/security.md)")  # fmt: skip


def _stored(kube: Kube, fleet: str, robot: str) -> tuple[dict | None, robot_pool.Reservation | None]:
    """The robot's reservation ConfigMap and what it holds (None when it holds nothing that can be read)."""
    found = kube.get("ConfigMap", robot_pool.configmap_name(robot), fleet_namespace(fleet))
    return found, (robot_pool.reservation_of(found) if found else None)


def current(kube: Kube, fleet: str, robot: str) -> robot_pool.Reservation | None:
    return _stored(kube, fleet, robot)[1]


def _not_theirs(robot: str, before: robot_pool.Reservation, identity: str, what: str) -> str:
    """Why the caller may not ``what`` (renew, give back) ``before`` ('' when they may): another Kubernetes user wrote it."""
    if not before.identity or not identity or before.identity == identity:
        return ""
    return (f"robot {robot} is {before.describe()}, written by Kubernetes user {before.identity}; you are {identity}: "
            f"only they {what} it")  # fmt: skip


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
        raise KuberosError(f"{robot_pool.HOLD_OPTION}: {exc}") from None
    for field, why in (("owner", robot_pool.owner_problem(owner)), ("reason", robot_pool.reason_problem(reason))):
        if why:
            raise KuberosError(f"{field}: {why}")
    identity = caller(kube)
    before = current(kube, fleet, robot)
    if before is not None and before.active(moment) and before.owner != owner:
        raise PoolRefused(f"robot {robot} is {before.describe()}; ask {before.owner} to release it, or wait")
    if before is not None and before.active(moment):
        why = _not_theirs(robot, before, identity, "renew")
        if why:
            raise PoolRefused(f"{why} (or give it back with force: true, then reserve it)")
    since = before.since if before is not None and before.active(moment) else moment
    after = robot_pool.Reservation(robot, fleet, owner, reason, ends, since, identity)
    changed = (before is None or not before.active(moment)
               or (before.owner, before.reason, before.until, before.identity) != (owner, reason, ends, identity))  # fmt: skip
    if changed and not check_mode:
        namespace = fleet_namespace(fleet)
        if kube.get("Namespace", namespace) is None:
            kube.apply({"apiVersion": "v1", "kind": "Namespace",
                        "metadata": {"name": namespace, "labels": {labels.MANAGED_BY: "kuberos", labels.FLEET: fleet}}},
                       manager=MANAGER)  # fmt: skip
        kube.apply(robot_pool.reservation_configmap(after), manager=MANAGER)
    return {"changed": changed, "before": before, "after": after, "production": production_on(kube, fleet, robot),
            "passes": passes(kube, fleet, robot, reserving=True), "identity": identity,
            "ownership": ownership(identity, fleet)}  # fmt: skip


def release(kube: Kube, fleet: str, robot: str, owner: str, force: bool, check_mode: bool) -> dict:
    """Give ``robot`` back; only its holder may, unless ``force`` (or the reservation has ended). A ConfigMap that
    holds no reservation that can be read is removed."""
    identity = caller(kube)
    said = {"identity": identity, "ownership": ownership(identity, fleet)}
    stored, before = _stored(kube, fleet, robot)
    if stored is None:
        return {"changed": False, "before": None, "after": None, "production": [], "passes": passes(kube, fleet, robot, False),
                **said}  # fmt: skip
    if before is not None and before.active(now()) and not force:
        if before.owner != owner:
            raise PoolRefused(f"robot {robot} is {before.describe()}; only {before.owner} releases it (or force: true)")
        why = _not_theirs(robot, before, identity, "give back")
        if why:
            raise PoolRefused(f"{why} (or force: true)")
    if not check_mode:
        kube.delete("ConfigMap", robot_pool.configmap_name(robot), fleet_namespace(fleet))
    return {"changed": True, "before": before, "after": None, "production": [], "passes": passes(kube, fleet, robot, False),
            **said}  # fmt: skip
