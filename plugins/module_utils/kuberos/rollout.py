"""Rollouts: what a move from one applied state of a deployment to another changes, robot by robot, in waves.

Pure: rendered objects (plain dicts) in, a plan out. ``plan_rollout`` compares the objects the deployment's
current record renders with the objects the new state renders and groups the differences:

- ``prepare``: objects that are not one robot's (parameter ConfigMaps, Services, fleet objects), applied before
  the first wave (new ones are created; a changed parameter ConfigMap reaches every robot's mounted file);
- ``waves``: the module Deployments that change, grouped by robot: the canary robots first, then waves of
  ``wave_size`` robots in the fleet's order. A shared instance goes with the first of its robots to be reached;
- ``removals``: objects the new state no longer renders, removed once every wave passed.

Robots whose modules do not change are in no wave and are never touched. Robots that are offline (their computer's
node not Ready) are in no wave either: their changes are ``pending``, reported, and the next rollout run finishes
them (``behind_live`` finds a robot whose modules still run an older state than the record's). Nothing waits for a
robot that is away (docs/connectivity.md). ``gate_verdict`` is the health gate a wave must pass (pure over what
was observed); ``Downtime`` measures, per instance, the time no pod of it was Ready while it was replaced.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

from . import labels as node_labels
from . import pod_security
from .labels import COMPONENT, MODULE, ROBOTS_ANNOTATION, TIER_ANNOTATION, VERSION
from .manifests import ROBOT_DISCOVERY
from .naming import object_key

ROLLOUT_KEYS = ("apiVersion", "kind", "metadata", "spec", "data", "binaryData", "type")
FAILING_REASONS = ("CrashLoopBackOff", "ErrImagePull", "ImagePullBackOff", "CreateContainerConfigError", "RunContainerError")


# The rollout's numeric options (rosdeployment_rollout), each from its least to its most: a count, or seconds (a wave's
# gate, soak and lock wait, the pre-pulls in all). NaN and infinities are refused with the rest: a soak or gate of
# .inf would never end.
OPTION_BOUNDS = {
    "canary": (0, 10000),
    "wave_size": (1, 10000),
    "prestage_parallel": (1, 1000),
    "soak": (0, 3600),
    "gate_timeout": (0, 3600),
    "update_lock_wait": (0, 3600),
    "prestage_timeout": (0, 86400),
}
_ABOVE_ZERO = ("gate_timeout", "update_lock_wait", "prestage_timeout")


def option_problem(params: dict) -> str:
    """Why a rollout's numeric options cannot be used ('' when they can): the first option out of its bounds
    (``OPTION_BOUNDS``), named, with the bounds and the value given."""
    for name, (low, high) in OPTION_BOUNDS.items():
        value = params.get(name)
        counted = name in ("canary", "wave_size", "prestage_parallel")
        unit = "" if counted else " seconds"
        if counted:
            ok = isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and low <= value <= high
            ok = ok and not (name in _ABOVE_ZERO and value == 0)
        if not ok:
            least = "above 0" if name in _ABOVE_ZERO else f"{low} or more"
            shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
            return f"{name} must be {least} and at most {high}{unit}; got {shown}"
    return ""


@dataclass(frozen=True)
class Change:
    """One object a rollout creates, updates or removes."""

    action: str  # create | update | remove
    kind: str
    namespace: str
    name: str
    robot: str = ""  # the robot it belongs to ("" for fleet objects)
    module: str = ""
    summary: str = ""  # what changes, for people (image, version, ...)
    before: dict | None = field(default=None, compare=False, repr=False)
    after: dict | None = field(default=None, compare=False, repr=False)

    @property
    def instance(self) -> str:
        return self.name if self.kind == "Deployment" else ""


@dataclass
class Wave:
    number: int
    canary: bool
    robots: tuple[str, ...]
    changes: list[Change]


@dataclass
class RolloutPlan:
    prepare: list[Change] = field(default_factory=list)
    waves: list[Wave] = field(default_factory=list)
    removals: list[Change] = field(default_factory=list)
    untouched: tuple[str, ...] = ()  # robots with nothing to change
    pending: list[Change] = field(default_factory=list)  # changes of robots that are offline: the next run's
    pending_robots: tuple[str, ...] = ()

    @property
    def changed(self) -> bool:
        return bool(self.prepare or self.waves or self.removals)

    def instances(self) -> list[str]:
        """Every module instance the rollout replaces (the controller leaves them alone meanwhile)."""
        return sorted({c.name for w in self.waves for c in w.changes if c.kind == "Deployment"})

    def prestage(self) -> dict[str, dict]:
        """Robot computer -> ``{"images": [(image, pull policy), ...], "pull_secrets": [...]}``: what its waves' new
        module pods will pull, which a rollout pulls onto the robot before its first wave, so that no robot's downtime
        includes pulling an image over its link. Only onboard pods whose image changes (or that are new), and no image
        the kubelet never pulls (``imagePullPolicy: Never``)."""
        nodes: dict[str, dict[str, set]] = {}
        for change in (c for w in self.waves for c in w.changes):
            if change.kind != "Deployment" or change.after is None:
                continue
            if (change.after["metadata"].get("annotations") or {}).get(TIER_ANNOTATION) != "onboard":
                continue
            pod = change.after["spec"]["template"]["spec"]
            node = next(iter((pod.get("nodeSelector") or {}).values()), "")
            before = _images(change.before) if change.before else set()
            for container in [*pod.get("initContainers", []), *pod["containers"]]:
                policy = container.get("imagePullPolicy", "IfNotPresent")
                if node and policy != "Never" and container["image"] not in before:
                    entry = nodes.setdefault(node, {"images": set(), "pull_secrets": set()})
                    entry["images"].add((container["image"], policy))
                    entry["pull_secrets"].update(s["name"] for s in pod.get("imagePullSecrets") or [] if s.get("name"))
        return {
            node: {"images": sorted(entry["images"]), "pull_secrets": sorted(entry["pull_secrets"])}
            for node, entry in sorted(nodes.items())
        }

    def per_robot(self) -> dict[str, list[str]]:
        """For --check --diff: per robot, one line per module that changes."""
        out: dict[str, list[str]] = {}
        for wave in self.waves:
            for change in wave.changes:
                for robot in change.robot.split(","):
                    out.setdefault(robot, []).append(f"{change.module}: {change.action} ({change.summary})")
        for change in self.prepare + self.removals:
            out.setdefault("(fleet)", []).append(f"{change.kind}/{change.name}: {change.action} ({change.summary})")
        for change in self.pending:
            for robot in change.robot.split(","):
                out.setdefault(robot, []).append(f"{change.module}: pending, the robot is offline ({change.summary})")
        return {robot: sorted(lines) for robot, lines in sorted(out.items())}

    def to_dict(self) -> dict:
        def rows(changes):
            return [
                {"action": c.action, "kind": c.kind, "name": c.name, "robot": c.robot, "module": c.module, "summary": c.summary}
                for c in changes
            ]

        return {
            "prepare": rows(self.prepare),
            "waves": [
                {"number": w.number, "canary": w.canary, "robots": list(w.robots), "changes": rows(w.changes)} for w in self.waves
            ],
            "removals": rows(self.removals),
            "untouched": list(self.untouched),
            "pending": rows(self.pending),
            "pending_robots": list(self.pending_robots),
        }


def _comparable(obj: dict) -> dict:
    return {k: obj[k] for k in ROLLOUT_KEYS if k in obj}


def _container(obj: dict) -> dict:
    containers = ((obj.get("spec") or {}).get("template") or {}).get("spec", {}).get("containers") or [{}]
    return containers[0]


def _loosened_namespaces(before: list[dict], after: list[dict]) -> list[Change]:
    """Namespaces whose pods need a looser Pod Security level after the change (a module that now runs as root):
    relabelled before the first wave, or the new pods would be refused. A level that could be stricter is left as it
    is until the next deploy (other deployments of the fleet may need it)."""
    old = {o["metadata"]["name"]: o for o in before if o["kind"] == "Namespace"}
    changes = []
    for obj in after:
        if obj["kind"] != "Namespace" or obj["metadata"]["name"] not in old:
            continue
        was = (old[obj["metadata"]["name"]]["metadata"].get("labels") or {}).get(pod_security.ENFORCE, "restricted")
        now = (obj["metadata"].get("labels") or {}).get(pod_security.ENFORCE, "restricted")
        if pod_security.LEVELS.index(now) > pod_security.LEVELS.index(was):
            name = obj["metadata"]["name"]
            summary = f"enforces the {now} Pod Security level (was {was})"
            changes.append(Change("update", "Namespace", "", name, "", "", summary, old[name], obj))
    return changes


def summarize(before: dict | None, after: dict | None) -> str:
    """What differs between two renderings of one object, in a few words."""
    if before is None:
        return "new"
    if after is None:
        return "no longer rendered"
    if before["kind"] != "Deployment":
        return "content changed"
    parts = []
    old_c, new_c = _container(before), _container(after)
    old_v = (before["metadata"].get("labels") or {}).get(VERSION)
    new_v = (after["metadata"].get("labels") or {}).get(VERSION)
    if old_v != new_v:
        parts.append(f"version {old_v or '-'} -> {new_v or '-'}")
    if old_c.get("image") != new_c.get("image"):
        parts.append(f"image {old_c.get('image')} -> {new_c.get('image')}")
    old_node = before["spec"]["template"]["spec"].get("nodeSelector")
    new_node = after["spec"]["template"]["spec"].get("nodeSelector")
    if old_node != new_node:
        parts.append(f"node {'/'.join((old_node or {}).values())} -> {'/'.join((new_node or {}).values())}")
    for key, words in (("args", "launch"), ("env", "env"), ("resources", "resources"), ("volumeMounts", "parameters")):
        if old_c.get(key) != new_c.get(key):
            parts.append(f"{words} changed")
    if not parts and before["spec"].get("strategy") != after["spec"].get("strategy"):
        parts.append("upgrade strategy changed")
    return "; ".join(parts) or "metadata changed"


def _robots_of(obj: dict) -> tuple[str, ...]:
    labels = obj["metadata"].get("labels") or {}
    if labels.get(node_labels.ROBOT):
        return (labels[node_labels.ROBOT],)
    robots = (obj["metadata"].get("annotations") or {}).get(ROBOTS_ANNOTATION, "")
    return tuple(r for r in robots.split(",") if r)


def _images(deployment: dict) -> set[str]:
    pod = deployment["spec"]["template"]["spec"]
    return {c["image"] for c in [*pod.get("initContainers", []), *pod["containers"]]}


def plan_rollout(
    before: list[dict],
    after: list[dict],
    robots: list[str] | tuple[str, ...],
    canary: int = 1,
    wave_size: int = 10,
    canary_robots: tuple[str, ...] = (),
    skip=lambda obj: False,
    offline: tuple[str, ...] | set[str] = (),
) -> RolloutPlan:
    """Group the differences between two renderings of a deployment into prepare, waves and removals.

    ``robots`` is the fleet's robot order; ``canary_robots`` (when given) are the canary set, else the first
    ``canary`` robots with a change. Objects for which ``skip(obj)`` is true (the record) are left out. The changes
    of a module instance whose robots are all ``offline`` are ``pending`` instead of in a wave."""
    if canary < 0 or wave_size < 1:
        raise ValueError("canary must be 0 or more and wave_size 1 or more")
    old = {object_key(o): o for o in before if not skip(o) and o["kind"] != "Namespace"}
    new = {object_key(o): o for o in after if not skip(o) and o["kind"] != "Namespace"}
    plan = RolloutPlan()
    plan.prepare.extend(_loosened_namespaces(before, after))
    by_robot: dict[str, list[Change]] = {}
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if a is not None and b is not None and _comparable(a) == _comparable(b):
            continue
        obj = b if b is not None else a
        action = "create" if a is None else "remove" if b is None else "update"
        labels = obj["metadata"].get("labels") or {}
        module = labels.get(MODULE, labels.get(COMPONENT, ""))
        # a module instance, or a robot's own discovery server, goes with its robot(s)
        owners = (
            _robots_of(obj) if obj["kind"] == "Deployment" and labels.get(COMPONENT) in ("ros-module", ROBOT_DISCOVERY) else ()
        )
        change = Change(action, key[0], key[1], key[2], ",".join(owners), module, summarize(a, b), a, b)
        if action == "remove":
            plan.removals.append(change)
        elif not owners:
            plan.prepare.append(change)
        elif all(r in offline for r in owners):
            plan.pending.append(change)
        else:
            first = min(owners, key=lambda r: (robots.index(r) if r in robots else len(robots), r))
            by_robot.setdefault(first, []).append(change)
    order = [r for r in robots if r in by_robot] + sorted(r for r in by_robot if r not in robots)
    chosen = [r for r in canary_robots if r in by_robot] if canary_robots else order[:canary]
    rest = [r for r in order if r not in chosen]
    groups = ([(True, chosen)] if chosen else []) + [(False, rest[i : i + wave_size]) for i in range(0, len(rest), wave_size)]
    for number, (is_canary, members) in enumerate(groups, start=1):
        changes = [c for r in members for c in by_robot[r]]
        touched = tuple(sorted({r for c in changes for r in c.robot.split(",")}))
        plan.waves.append(Wave(number, is_canary, touched, changes))
    plan.pending_robots = tuple(sorted({r for c in plan.pending for r in c.robot.split(",")}))
    touched_all = {r for w in plan.waves for r in w.robots} | set(plan.pending_robots)
    plan.untouched = tuple(r for r in robots if r not in touched_all)
    return plan


def _containers(obj: dict) -> list[dict]:
    return ((obj.get("spec") or {}).get("template") or {}).get("spec", {}).get("containers") or []


def _signature(container: dict) -> tuple:
    """What a rendering sets of a container, as the API server gives it back: image, command, args, env (an entry
    from elsewhere by its name only; an empty value as the server leaves it out)."""
    env = tuple((e.get("name"), "<from>" if "valueFrom" in e else (e.get("value") or "")) for e in container.get("env") or [])
    return container.get("image"), tuple(container.get("command") or ()), tuple(container.get("args") or ()), env


def behind_live(rendered: list[dict], live: list[dict]) -> list[dict]:
    """``rendered`` (what the record says runs) with each module Deployment whose live containers differ from it (a
    robot a rollout left pending while it was offline or held its update lock: another image, version, command or
    environment) given the live containers and version, so that a plan against the new state includes it again.
    Other objects as they are."""
    running = {}
    for obj in live:
        meta = obj.get("metadata") or {}
        running[(meta.get("namespace", ""), meta.get("name", ""))] = obj
    out = []
    for obj in rendered:
        meta = obj["metadata"]
        now = running.get((meta.get("namespace", ""), meta["name"])) if obj["kind"] == "Deployment" else None
        if now is None:
            out.append(obj)
            continue
        version = (now["metadata"].get("labels") or {}).get(VERSION)
        live_containers = {c.get("name"): c for c in _containers(now)}
        same = version == (meta.get("labels") or {}).get(VERSION) and all(
            c.get("name") in live_containers and _signature(c) == _signature(live_containers[c.get("name")])
            for c in _containers(obj)
        )
        if same:
            out.append(obj)
            continue
        older = copy.deepcopy(obj)
        for container in _containers(older):
            running_container = live_containers.get(container.get("name"))
            if running_container is None:
                continue
            for key in ("image", "command", "args", "env"):
                if key in running_container:
                    container[key] = copy.deepcopy(running_container[key])
                else:
                    container.pop(key, None)
        labels = older["metadata"].setdefault("labels", {})
        if version is None:
            labels.pop(VERSION, None)
        else:
            labels[VERSION] = version
        out.append(older)
    return out


# -- the health gate ------------------------------------------------------------------------------
@dataclass(frozen=True)
class PodState:
    """One pod of an instance as observed: enough for the gate."""

    name: str
    node: str
    phase: str
    ready: bool
    restarts: int = 0
    waiting_reason: str = ""
    deleting: bool = False
    image: str = ""


def pod_failure(pod: PodState, baseline_restarts: int = 0) -> str | None:
    """Why a pod counts as failing, or None."""
    if pod.deleting:
        return None
    if pod.phase == "Failed":
        return f"pod {pod.name} failed"
    if pod.waiting_reason in FAILING_REASONS:
        return f"pod {pod.name} is in {pod.waiting_reason} ({pod.restarts} restarts)"
    if pod.restarts > baseline_restarts:
        return f"pod {pod.name} restarted ({pod.restarts} restarts)"
    return None


def instance_settled(pods: list[PodState], node: str, image: str) -> bool:
    """The instance runs exactly one pod, of the new image, Running and Ready on its placed node."""
    live = [p for p in pods if not p.deleting]
    return len(live) == 1 and live[0].node == node and live[0].phase == "Running" and live[0].ready and live[0].image == image


def gate_verdict(
    observed: dict[str, list[PodState]], wanted: dict[str, tuple[str, str]], old_pods: frozenset | set = frozenset()
) -> tuple[list[str], list[str]]:
    """(failures, pending) of a wave: ``wanted`` maps each instance to (node, image) of its new state; ``old_pods``
    names the pods that ran before the wave was applied (their past restarts are not the new state's failures)."""
    failures, pending = [], []
    for instance, (node, image) in sorted(wanted.items()):
        pods = observed.get(instance, [])
        new_pods = [p for p in pods if p.image == image and p.name not in old_pods]
        failing = [why for p in new_pods if (why := pod_failure(p)) is not None]
        if failing:
            failures.append(f"{instance}: {failing[0]}")
        elif not instance_settled(pods, node, image):
            pending.append(instance)
    return failures, pending


@dataclass
class Downtime:
    """Per instance, the seconds no pod of it was Ready while it was replaced (from polling)."""

    down_since: dict[str, float] = field(default_factory=dict)
    total: dict[str, float] = field(default_factory=dict)

    def observe(self, instance: str, any_ready: bool, now: float) -> None:
        self.total.setdefault(instance, 0.0)
        if any_ready:
            since = self.down_since.pop(instance, None)
            if since is not None:
                self.total[instance] += now - since
        else:
            self.down_since.setdefault(instance, now)

    def finish(self, now: float) -> dict[str, float]:
        for instance in list(self.down_since):
            self.observe(instance, True, now)
        return {k: round(v, 3) for k, v in sorted(self.total.items())}


@dataclass
class RevisionInfo:
    """One kept revision of a deployment, for listings."""

    number: int
    cause: str
    versions: dict[str, str]
    created: str = ""


def revision_table(revisions: list[RevisionInfo], current: int) -> str:
    lines = ["REVISION  CAUSE     MODULES"]
    for rev in sorted(revisions, key=lambda r: r.number):
        mark = "*" if rev.number == current else " "
        modules = ", ".join(f"{m} {v}" for m, v in sorted(rev.versions.items()))
        lines.append(f"{rev.number:>7}{mark}  {rev.cause:<8}  {modules}")
    return "\n".join(lines)
