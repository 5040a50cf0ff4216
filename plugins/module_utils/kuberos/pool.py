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

Every date and duration is bounded: a hold is at most ``MAX_HOLD`` (90 days), a time is RFC 3339 with a zone and
within years 1 to 9999 in UTC; anything else is refused with the bound, never an overflow. A reservation that cannot
be read (a field missing or not text, a time out of range, an owner or reason the pool would not write) holds
nothing: ``read`` returns it as a warning naming the ConfigMap and why, and every reader (deploy, rollout, the
dashboard, the pool's list) says that warning and goes on with the others.

``owner`` is a name, the one a development deployment gives in ``metadata.developer``; ``identity`` is the
Kubernetes user the cluster said wrote the reservation (a SelfSubjectReview, when it can tell): docs/security.md says
what each one guarantees (advisory: anyone who may write ConfigMaps in the fleet's namespace can change either).
"""

from __future__ import annotations

import datetime
import re
from dataclasses import dataclass

from . import labels
from .errors import Problem
from .naming import dns_label, fleet_namespace
from .schema import DEVELOPER
from .yaml_source import character_name

LABEL = "kuberos.io/reservation"
_DURATION = re.compile(r"\s*([0-9]+(?:\.[0-9]+)?)\s*(m|min|h|d)\s*\Z")  # nothing after but blanks (\Z, not $)
_UNITS = {"m": 60, "min": 60, "h": 3600, "d": 86400}
MAX_HOLD = datetime.timedelta(days=90)
MAX_TIME_TEXT = 64  # an RFC 3339 time with nanoseconds and a zone is 35 characters
HOLD_OPTION = "until (playbooks/pool.yml: -e hold=)"


@dataclass(frozen=True)
class Reservation:
    robot: str
    fleet: str
    owner: str
    reason: str
    until: datetime.datetime  # UTC
    since: datetime.datetime
    identity: str = ""  # the Kubernetes user who wrote it, as the cluster said ('' when it could not tell)

    def active(self, now: datetime.datetime) -> bool:
        return now < self.until

    def describe(self) -> str:
        return f"reserved by {self.owner} until {stamp(self.until)}" + (f" ({self.reason})" if self.reason else "")

    def to_dict(self, now: datetime.datetime | None = None) -> dict:
        data = {"robot": self.robot, "fleet": self.fleet, "owner": self.owner, "reason": self.reason,
                "until": stamp(self.until), "since": stamp(self.since)}  # fmt: skip
        if self.identity:
            data["identity"] = self.identity
        if now is not None:
            data["active"] = self.active(now)
        return data


MAX_REASON = 200  # a line in status, the pool's list and the dashboard


def owner_problem(owner: str) -> str:
    """Why ``owner`` cannot hold robots ('' when it can): the name a development deployment gives in
    ``metadata.developer``, so the spec's own rule."""
    if not isinstance(owner, str) or not owner:
        return "is empty; expected who holds the robot, such as 'alice'"
    if len(owner) > 63 or not re.fullmatch(DEVELOPER, owner):
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
            return (f"has control character {character_name(character)}; expected one printable line (no tab, line "
                    "break or other control character)")  # fmt: skip
    return ""


def _shown(text, width: int = 40) -> str:
    """``text`` quoted for a message, cut to ``width`` characters."""
    text = str(text)
    return repr(text) if len(text) <= width else repr(text[:width]) + f"... ({len(text)} characters)"


def stamp(moment: datetime.datetime) -> str:
    """``2026-11-28T18:00:00Z``; years before 1000 with four digits, so that ``parse_time`` reads them back."""
    return moment.astimezone(datetime.UTC).replace(tzinfo=None, microsecond=0).isoformat() + "Z"


def parse_time(text: str) -> datetime.datetime:
    """An RFC 3339 time (``2026-11-28T18:00:00Z``) as UTC, within years 1 to 9999; ``ValueError`` saying what is
    expected."""
    text = str(text)
    example = "expected e.g. '2026-11-28T18:00:00Z'"
    if len(text.strip()) > MAX_TIME_TEXT:
        raise ValueError(f"{_shown(text)} is not a time; {example} or a duration such as '4h'")
    try:
        moment = datetime.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"{_shown(text)} is not a time; {example} or a duration such as '4h'") from None
    if moment.tzinfo is None:
        raise ValueError(f"{_shown(text)} has no time zone; {example}")
    try:
        return moment.astimezone(datetime.UTC)
    except OverflowError:  # 9999-12-31T23:59:59-12:00 is in year 10000 in UTC
        raise ValueError(f"{_shown(text)} is out of range; expected a time within years 1 to 9999 in UTC") from None


def parse_until(text: str, now: datetime.datetime) -> datetime.datetime:
    """When a reservation ends: a time, or a duration from ``now`` ('90m', '4h', '2d'); at most 90 days ahead."""
    found = _DURATION.match(str(text))
    bound = "a robot is reserved for at most 90 days at a time (90d, 2160h or 129600m)"
    if found:
        seconds = float(found[1]) * _UNITS[found[2]]  # a float: 400 digits are inf, never an overflow
        if seconds > MAX_HOLD.total_seconds():
            raise ValueError(f"{_shown(text)} is more than 90 days; {bound}")
        until = now + datetime.timedelta(seconds=seconds)
    else:
        until = parse_time(text)
    if until <= now:
        raise ValueError(f"{_shown(text)} is not in the future; expected a later time or a duration such as '4h'")
    if until - now > MAX_HOLD:
        raise ValueError(f"{_shown(text)} is more than 90 days ahead; {bound}")
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


def read_reservation(configmap) -> Reservation:
    """The reservation a ConfigMap holds; ``ValueError`` saying why it holds none that can be read."""
    data = configmap.get("data") if isinstance(configmap, dict) else None
    if not isinstance(data, dict):
        raise ValueError("its data is not a mapping")
    for key in ("robot", "fleet", "owner", "until"):
        if key not in data:
            raise ValueError(f"has no {key}")
    for key in ("robot", "fleet", "owner", "reason", "until", "since", "identity"):
        if key in data and not isinstance(data[key], str):
            raise ValueError(f"{key}: is not text")
    for key, largest in (("robot", 253), ("fleet", 63), ("identity", 256)):
        value = data.get(key, "")
        if len(value) > largest or not all(c.isprintable() and not c.isspace() for c in value):
            raise ValueError(f"{key}: {_shown(value)} is not a name (printable, no blanks, at most {largest} characters)")
    if not data["robot"] or not data["fleet"]:
        raise ValueError("robot and fleet: expected names, found an empty one")
    for key, why in (("owner", owner_problem(data["owner"])), ("reason", reason_problem(data.get("reason", "")))):
        if why:
            raise ValueError(f"{key}: {why}")
    times = {}
    for key in ("until", "since"):
        try:
            times[key] = parse_time(data.get(key) or data["until"])
        except ValueError as exc:
            raise ValueError(f"{key}: {exc}") from None
    return Reservation(data["robot"], data["fleet"], data["owner"], data.get("reason", ""), times["until"],
                       times["since"], data.get("identity", ""))  # fmt: skip


def reservation_of(configmap: dict) -> Reservation | None:
    """The reservation a ConfigMap holds, or None when it holds none that can be read (it then holds nothing)."""
    try:
        return read_reservation(configmap)
    except ValueError:
        return None


def read(configmaps) -> tuple[list[Reservation], list[str]]:
    """The reservations of the pool's ConfigMaps that can be read, and one warning for each that cannot (it holds
    nothing), naming the ConfigMap and why: every reader says these and goes on."""
    found, warnings = [], []
    for configmap in configmaps:
        try:
            found.append(read_reservation(configmap))
        except ValueError as exc:
            meta = (configmap.get("metadata") if isinstance(configmap, dict) else None) or {}
            where = f"{meta.get('namespace', '')}/{meta.get('name', '')}"
            robot = (configmap.get("data") or {}).get("robot") if isinstance(configmap.get("data"), dict) else None
            robot = robot if isinstance(robot, str) and re.fullmatch(r"[-A-Za-z0-9_.]{1,63}", robot) else "ROBOT"
            warnings.append(f"reservation {where} ignored (it holds nothing): {exc}; give it back with "
                            f"playbooks/pool.yml -e robot={robot} -e owner=YOU -e state=absent, or delete the "
                            "ConfigMap")  # fmt: skip
    return found, warnings


def readable(configmaps) -> list[Reservation]:
    """The reservations of the pool's ConfigMaps that can be read (the others hold nothing)."""
    return read(configmaps)[0]


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
