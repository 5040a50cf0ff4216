"""What the controller decides, from what it observed: pure, so every rule is testable without a cluster.

Faults it reacts to, per module instance:

- its node is NotReady (Ready False or Unknown) or gone from the cluster, unless that node is a robot's computer:
  a robot that is offline (a dead zone, roaming, a lift) keeps its modules where they are and runs them on its own;
  nothing of it moves, restarts or runs twice (``Decision.offline``, docs/connectivity.md);
- its pod keeps failing there (restarts at or above a threshold, CrashLoopBackOff, or phase Failed);
- a measured round-trip time from one of its robots to its node is above the module's ``max_latency``.

A fault must last ``grace_s`` (measured from the node condition's lastTransitionTime when there is
one, else from when the controller first saw it) before anything moves: a blip does not move modules.
Moved instances never move back on their own (placements are sticky), a node a pod kept failing on
is avoided for ``avoid_s``, and an instance moved for a latency or pod fault waits ``cooldown_s``
before it may move again for such a fault, so nothing ping-pongs. Node loss is never delayed by the
cooldown. Re-placement uses ``replacement.replace_modules``: the same rules as deploy.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from .placement import Instance, Replacement
from .record import Record
from .replacement import replace_modules


@dataclass(frozen=True)
class Settings:
    grace_s: float = 5.0
    restart_threshold: int = 3
    cooldown_s: float = 30.0
    avoid_s: float = 600.0


@dataclass(frozen=True)
class NodeView:
    """A cluster node as the controller sees it, by its inventory name."""

    name: str
    ready: bool
    condition: str = ""  # e.g. "Ready=Unknown (NodeStatusUnknown)"
    since: float | None = None  # lastTransitionTime of the Ready condition, epoch seconds
    probe: str = ""  # the controller's own probe found its kubelet gone (kuberos_controller/liveness.py), before Kubernetes


@dataclass(frozen=True)
class PodView:
    name: str
    namespace: str
    instance: str
    node: str  # inventory name of the node it is bound to ("" while pending)
    phase: str
    ready: bool
    restarts: int = 0
    waiting_reason: str = ""
    deleting: bool = False


@dataclass
class ClusterView:
    nodes: dict[str, NodeView] = field(default_factory=dict)  # inventory node name -> view; absent = not in the cluster
    measured: dict[str, dict[str, float]] = field(default_factory=dict)  # robot -> node -> RTT ms
    pods: dict[str, list[PodView]] = field(default_factory=dict)  # instance name -> its pods


@dataclass
class Memory:
    """What the controller remembers between passes about one record (lost on restart, and that is safe)."""

    first_seen: dict[tuple, float] = field(default_factory=dict)
    avoid: dict[str, dict[str, tuple[str, float]]] = field(default_factory=dict)  # instance -> node -> (why, until)
    last_move: dict[str, float] = field(default_factory=dict)


@dataclass
class Decision:
    record: Record
    replacement: Replacement | None = None  # None: nothing moves
    waiting: list[str] = field(default_factory=list)  # faults inside their grace period, for the log
    offline: dict[str, str] = field(default_factory=dict)  # robot's node -> why it counts as offline; its instances stay
    wake_at: float | None = None  # when the earliest waiting fault becomes due


def node_fault(name: str, cluster: ClusterView) -> tuple[str, float | None] | None:
    view = cluster.nodes.get(name)
    if view is None:
        return f"node {name} is not in the cluster", None
    if view.probe:
        return f"node {name} is down ({view.probe})", view.since
    if not view.ready:
        return f"node {name} is NotReady ({view.condition or 'no Ready condition'})", view.since
    return None


def pod_fault(inst: Instance, cluster: ClusterView, settings: Settings) -> str | None:
    for pod in cluster.pods.get(inst.name, ()):
        if pod.deleting or pod.node != inst.node:
            continue
        if pod.phase == "Failed":
            return f"pod {pod.name} failed on {pod.node}"
        if pod.waiting_reason == "CrashLoopBackOff" or pod.restarts >= settings.restart_threshold:
            extra = f", {pod.waiting_reason}" if pod.waiting_reason else ""
            return f"pod {pod.name} keeps failing on {pod.node} ({pod.restarts} restarts{extra})"
    return None


def latency_fault(inst: Instance, record: Record, cluster: ClusterView) -> str | None:
    module = next((m for m in record.spec.modules if m.name == inst.module), None)
    if module is None or module.requirements.max_latency_ms is None:
        return None
    for robot in inst.robots:
        rtt = cluster.measured.get(robot, {}).get(inst.node)
        if rtt is not None and rtt > module.requirements.max_latency_ms:
            return f"measured RTT {rtt:g} ms from {robot} to {inst.node} > max_latency {module.requirements.max_latency_ms:g} ms"
    return None


def _due(memory: Memory, key: tuple, since: float | None, now: float, grace: float) -> tuple[bool, float]:
    first = memory.first_seen.setdefault(key, now)
    start = min(first, since) if since is not None and since <= now else first
    return now - start >= grace, start + grace


def decide(record: Record, cluster: ClusterView, memory: Memory, settings: Settings, now: float, allocated=None) -> Decision:
    """Which instances of one record move now, and where; or what waits for its grace period."""
    decision = Decision(record)
    seen: set[tuple] = set()
    unavailable: dict[str, str] = {}
    hold: set[str] = set()
    avoid: dict[str, dict[str, str]] = {}
    due_any = False
    wake: list[float] = []

    bad_nodes = {}
    robot_nodes = {name for name, node in record.inventory.nodes.items() if node.tier == "onboard"}
    nodes_used = {i.node for i in record.placement.instances} | {
        s.node for servers in record.placement.discovery.values() for s in servers
    }
    for name in sorted(set(record.inventory.nodes) | nodes_used):
        fault = node_fault(name, cluster)
        if fault is None:
            continue
        unavailable[name] = fault[0]  # never a target while it is bad
        key = ("node", name)
        seen.add(key)
        due, at = _due(memory, key, fault[1], now, settings.grace_s)
        bad_nodes[name] = due
        if not due:
            wake.append(at)
    for inst in record.placement.instances:
        if inst.cluster:
            continue  # runs in a third-party cluster, whose own scheduler keeps it running
        if inst.node in robot_nodes and inst.node in unavailable:
            hold.add(inst.name)  # an offline robot: its modules stay and run there, never twice
            decision.offline.setdefault(inst.node, unavailable[inst.node])
            continue
        if inst.node in bad_nodes:
            if bad_nodes[inst.node]:
                due_any = True
            else:
                hold.add(inst.name)
                decision.waiting.append(f"{inst.name}: {unavailable[inst.node]}")
            continue
        for kind, why in (("pod", pod_fault(inst, cluster, settings)), ("latency", latency_fault(inst, record, cluster))):
            if why is None:
                continue
            key = (kind, inst.name, inst.node)
            seen.add(key)
            due, at = _due(memory, key, None, now, settings.grace_s)
            cooling = now - memory.last_move.get(inst.name, -math.inf) < settings.cooldown_s
            if due and not cooling:
                due_any = True
                if kind == "pod":
                    memory.avoid.setdefault(inst.name, {})[inst.node] = (why, now + settings.avoid_s)
                else:
                    avoid.setdefault(inst.name, {})[inst.node] = why  # says what was measured
            else:
                hold.add(inst.name)
                decision.waiting.append(f"{inst.name}: {why}" + (" (cooling down after a move)" if due else ""))
                wake.append(max(at, memory.last_move.get(inst.name, -math.inf) + settings.cooldown_s))
            break
    for server in (s for servers in record.placement.discovery.values() for s in servers):
        if server.node in robot_nodes and server.node in unavailable:
            hold.add(server.name)
            decision.offline.setdefault(server.node, unavailable[server.node])
        elif server.node in bad_nodes:
            if bad_nodes[server.node]:
                due_any = True
            else:
                hold.add(server.name)

    for key in [k for k in memory.first_seen if k not in seen]:
        del memory.first_seen[key]  # the fault cleared: its grace starts again if it comes back
    for inst_name, nodes in list(memory.avoid.items()):
        live = {n: why for n, (why, until) in nodes.items() if until > now}
        if live:
            avoid[inst_name] = {**live, **avoid.get(inst_name, {})}
        else:
            memory.avoid.pop(inst_name, None)

    decision.wake_at = min(wake) if wake else None
    if not due_any:
        return decision
    inventory = record.inventory.with_measured_latency(cluster.measured) if cluster.measured else record.inventory
    replacement = replace_modules(
        record.deployments, inventory, record.placement, allocated, unavailable=unavailable, avoid=avoid, hold=hold
    )
    for move in replacement.moves:
        memory.last_move[move.instance] = now
    decision.replacement = replacement
    return decision


# Phases shown per robot and module.
RUNNING, PENDING, STRANDED, MISSING, MOVING, REMOTE = "Running", "Pending", "Stranded", "Missing", "Moving", "Remote"
OFFLINE = "Offline"  # on a robot that is offline: it runs there as far as anyone knows, out of the cluster's sight


def instance_phase(inst: Instance, pods: list[PodView], stranded: bool, offline: bool = False) -> tuple[str, str]:
    """(phase, pod name) of one instance from its pods (``offline``: its node is a robot's, offline)."""
    if inst.cluster:
        return REMOTE, ""  # its pods are in the third-party cluster
    live = [p for p in pods if not p.deleting]
    on_node = [p for p in live if p.node == inst.node]
    if offline:
        return OFFLINE, on_node[0].name if on_node else ""
    if stranded:
        return STRANDED, on_node[0].name if on_node else ""
    if any(p.phase == "Running" and p.ready for p in on_node):
        return RUNNING, next(p.name for p in on_node if p.phase == "Running" and p.ready)
    if any(p.node and p.node != inst.node for p in live) or any(p.deleting for p in pods):
        return MOVING, ""
    if live:
        return PENDING, live[0].name
    return MISSING, ""


def offline_note(node: str, tier: str, cluster: ClusterView) -> str:
    """Why a robot's computer counts as offline ("" when it is online, or the node is not a robot's)."""
    fault = node_fault(node, cluster) if tier == "onboard" else None
    if fault is None:
        return ""
    since = fault[1]
    when = f" since {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime(since))}" if since is not None else ""
    return f"robot offline{when}: {fault[0]}"


def status_rows(record: Record, cluster: ClusterView, stranded: dict[str, str], history: dict[str, dict]) -> list[dict]:
    """One row per (robot, module) plus one per discovery server: node, phase, pod and the last move."""
    rows = []
    versions = {m.name: (m.version or m.image.rsplit("/", 1)[-1]) for m in record.spec.modules}
    for inst in record.placement.instances:
        offline = offline_note(inst.node, inst.tier, cluster)
        phase, pod = instance_phase(inst, cluster.pods.get(inst.name, []), inst.name in stranded, bool(offline))
        last = history.get(inst.name, {})
        for robot in inst.robots:
            rows.append(
                {
                    "robot": robot,
                    "module": inst.module,
                    "version": versions.get(inst.module, ""),
                    "instance": inst.name,
                    "node": inst.node,
                    "tier": inst.tier,
                    "phase": phase,
                    "pod": pod,
                    "last_move": last,
                    "note": offline or stranded.get(inst.name, ""),
                }
            )
    for servers in record.placement.discovery.values():
        for server in servers:
            offline = offline_note(server.node, server.tier, cluster)
            phase, pod = instance_phase(
                Instance(server.name, "", server.fleet, server.namespace, "", server.node, server.tier, (), "", 0, 0, 0, 0),
                cluster.pods.get(server.name, []),
                server.name in stranded,
                bool(offline),
            )
            rows.append(
                {
                    "robot": "-",
                    "module": server.name,
                    "version": "",
                    "instance": server.name,
                    "node": server.node,
                    "tier": server.tier,
                    "phase": phase,
                    "pod": pod,
                    "last_move": history.get(server.name, {}),
                    "note": offline or stranded.get(server.name, ""),
                }
            )
    rows.sort(key=lambda r: (r["robot"] == "-", r["robot"], r["module"]))
    return rows
