"""Scaling shared modules (pure): how many instances a load signal asks for, stabilised so that nothing flaps, and
which robots move when instances are added or removed.

The controller (``kuberos_controller.controller``) measures the signal and acts; everything it decides is here:

- ``recommend``: the instances the signal asks for, as the Kubernetes HPA computes it: ``ceil(current * value /
  target)``, unchanged within a tolerance of 10 %;
- ``Windows``: a recommendation counts only as much as the window allows: scale up to the lowest recommendation of
  the last ``scaleUpWindow``, down to the highest of the last ``scaleDownWindow``, and never down before the window
  has been watched whole (after a restart, a takeover or a step, the window starts again; the recommendations of
  the window stay, so a step up is followed by another only when the window's lowest asks for it);
- ``bounds``: ``minInstances``..``maxInstances``, never fewer than the robots need at ``robotsPerInstance`` and
  never more instances than robots;
- ``grow`` / ``shrink``: sticky re-assignment: an instance added takes robots from the instances that serve the
  most, one at a time; an instance removed gives its robots to those that serve the fewest; every other robot
  stays where it is;
- ``ScaleState`` and ``serving``: a change is handed over in steps. A robot moved to a new instance is still
  served by its old one until the new one is Ready (``handover``); an instance removed serves nobody from the
  moment its robots moved and keeps running for ``drainTime`` to finish what it had accepted (``leaving``), then
  it stops. ``serving`` is what each instance serves now: the assignment the instances read.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from .spec import ScalingPolicy

TOLERANCE = 0.1
# One sample line of the Prometheus text format: a name, its labels (values quoted, with escapes), a value and an
# optional timestamp.
_SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)\s*(\{(?:[^"}]|"(?:[^"\\]|\\.)*")*\})?\s+(\S+)(?:\s+-?[0-9]+)?\s*$')


def gauge_value(text: str, metric: str) -> float | None:
    """The sum of a gauge's samples (all label sets) in a Prometheus text exposition; None when it is absent or
    the text is not the format (a module's own load gauge, read by the controller and the simulator's scaler)."""
    total, seen = 0.0, False
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        sample = _SAMPLE.match(line)
        if sample is None:
            return None
        if sample.group(1) == metric:
            try:
                total += float(sample.group(3))
            except ValueError:
                return None
            seen = True
    return total if seen else None


def bounds(policy: ScalingPolicy, robots: int, per_instance: int) -> tuple[int, int]:
    """(fewest, most) instances for ``robots`` robots."""
    if robots <= 0:
        return 0, 0
    low = max(policy.min_instances, math.ceil(robots / max(per_instance, 1)))
    high = min(policy.max_instances, robots)
    return min(low, robots), max(min(low, robots), high)


def recommend(current: int, values: list[float], target: float, tolerance: float = TOLERANCE) -> int | None:
    """Instances the signal asks for: the mean of ``values`` (one per instance that reported) against ``target``.
    None without a value; ``current`` within the tolerance."""
    if not values or current <= 0 or target <= 0:
        return None
    ratio = (sum(values) / len(values)) / target
    if abs(ratio - 1.0) <= tolerance:
        return current
    return max(1, math.ceil(current * ratio - 1e-9))


@dataclass
class Windows:
    """The recommendations of one module over time (kept in memory: a new leader starts watching anew)."""

    since: float | None = None  # when watching started (or restarted after a change)
    history: list[tuple[float, int]] = field(default_factory=list)

    def restart(self, now: float) -> None:
        """After a step: the scale-down window starts again (it must be watched whole); the recommendations stay, so
        the scale-up window still damps the next step up."""
        self.since = now

    def desired(self, policy: ScalingPolicy, now: float, current: int, recommendation: int) -> tuple[int, str]:
        """The instance count to move to now, and why it is held back when it is."""
        if self.since is None:
            self.since = now
        self.history.append((now, recommendation))
        horizon = max(policy.scale_up_window_s, policy.scale_down_window_s)
        self.history = [(t, r) for t, r in self.history if t >= now - horizon - 1e-9]
        if recommendation > current:
            recent = [r for t, r in self.history if t >= now - policy.scale_up_window_s - 1e-9]
            return max(current, min(recent)), ""
        if recommendation < current:
            watched = now - self.since
            if watched < policy.scale_down_window_s:
                return current, f"scale-down window: {watched:.0f} of {policy.scale_down_window_s:g} s watched"
            recent = [r for t, r in self.history if t >= now - policy.scale_down_window_s - 1e-9]
            highest = max(recent)
            if highest >= current:
                return current, f"a recommendation of {highest} within the last {policy.scale_down_window_s:g} s"
            return highest, ""
        return current, ""


def _largest(assignment: dict[str, list[str]], exclude=()) -> str | None:
    """The instance serving the most robots (ties: the later name, the newest), not in ``exclude``."""
    names = [n for n in assignment if n not in exclude and assignment[n]]
    return max(names, key=lambda n: (len(assignment[n]), n)) if names else None


def grow(assignment: dict[str, tuple[str, ...]], new: list[str], fits=lambda robot, instance: True):
    """Add the instances ``new``: each takes robots from the instances serving the most until the load is even.

    Returns ``(assignment, moved)``: the new robots of every instance, and robot -> (from, to) for each one moved.
    ``fits(robot, instance)`` says whether a robot may be served by an instance (its max_latency)."""
    result = {name: list(robots) for name, robots in assignment.items()}
    moved: dict[str, tuple[str, str]] = {}
    for name in new:
        result[name] = []
    total = sum(len(r) for r in result.values())
    share = total // len(result) if result else 0
    for name in new:
        while len(result[name]) < share:
            donors = sorted((n for n in result if n not in new and len(result[n]) > share), key=lambda n: (-len(result[n]), n))
            robot = next((r for d in donors for r in reversed(result[d]) if fits(r, name)), None)
            if robot is None:
                break
            donor = next(d for d in donors if robot in result[d])
            result[donor].remove(robot)
            result[name].append(robot)
            moved[robot] = (donor, name)
    return {n: tuple(r) for n, r in result.items()}, moved


def leaving_instances(assignment: dict[str, tuple[str, ...]], count: int, rank=None) -> list[str]:
    """The ``count`` instances to remove: those on the least preferred tier first (``rank``: instance -> the index of
    its tier in the module's preference; a peak's cloud instances leave before the edge ones, so that the VMs
    provisioned for it can be released), then those serving the fewest robots, the newest first among equals."""
    rank = rank or {}
    order = sorted(assignment, key=lambda n: (-rank.get(n, 0), len(assignment[n]), [-ord(c) for c in n]))
    return order[:count]


def shrink(assignment: dict[str, tuple[str, ...]], leaving: list[str], per_instance: int, fits=lambda r, i: True):
    """Remove the instances ``leaving``: their robots go to the instances serving the fewest (with room, that fit).

    Returns ``(assignment, moved)`` as ``grow`` does, or None when some robot has nowhere to go."""
    result = {name: list(robots) for name, robots in assignment.items()}
    moved: dict[str, tuple[str, str]] = {}
    staying = [n for n in result if n not in leaving]
    if not staying:
        return None
    for name in leaving:
        for robot in list(result[name]):
            options = [n for n in staying if len(result[n]) < per_instance and fits(robot, n)]
            if not options:
                return None
            target = min(options, key=lambda n: (len(result[n]), n))
            result[name].remove(robot)
            result[target].append(robot)
            moved[robot] = (name, target)
    return {n: tuple(r) for n, r in result.items()}, moved


@dataclass
class ScaleState:
    """A change in progress for one module, kept in the deployment record (it survives a takeover)."""

    handover: dict[str, str] = field(default_factory=dict)  # robot -> the instance that serves it until its new one is Ready
    leaving: dict[str, float] = field(default_factory=dict)  # instance -> when it stops (epoch seconds)

    @property
    def busy(self) -> bool:
        return bool(self.handover or self.leaving)

    def to_dict(self) -> dict:
        return {"handover": dict(sorted(self.handover.items())), "leaving": dict(sorted(self.leaving.items()))}

    @classmethod
    def from_dict(cls, data) -> ScaleState:
        data = data if isinstance(data, dict) else {}
        handover = data.get("handover") if isinstance(data.get("handover"), dict) else {}
        leaving = data.get("leaving") if isinstance(data.get("leaving"), dict) else {}
        return cls(
            {str(k): str(v) for k, v in handover.items()},
            {str(k): float(v) for k, v in leaving.items() if isinstance(v, (int, float))},
        )


def serving(assignment: dict[str, tuple[str, ...]], state: ScaleState) -> dict[str, tuple[str, ...]]:
    """What every instance serves now: its placed robots, except those still handed over from another instance."""
    result: dict[str, list[str]] = {name: [] for name in assignment}
    for name, robots in assignment.items():
        for robot in robots:
            holder = state.handover.get(robot)
            result[holder if holder in result else name].append(robot)
    return {n: tuple(sorted(r)) for n, r in result.items()}


def settle(
    state: ScaleState, assignment: dict[str, tuple[str, ...]], ready: set[str], now: float
) -> tuple[ScaleState, list[str]]:
    """Advance a change: hand robots to new instances that are Ready, and stop leaving instances once drained.

    Returns the new state and the instances to stop now."""
    placed = {robot: name for name, robots in assignment.items() for robot in robots}
    handover = {
        robot: holder
        for robot, holder in state.handover.items()
        if robot in placed and holder in assignment and placed[robot] != holder and placed[robot] not in ready
    }
    stop = sorted(
        name
        for name, until in state.leaving.items()
        if name in assignment and not assignment[name] and now >= until and name not in handover.values()
    )
    leaving = {n: t for n, t in state.leaving.items() if n in assignment and n not in stop}
    return ScaleState(handover, leaving), stop


@dataclass
class Step:
    """What one pass does to one scaled module."""

    instances: list  # the module's instances after the step (Instance), for the placement
    state: ScaleState
    start: list[str] = field(default_factory=list)  # new instances: their Deployments to create
    stop: list[str] = field(default_factory=list)  # drained instances: their Deployments to delete
    events: list[tuple[str, str, str, bool]] = field(default_factory=list)  # (object, reason, message, warning)
    summary: dict = field(default_factory=dict)  # for the status: instances, desired, signal, held
    wake_at: float | None = None
    decided: bool = False  # False: held before deciding (a handover, a drain, an instance not Ready, no signal)

    @property
    def changed(self) -> bool:
        return bool(self.start or self.stop or self.events)


def lacking(result: Step, previous: str | None) -> str | None:
    """Why the module still lacks a node after this step (the fleet's demand for the cloud), or None: the step's own
    ``ModuleScaleBlocked`` message; else, while a step is held before it decides (the instances it did place being
    handed robots or not Ready yet), the previous step's. A shortfall stands until a step decides without it, so
    that a VM provisioned for it is not released as idle while the step waits."""
    blocked = next((message for _name, reason, message, _warning in result.events if reason == "ModuleScaleBlocked"), None)
    if blocked is not None:
        return blocked
    return None if result.decided else previous


def within_latency(module, inventory):
    """``fits(robot, node)`` for ``step``: may the robot be served from that node (the module's max_latency)."""
    limit = module.requirements.max_latency_ms

    def fits(robot: str, node: str) -> bool:
        return limit is None or inventory.latency_ms(robot, node) <= limit

    return fits


def _names(deployment: str, module: str, used: set[str], count: int) -> list[str]:
    from .naming import shared_instance_name

    names, index = [], 0
    while len(names) < count:
        name = shared_instance_name(deployment, module, index)
        if name not in used:
            names.append(name)
        index += 1
    return names


def step(dep, module, instances: list, state: ScaleState, ready: set[str], values: dict[str, float], windows: Windows,
         now: float, place, fits) -> Step:  # fmt: skip
    """One pass for one scaled module.

    ``instances``: its instances in the placement; ``ready``: those with a Ready pod on their node; ``values``: the
    signal per instance that reported; ``place(robots)`` -> ``(node, tier, latency, reason)`` or ``(None, None,
    None, accounts)`` (the scheduler's ``choose``); ``fits(robot, node)``: may the robot be served from that node."""
    from dataclasses import replace

    policy = module.scaling
    by_name = {i.name: i for i in instances}
    assignment = {i.name: i.robots for i in instances}
    state, stop = settle(state, assignment, ready, now)
    result = Step([i for i in instances if i.name not in stop], state, stop=stop)
    for name in stop:
        result.events.append((name, "ModuleInstanceStopped", f"{module.name}: {name} stopped, its robots drained", False))
    active = [i.name for i in result.instances if i.name not in state.leaving]
    robots = sorted(r for i in result.instances for r in i.robots)
    low, high = bounds(policy, len(robots), module.robots_per_instance)
    reported = [values[n] for n in active if n in values]
    mean = sum(reported) / len(reported) if reported else None
    current = len(active)
    summary = {
        "module": module.name,
        "instances": current,
        "min": low,
        "max": high,
        "metric": policy.metric,
        "target": policy.target,
        "value": None if mean is None else round(mean, 4),
        "reported": len(reported),
        "desired": current,
        "held": "",
    }
    result.summary = summary
    if state.leaving:
        result.wake_at = min(state.leaving.values())
    if state.busy:
        summary["held"] = "handing robots over" if state.handover else "draining " + ", ".join(sorted(state.leaving))
        return result
    if any(n not in ready for n in active):
        summary["held"] = "waiting for every instance to be Ready"
        return result
    result.decided = True  # from here on the step decides (to hold by its windows, to change, or that it cannot)
    recommendation = recommend(current, reported, policy.target)
    if current < low or current > high:
        desired, held = min(max(current, low), high), ""
        cause = f"{current} is outside {low}..{high} instances"
    elif recommendation is None:
        summary["held"] = "no signal from the instances"
        result.decided = False
        return result
    else:
        desired, held = windows.desired(policy, now, current, min(max(recommendation, low), high))
        cause = f"{policy.metric} {mean:.3g} per instance, target {policy.target:g}"
    summary["desired"], summary["held"] = desired, held
    if desired == current:
        return result
    windows.restart(now)
    if desired > current:
        new = _names(dep.name, module.name, set(by_name), desired - current)
        grown, moved = grow({n: by_name[n].robots for n in active}, new)
        placed = {}
        for name in new:
            node, tier, latency, reason = place(grown[name])
            if node is None:
                why = "; ".join(reason[:6])
                summary["held"] = f"no node for another instance: {why}"
                result.events.append((module.name, "ModuleScaleBlocked", f"{module.name}: {cause}; no node: {why}", True))
                if placed:
                    break  # the instances that found a node are started
                return result
            placed[name] = (node, tier, latency, reason)
        new = list(placed)

        def may_serve(robot, name):
            return name not in placed or fits(robot, placed[name][0].name)

        grown, moved = grow({n: by_name[n].robots for n in active}, new, may_serve)
        template = by_name[active[0]]
        for name in new:
            node, tier, latency, reason = placed[name]
            result.instances.append(
                replace(
                    template,
                    name=name,
                    node=node.name,
                    tier=tier,
                    robots=grown[name],
                    latency_ms=latency,
                    reason=f"{reason}; added by scaling",
                )
            )
        result.instances = [replace(i, robots=grown.get(i.name, i.robots)) for i in result.instances]
        state.handover.update({robot: old for robot, (old, _new) in moved.items()})
        result.start = new
        who = "; ".join(f"{', '.join(sorted(r for r, (_o, n) in moved.items() if n == name))} to {name}" for name in new)
        message = f"{module.name}: {current} -> {current + len(new)} instances ({cause}); robots move: {who}"
        result.events.append((new[0], "ModuleScaledUp", message, False))
        return result
    tiers = list(module.tiers)
    rank = {n: tiers.index(by_name[n].tier) if by_name[n].tier in tiers else len(tiers) for n in active}
    leaving = leaving_instances({n: by_name[n].robots for n in active}, current - desired, rank)
    node_of = {i.name: i.node for i in result.instances}
    shrunk = shrink({n: by_name[n].robots for n in active}, leaving, module.robots_per_instance,
                    lambda r, n: fits(r, node_of[n]))  # fmt: skip
    if shrunk is None:
        summary["held"] = "the robots of an instance to remove have nowhere else to go (robotsPerInstance, max_latency)"
        return result
    assigned, moved = shrunk
    result.instances = [replace(i, robots=assigned.get(i.name, i.robots)) for i in result.instances]
    for name in leaving:
        state.leaving[name] = now + policy.drain_s
    result.wake_at = now + policy.drain_s
    who = "; ".join(f"{r} to {n}" for r, (_o, n) in sorted(moved.items()))
    message = (
        f"{module.name}: {current} -> {desired} instances ({cause}); {', '.join(leaving)} drains for "
        f"{policy.drain_s:g} s; robots move: {who or 'none'}"
    )
    result.events.append((leaving[0], "ModuleScaledDown", message, False))
    return result
