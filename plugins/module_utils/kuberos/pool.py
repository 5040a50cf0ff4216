"""The robot pool: a developer reserves a robot to develop and test on it, and gives it back.

A reservation is a ConfigMap in the fleet's namespace, one per robot (``kuberos-reservation-<robot>``, label
``kuberos.io/reservation``): who holds the robot, why, until when. While it holds (``active``):

- production deployments (no ``metadata.developer``) leave the robot out: nothing of theirs is placed for it, and
  what ran there for them is stopped by their next deploy or rollout (it is no longer rendered); ``left_out`` says
  which robots each one left out, and why. The pool's playbook runs that pass at once (a rollout of each one at its
  current revision), for the deployments ``passes`` names;
- a development deployment (``metadata.developer: alice``) runs only on robots of its ``robotSelector`` that alice
  holds (``development_problems`` refuses any other, naming the robot and who holds it).

A reservation past its ``until`` no longer holds: production deployments return to the robot on their next pass,
as after a release (the pool's playbook runs that pass at once on a release). Pure: the pool module
(``robot_pool``) and the deploy read and write the ConfigMaps.
"""

from __future__ import annotations

import datetime
import re
from dataclasses import dataclass

from . import labels
from .errors import Problem
from .naming import dns_label, fleet_namespace
from .schema import DEVELOPER
from .yaml_source import control_character_reason

LABEL = "kuberos.io/reservation"
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(m|min|h|d)\s*$")
_UNITS = {"m": 60, "min": 60, "h": 3600, "d": 86400}
MAX_HOLD = datetime.timedelta(days=90)


@dataclass(frozen=True)
class Reservation:
    robot: str
    fleet: str
    owner: str
    reason: str
    until: datetime.datetime  # UTC
    since: datetime.datetime

    def active(self, now: datetime.datetime) -> bool:
        return now < self.until

    def describe(self) -> str:
        return f"reserved by {self.owner} until {stamp(self.until)}" + (f" ({self.reason})" if self.reason else "")

    def to_dict(self, now: datetime.datetime | None = None) -> dict:
        data = {"robot": self.robot, "fleet": self.fleet, "owner": self.owner, "reason": self.reason,
                "until": stamp(self.until), "since": stamp(self.since)}  # fmt: skip
        if now is not None:
            data["active"] = self.active(now)
        return data


MAX_REASON = 200  # a line in status, the pool's list and the dashboard


def owner_problem(owner: str) -> str:
    """Why ``owner`` cannot hold robots ('' when it can): the name a development deployment gives in
    ``metadata.developer``, so the spec's own rule."""
    if not isinstance(owner, str) or not owner:
        return "is empty; expected who holds the robot, such as 'alice'"
    if len(owner) > 63 or not re.match(DEVELOPER, owner):
        return (f"{owner[:70]!r} cannot be a RosDeployment's metadata.developer; expected letters and digits, with "
                "'-', '_', '.' and '@' inside, at most 63 characters (such as 'alice' or 'alice@example.com')")  # fmt: skip
    return ""


def reason_problem(reason: str) -> str:
    """Why ``reason`` cannot be shown to the others ('' when it can): one printable line, at most ``MAX_REASON``."""
    if not isinstance(reason, str):
        return "is not text"
    if len(reason) > MAX_REASON:
        return f"has {len(reason)} characters; expected at most {MAX_REASON} (one line, for the pool's list)"
    for character in reason:
        if not character.isprintable():
            return control_character_reason(character)
    return ""


def stamp(moment: datetime.datetime) -> str:
    return moment.astimezone(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_time(text: str) -> datetime.datetime:
    """An RFC 3339 time (``2026-11-28T18:00:00Z``) as UTC; ``ValueError`` saying what is expected."""
    try:
        moment = datetime.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"{text!r} is not a time; expected e.g. '2026-11-28T18:00:00Z' or a duration such as '4h'") from None
    if moment.tzinfo is None:
        raise ValueError(f"{text!r} has no time zone; expected e.g. '2026-11-28T18:00:00Z'")
    return moment.astimezone(datetime.UTC)


def parse_until(text: str, now: datetime.datetime) -> datetime.datetime:
    """When a reservation ends: a time, or a duration from ``now`` ('90m', '4h', '2d'); at most 90 days ahead."""
    found = _DURATION.match(str(text))
    until = now + datetime.timedelta(seconds=float(found[1]) * _UNITS[found[2]]) if found else parse_time(text)
    if until <= now:
        raise ValueError(f"{text!r} is not in the future; expected a later time or a duration such as '4h'")
    if until - now > MAX_HOLD:
        raise ValueError(f"{text!r} is more than 90 days ahead; a robot is reserved for at most 90 days at a time")
    return until


def configmap_name(robot: str) -> str:
    return dns_label("kuberos-reservation", robot)


def reservation_configmap(reservation: Reservation) -> dict:
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": configmap_name(reservation.robot),
            "namespace": fleet_namespace(reservation.fleet),
            "labels": {LABEL: "true", labels.ROBOT: dns_label(reservation.robot), labels.MANAGED_BY: "kuberos"},
        },
        "data": {k: v for k, v in reservation.to_dict().items() if k != "active"},
    }


def reservation_of(configmap: dict) -> Reservation | None:
    """The reservation a ConfigMap holds, or None when it holds none that can be read (it then holds nothing)."""
    data = configmap.get("data") or {}
    try:
        return Reservation(data["robot"], data["fleet"], data["owner"], data.get("reason", ""),
                           parse_time(data["until"]), parse_time(data.get("since") or data["until"]))  # fmt: skip
    except (KeyError, ValueError, TypeError):
        return None


def readable(configmaps) -> list[Reservation]:
    """The reservations of the pool's ConfigMaps that can be read (the others hold nothing)."""
    return [r for r in map(reservation_of, configmaps) if r is not None]


def held(reservations, now: datetime.datetime) -> dict[str, Reservation]:
    """The robots reserved now, by name."""
    return {r.robot: r for r in reservations if r.active(now)}


def left_out(dep, robots, holding: dict[str, Reservation]) -> dict[str, str]:
    """The robots of ``robots`` a production deployment leaves out, and why (a development deployment: none)."""
    if dep.developer:
        return {}
    return {robot: holding[robot].describe() for robot in robots if robot in holding}


def passes(placed: list[dict], robot: str, reserving: bool) -> list[str]:
    """The production deployments of a placement's ``deployments`` entries whose pass changes what runs for
    ``robot`` now: when it is reserved, those that place modules for it (the pass stops them); when it is given
    back, those that left it out for a reservation (the pass returns to it)."""
    names = []
    for entry in placed:
        if entry.get("developer"):
            continue
        if robot in (entry.get("robots") or ()) if reserving else robot in (entry.get("left_out") or {}):
            names.append(entry["name"])
    return names


def development_problems(deployments, holding: dict[str, Reservation]) -> list[Problem]:
    """Each robot of a development deployment that its developer does not hold now."""
    problems = []
    for dep in deployments:
        if not dep.developer:
            continue
        for index, robot in enumerate(dep.robots or ()):
            found = holding.get(robot)
            if found is not None and found.owner == dep.developer:
                continue
            why = f"is {found.describe()}" if found else "is not reserved"
            path = f"metadata.robotSelector.robot[{index}]"
            problems.append(
                Problem(
                    dep.source,
                    dep.field(path),
                    f"robot {robot} {why}; the development deployment of {dep.developer} "
                    f"runs only on robots {dep.developer} holds (playbooks/pool.yml -e robot={robot} "
                    f"-e owner={dep.developer})",
                    dep.line_of(path),
                )
            )
    return problems
