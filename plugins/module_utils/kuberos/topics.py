"""Declared topics: what each module says it publishes and subscribes, checked before anything is applied and
against the live graph afterwards.

A module (or its catalog entry) may declare ``topics``::

    topics:
      publishes:
      - {name: detections, type: geometry_msgs/msg/PoseArray, qos: {reliability: best_effort}, rate: {min: 5}}
      subscribes:
      - {name: camera/rgb, type: sensor_msgs/msg/Image, external: true}

A relative name is in the robot's namespace (``detections`` is ``/fetch_1/detections`` on fetch-1), the same topic
as ``/{robot}/detections``; an absolute name without ``{robot}`` is one topic for the whole fleet.

``declaration_findings`` (called by the spec's validation) refuses a graph whose declarations cannot match: a
subscription that no module publishes (unless ``external``), a type that differs, QoS that never matches (a reliable
subscription of a best-effort publisher, a transient-local subscription of a volatile one), a subscription that needs
more than the publisher's declared rate. Each problem is one line naming both modules, the topic and why; a
deployment shows the first ``MAX_FINDINGS`` (20) and counts the others. Declarations that decide a match alike are
judged once per group, so that modules sharing one ``topics`` block through a YAML alias (100 modules x 100 topics:
a million pairs from 13 KB of text) cost one judgement per group, not one per pair.

``expectations`` turns the declarations into the plain data the ROS probe receives (``KUBEROS_TOPICS``);
``live_problems`` judges what the probe saw in the graph (endpoints with their types and QoS, measured rates)
against it. Both are pure: the probe (``kuberos_deploy/ros_graph_probe.py``) only gathers what it sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .naming import robot_ros_name
from .quantities import format_latency, parse_latency_ms
from .spec_model import DeclaredTopic

ROBOT = "{robot}"
DEFAULT_RELIABILITY = "reliable"
DEFAULT_DURABILITY = "volatile"
DEFAULT_DEPTH = 10
DEFAULT_LIVELINESS = "automatic"
DIRECTIONS = ("publishes", "subscribes")
PROBE_NODE = "kuberos_rollout_probe"  # the probe's own node; its rate subscriptions are not the modules'


def scoped(name: str) -> str:
    """The form compared across modules: ``detections`` and ``/{robot}/detections`` are ``/{robot}/detections``."""
    return name if name.startswith("/") else f"/{ROBOT}/{name}"


def for_robot(name: str, robot: str) -> str:
    """A scoped name on one robot: ``/{robot}/detections`` is ``/fetch_1/detections`` on fetch-1."""
    return name.replace(ROBOT, robot_ros_name(robot))


def declared(raw, origin: str = "") -> tuple[DeclaredTopic, ...]:
    """The declarations of a module's validated ``topics`` mapping, publishes first."""
    topics = []
    for direction in DIRECTIONS:
        for position, item in enumerate((raw or {}).get(direction) or ()):
            qos = item.get("qos") or {}
            rate = item.get("rate") or {}
            topics.append(
                DeclaredTopic(
                    name=item["name"],
                    type=item["type"],
                    direction=direction,
                    reliability=qos.get("reliability", DEFAULT_RELIABILITY),
                    durability=qos.get("durability", DEFAULT_DURABILITY),
                    depth=int(qos.get("depth", DEFAULT_DEPTH)),
                    deadline_ms=_duration_ms(qos.get("deadline")),
                    liveliness=qos.get("liveliness", DEFAULT_LIVELINESS),
                    lease_ms=_duration_ms(qos.get("lease_duration")),
                    rate_min=float(rate["min"]) if "min" in rate else None,
                    rate_max=float(rate["max"]) if "max" in rate else None,
                    external=bool(item.get("external", False)),
                    position=position,
                    origin=origin,
                )
            )
    return tuple(topics)


def _duration_ms(value) -> float | None:
    """A validated duration in milliseconds; None when absent or 0 (ROS's infinite)."""
    if value is None:
        return None
    ms = parse_latency_ms(value)
    return ms if ms > 0 else None


def _offered_within(offered: float | None, requested: float | None) -> bool:
    """Whether an offered duration (None: infinite) is at most the requested one (None: infinite)."""
    return requested is None or (offered is not None and offered <= requested)


def _duration(ms: float | None) -> str:
    return "none" if ms is None else format_latency(ms)


# (policy, what a subscription may demand, the publisher's value that never serves it)
_STRICTER = (
    ("reliability", "reliable", "best_effort"),
    ("durability", "transient_local", "volatile"),
    ("liveliness", "manual_by_topic", "automatic"),
)
# (attribute, what it is): a publisher serves a subscription when it offers at most the duration requested
_DURATIONS = (("deadline_ms", "deadline"), ("lease_ms", "liveliness lease"))


def qos_mismatch(publisher, subscription) -> str:
    """Why a publisher's QoS never serves a subscription's (ROS 2's request-offered rules), or ''. Both carry
    ``reliability``, ``durability``, ``liveliness``, ``deadline_ms`` and ``lease_ms`` (a ``DeclaredTopic`` or an
    ``Endpoint`` the probe saw)."""
    reasons = []
    for policy, demanded, short in _STRICTER:
        if getattr(subscription, policy) == demanded and getattr(publisher, policy) == short:
            article = "an" if short[0] in "aeiou" else "a"
            reasons.append(
                f"a {demanded} subscription gets nothing from {article} {short} publisher (expected {policy} {short} "
                f"in the subscription, or {demanded} in the publisher)"
            )
    for attribute, what in _DURATIONS:
        offered, requested = getattr(publisher, attribute), getattr(subscription, attribute)
        if not _offered_within(offered, requested):
            reasons.append(
                f"a subscription requesting a {what} of {_duration(requested)} gets nothing from a publisher offering "
                f"{_duration(offered)} (expected the publisher's {what} at most the subscription's)"
            )
    return "; ".join(reasons)


MAX_FINDINGS = 20  # lines one deployment's declared-topic problems show; the rest are counted, not built


@dataclass(frozen=True)
class Finding:
    """One declaration that cannot match: the module and declaration it is about, and the line saying why."""

    module: object  # the RosModule
    topic: DeclaredTopic
    message: str


@dataclass
class Findings:
    """The first ``limit`` findings of one deployment, in the order of the spec, and how many more there are."""

    shown: list[Finding] = field(default_factory=list)
    more: int = 0
    limit: int = MAX_FINDINGS

    @property
    def room(self) -> int:
        return self.limit - len(self.shown)

    def add(self, module, topic: DeclaredTopic, message: str) -> None:
        if self.room > 0:
            self.shown.append(Finding(module, topic, message))
        else:
            self.more += 1


def _rate(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"{low:g}-{high:g} Hz"
    return f"at least {low:g} Hz" if low is not None else f"at most {high:g} Hz"


def _publisher_signature(topic: DeclaredTopic) -> tuple:
    """What ``_pair_problem`` reads of a publication: publications alike in it meet every subscription alike."""
    return (topic.type, topic.reliability, topic.durability, topic.liveliness, topic.deadline_ms, topic.lease_ms, topic.rate_max)


def _subscription_signature(topic: DeclaredTopic) -> tuple:
    return (topic.type, topic.reliability, topic.durability, topic.liveliness, topic.deadline_ms, topic.lease_ms, topic.rate_min)


@dataclass
class _Offers:
    """The publications of one topic: all of them in the spec's order, and grouped by signature (a representative
    declaration and how many share it)."""

    all: list = field(default_factory=list)  # (module, DeclaredTopic)
    groups: dict = field(default_factory=dict)  # signature -> [representative DeclaredTopic, count]

    def add(self, module, topic: DeclaredTopic) -> None:
        self.all.append((module, topic))
        group = self.groups.setdefault(_publisher_signature(topic), [topic, 0])
        group[1] += 1


def declaration_findings(modules, limit: int = MAX_FINDINGS) -> Findings:
    """Every declaration of ``modules`` (one deployment's) that cannot match another, or that contradicts itself: the
    first ``limit`` as findings, the others counted.

    Declarations are grouped by topic and, within a topic, by what decides a match (type, QoS, rate): each group of
    subscriptions is judged once against each group of publications, so that modules sharing one ``topics`` block
    (a YAML alias) cost one judgement, not one per pair; the pairs past ``limit`` are counted by multiplying group
    sizes, never built."""
    findings = Findings(limit=limit)
    offers: dict[str, _Offers] = {}
    seen: dict[tuple, DeclaredTopic] = {}
    for module in modules:
        for topic in module.topics:
            key = (module.name, topic.direction, scoped(topic.name))
            if key in seen:
                first = seen[key]
                message = (
                    f"{module.name} already declares {topic.direction} {scoped(topic.name)} "
                    f"({topic.direction}[{first.position}]); expected each topic once"
                )
                findings.add(module, topic, message)
                continue
            seen[key] = topic
            if topic.rate_min is not None and topic.rate_max is not None and topic.rate_min > topic.rate_max:
                findings.add(module, topic, f"rate min {topic.rate_min:g} Hz is above max {topic.rate_max:g} Hz")
            if topic.direction == "publishes":
                offers.setdefault(scoped(topic.name), _Offers()).add(module, topic)
    refused: dict[tuple, int] = {}  # (topic, subscription signature) -> how many publications never serve it
    for module in modules:
        for topic in module.topics:
            if topic.direction != "subscribes" or seen.get((module.name, topic.direction, scoped(topic.name))) is not topic:
                continue
            name = scoped(topic.name)
            offered = offers.get(name) or _Offers()
            if not offered.all and not topic.external:
                message = (
                    f"{module.name} subscribes to {name}, which no module of the deployment publishes; expected a "
                    "module that declares it in publishes, or external: true for a topic published outside the deployment"
                )
                findings.add(module, topic, message)
            key = (name, _subscription_signature(topic))
            if key not in refused:
                refused[key] = sum(count for published, count in offered.groups.values() if _pair_problem(published, topic))
            count = refused[key]
            if count and findings.room > 0:
                shown = 0
                for other, published in offered.all:
                    if shown == count or findings.room == 0:
                        break
                    why = _pair_problem(published, topic)
                    if why:
                        findings.add(module, topic, f"{module.name} subscribes to {name} but {other.name} publishes it: {why}")
                        shown += 1
                findings.more += count - shown
            else:
                findings.more += count
    return findings


def _pair_problem(published: DeclaredTopic, subscribed: DeclaredTopic) -> str:
    if published.type != subscribed.type:
        return f"the types differ ({subscribed.type} subscribed, {published.type} published)"
    why = qos_mismatch(published, subscribed)
    if why:
        return why
    if subscribed.rate_min is not None and published.rate_max is not None and subscribed.rate_min > published.rate_max:
        return (f"it needs at least {subscribed.rate_min:g} Hz and the publisher declares at most "
                f"{published.rate_max:g} Hz")  # fmt: skip
    return ""


# -- the live check ------------------------------------------------------------------------------------------------


@dataclass
class Expectation:
    """One topic as the live check wants it on every robot (or once, for a fleet-wide name)."""

    name: str  # scoped
    type: str
    publishers: list[str] = field(default_factory=list)  # modules that declare publishing it
    subscribers: list[str] = field(default_factory=list)
    rate_min: float | None = None
    rate_max: float | None = None
    rate_by: list[str] = field(default_factory=list)  # modules whose bounds these are
    external: bool = False

    def to_dict(self) -> dict:
        data = {"name": self.name, "type": self.type, "publishers": self.publishers, "subscribers": self.subscribers}
        if self.rate_min is not None:
            data["rate_min"] = self.rate_min
        if self.rate_max is not None:
            data["rate_max"] = self.rate_max
        if self.rate_by:
            data["rate_by"] = self.rate_by
        if self.external:
            data["external"] = True
        return data

    @classmethod
    def from_dict(cls, data: dict) -> Expectation:
        if not isinstance(data, dict) or not isinstance(data.get("name"), str) or not isinstance(data.get("type"), str):
            raise ValueError(f"{str(data)[:80]!r} is not a topic expectation; expected a mapping with name and type")
        rate = {k: data.get(k) for k in ("rate_min", "rate_max")}
        for key, value in rate.items():
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)):
                raise ValueError(f"{data['name']}: {key} {value!r} is not a finite number")
        names = {k: data.get(k) or [] for k in ("publishers", "subscribers", "rate_by")}
        if not all(isinstance(v, list) and all(isinstance(x, str) for x in v) for v in names.values()):
            raise ValueError(f"{data['name']}: publishers, subscribers and rate_by must be lists of module names")
        return cls(data["name"], data["type"], names["publishers"], names["subscribers"], rate["rate_min"],
                   rate["rate_max"], names["rate_by"], bool(data.get("external", False)))  # fmt: skip

    @property
    def per_robot(self) -> bool:
        return ROBOT in self.name


def expectations(modules) -> list[Expectation]:
    """What the live check wants of the declared topics of ``modules`` (sorted by name)."""
    found: dict[str, Expectation] = {}
    for module in modules:
        for topic in module.topics:
            name = scoped(topic.name)
            want = found.setdefault(name, Expectation(name, topic.type))
            side = want.publishers if topic.direction == "publishes" else want.subscribers
            if module.name not in side:
                side.append(module.name)
            want.external = want.external or topic.external
            if topic.rate_min is not None or topic.rate_max is not None:
                want.rate_by.append(module.name)
            if topic.rate_min is not None:
                want.rate_min = max(topic.rate_min, want.rate_min or 0.0)
            if topic.rate_max is not None:
                want.rate_max = topic.rate_max if want.rate_max is None else min(topic.rate_max, want.rate_max)
    return [found[name] for name in sorted(found)]


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription the probe saw: its node (fully qualified), type and QoS names."""

    node: str
    type: str
    reliability: str
    durability: str
    deadline_ms: float | None = None  # None: infinite
    liveliness: str = DEFAULT_LIVELINESS
    lease_ms: float | None = None


@dataclass
class Observed:
    """One topic as the probe saw it."""

    publishers: list[Endpoint] = field(default_factory=list)
    subscribers: list[Endpoint] = field(default_factory=list)
    rate: float | None = None  # messages per second over the probe's window; None when not measured


def topics_to_watch(wanted: list[Expectation], robots: list[str]) -> list[tuple[str, Expectation, str]]:
    """(topic name, its expectation, robot or '') for every robot of every per-robot expectation, and each fleet-wide
    one once."""
    out = []
    for want in wanted:
        targets = robots if want.per_robot else [""]
        for robot in targets:
            out.append((for_robot(want.name, robot) if robot else want.name, want, robot))
    return out


def missing(name: str, want: Expectation, seen: Observed) -> list[str]:
    """What is not (yet) in the graph for ``name``: the lines of endpoints that discovery may still bring."""
    lines = []
    if want.subscribers and not seen.subscribers:
        lines.append(f"{name}: no subscription in the graph ({', '.join(want.subscribers)} declares one)")
    if (want.publishers or want.subscribers) and not seen.publishers:
        who = f"{', '.join(want.publishers)} declares it" if want.publishers else "declared external"
        lines.append(f"{name}: nobody publishes it ({who})")
    return lines


def mismatches(name: str, want: Expectation, seen: Observed) -> list[str]:
    """What waiting does not mend: endpoints of another type, publisher-subscription pairs whose QoS never match."""
    lines = []
    for side, endpoints in (("publishes", seen.publishers), ("subscribes", seen.subscribers)):
        for point in endpoints:
            if point.type != want.type:
                lines.append(f"{name}: {point.node} {side} {point.type}, but the declared type is {want.type}")
    for publisher in seen.publishers:
        for subscriber in seen.subscribers:
            why = qos_mismatch(publisher, subscriber)
            if why:
                lines.append(f"{name}: {subscriber.node} and {publisher.node} never match: {why}")
    return lines


def rate_problem(name: str, want: Expectation, seen: Observed, window_s: float) -> str:
    """Why the measured rate is outside the declared bounds, or ''."""
    if want.rate_min is None and want.rate_max is None:
        return ""
    declared_by = ", ".join(want.rate_by)
    bounds = _rate(want.rate_min, want.rate_max)
    if seen.rate is None:
        return f"{name}: rate not measured (declared {bounds} by {declared_by})"
    low = want.rate_min is not None and seen.rate < want.rate_min
    high = want.rate_max is not None and seen.rate > want.rate_max
    if low or high:
        return f"{name}: {seen.rate:.1f} Hz over {window_s:g} s, outside {bounds} (declared by {declared_by})"
    return ""


def live_problems(watched: list[tuple[str, Expectation, str]], observed: dict[str, Observed], window_s: float) -> list[str]:
    """Every line of what the graph lacks or gets wrong, for the topics ``topics_to_watch`` gave."""
    lines = []
    for name, want, _robot in watched:
        seen = observed.get(name) or Observed()
        absent = missing(name, want, seen)
        lines += absent + mismatches(name, want, seen)
        why = "" if absent else rate_problem(name, want, seen, window_s)
        if why:
            lines.append(why)
    return lines


def by_robot(topics: list[dict], problems: list[str], robots: list[str]) -> dict[str, dict]:
    """A probe report split per robot (``''`` for the fleet-wide topics): each robot's topics (name, type, publishing
    and subscribing nodes, rate) and the problem lines about its topics, ``ok`` when it has none."""
    split: dict[str, dict] = {robot: {"ok": True, "topics": [], "problems": []} for robot in robots}
    prefixes = {f"/{robot_ros_name(r)}/": r for r in robots}
    for topic in topics:
        entry = split.setdefault(topic.get("robot") or "", {"ok": True, "topics": [], "problems": []})
        entry["topics"].append(
            {
                "name": topic.get("name", ""),
                "type": topic.get("type", ""),
                "publishers": sorted({p.get("node", "") for p in topic.get("publishers") or ()}),
                "subscribers": sorted({p.get("node", "") for p in topic.get("subscribers") or ()}),
                "rate": topic.get("rate"),
            }
        )
    for line in problems:
        robot = next((r for prefix, r in prefixes.items() if line.startswith(prefix)), "")
        entry = split.setdefault(robot, {"ok": True, "topics": [], "problems": []})
        entry["problems"].append(line)
        entry["ok"] = False
    return split
