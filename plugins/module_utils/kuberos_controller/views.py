"""What the dashboard shows and ``/metrics`` counts, built from the controller's watch cache (plain data, no I/O).

``build_view`` turns one snapshot of the watched objects (nodes, KubeROS pods, deployment records, the status
ConfigMaps the leader writes, the fleets' software catalogs and the controller's Events) into a ``View``:

- ``resources``: one row per node (tier, fleet, robot, architecture, devices, Ready, allocatable and what the
  KubeROS pods on it request, measured round-trip times);
- ``modules``: one row per robot and module (node, tier, phase, live version, the placement's reason, the
  last move and why, the measured RTT against the module's ``max_latency``);
- ``fleets``: robots, deployments, discovery and bridge servers per fleet;
- ``software``: the catalog's versions, which robots run which version, rollouts in progress;
- ``events``: a timeline of moves, strandings, rollouts and node failures, newest first.

Every replica builds the same view from the cluster (the leader's own memory is not needed): phases come
from the pods, last moves and strandings from the status ConfigMaps.
"""

from __future__ import annotations

import datetime
import json
import time
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import INSTANCE
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    NodeView,
    PodView,
    instance_phase,
    offline_note,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import Record, catalog_of

RTT_ANNOTATION = "kuberos.io/rtt-ms"
RESOURCES = ("cpu", "memory", "gpu", "pods")
MAX_EVENTS = 500


@dataclass
class View:
    """One consistent picture of the platform; replaced whole, never changed in place."""

    generation: int = 0
    built_at: float = 0.0
    leader: str = ""
    summary: dict = field(default_factory=dict)
    resources: list[dict] = field(default_factory=list)
    modules: list[dict] = field(default_factory=list)
    fleets: list[dict] = field(default_factory=list)
    software: dict = field(default_factory=dict)
    events: list[dict] = field(default_factory=list)
    placements: dict[str, Placement] = field(default_factory=dict)  # "namespace/deployment" -> its placement
    max_latency: list[dict] = field(default_factory=list)  # per deployment and module that has one
    graphs: dict[str, dict] = field(default_factory=dict)  # "namespace/deployment" -> {robot: its last graph check}


def _ready(node: dict) -> tuple[bool, str, str]:
    """(Ready, condition text, lastTransitionTime) of a node."""
    ready = next((c for c in node.get("status", {}).get("conditions") or [] if c.get("type") == "Ready"), None)
    if not ready:
        return False, "no Ready condition", ""
    ok = ready.get("status") == "True"
    return ok, "" if ok else f"Ready={ready.get('status')} ({ready.get('reason', '')})", ready.get("lastTransitionTime", "")


def _quantity(kind: str, value) -> float:
    try:
        if kind == "cpu":
            return quantities.parse_cpu(str(value)) / 1000
        if kind == "memory":
            return float(quantities.parse_memory(str(value)))
        return float(int(str(value)))
    except (KuberosError, ValueError, TypeError):
        return 0.0


def pod_requests(pod: dict) -> dict[str, float]:
    """CPU (cores), memory (bytes) and GPUs a pod requests, and 1 pod."""
    used = {"cpu": 0.0, "memory": 0.0, "gpu": 0.0, "pods": 1.0}
    for container in pod.get("spec", {}).get("containers") or []:
        requests = (container.get("resources") or {}).get("requests") or {}
        used["cpu"] += _quantity("cpu", requests.get("cpu", "0"))
        used["memory"] += _quantity("memory", requests.get("memory", "0"))
        used["gpu"] += _quantity("gpu", requests.get("nvidia.com/gpu", "0"))
    return used


def _measured(node: dict) -> dict[str, float]:
    raw = (node["metadata"].get("annotations") or {}).get(RTT_ANNOTATION)
    if not raw:
        return {}
    try:
        return {str(k): float(v) for k, v in json.loads(raw).items()}
    except (ValueError, TypeError, AttributeError):
        return {}


def _image_version(image: str) -> str:
    """The tag (or digest) of an image reference: what a pod really runs."""
    last = image.rsplit("/", 1)[-1]
    if "@" in last:
        return last.split("@", 1)[1][:19]
    return last.split(":", 1)[1] if ":" in last else "latest"


@dataclass
class Snapshot:
    """The watched objects the view is built from (plain dicts as the API serves them)."""

    nodes: list[dict]
    pods: list[dict]
    records: list[tuple[dict, Record | None, str]]  # (ConfigMap, parsed record or None, why it cannot be read)
    statuses: list[dict] = field(default_factory=list)
    catalogs: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    reservations: list[dict] = field(default_factory=list)  # the robot pool's ConfigMaps
    graphs: list[dict] = field(default_factory=list)  # each deployment's last graph check, per robot
    node_log: list[dict] = field(default_factory=list)  # node Ready transitions this process saw
    leader: str = ""
    controller: dict = field(default_factory=dict)  # passes, moves, identity, leading


def _node_rows(snapshot: Snapshot, names: dict[str, str]) -> tuple[list[dict], dict[str, dict]]:
    allocated: dict[str, dict[str, float]] = {}
    for pod in snapshot.pods:
        node = pod.get("spec", {}).get("nodeName")
        if not node or pod["metadata"].get("deletionTimestamp") or pod.get("status", {}).get("phase") in ("Succeeded", "Failed"):
            continue
        entry = allocated.setdefault(names.get(node, node), dict.fromkeys(RESOURCES, 0.0))
        for key, value in pod_requests(pod).items():
            entry[key] += value
    rows = []
    for node in snapshot.nodes:
        meta = node["metadata"]
        node_label = meta.get("labels") or {}
        name = names[meta["name"]]
        ready, condition, since = _ready(node)
        status = node.get("status", {})
        capacity = status.get("allocatable") or status.get("capacity") or {}
        rows.append(
            {
                "name": name,
                "node": meta["name"],
                "tier": node_labels.TIER_OF_ROLE.get(node_label.get(node_labels.ROLE, ""), node_label.get(node_labels.ROLE, "")),
                "fleet": node_label.get(node_labels.FLEET, ""),
                "robot": node_label.get(node_labels.ROBOT, ""),
                "arch": node_label.get(node_labels.ARCH) or node_label.get("kubernetes.io/arch", ""),
                "group": node_label.get(node_labels.RESOURCE_GROUP, ""),
                "devices": sorted(
                    k[len(node_labels.DEVICE_PREFIX) :] for k in node_label if k.startswith(node_labels.DEVICE_PREFIX)
                ),
                "ready": ready,
                "condition": condition,
                "since": since,
                "allocatable": {
                    "cpu": _quantity("cpu", capacity.get("cpu", "0")),
                    "memory": _quantity("memory", capacity.get("memory", "0")),
                    "gpu": _quantity("gpu", capacity.get("nvidia.com/gpu", "0")),
                    "pods": _quantity("pods", capacity.get("pods", "0")),
                },
                "allocated": allocated.get(name, dict.fromkeys(RESOURCES, 0.0)),
                "rtt_ms": _measured(node),
            }
        )
    rows.sort(key=lambda r: ({"onboard": 0, "edge": 1, "cloud": 2}.get(r["tier"], 3), r["fleet"], r["name"]))
    return rows, {r["name"]: r for r in rows}


def _cluster_view(snapshot: Snapshot, names: dict[str, str], nodes: dict[str, dict]) -> tuple[ClusterView, dict, dict]:
    """The reconciler's view of the cluster, each pod's image, and per instance when its newest pod that runs and is
    Ready was created (a rollout has replaced an instance once such a pod is newer than the rollout)."""
    view = ClusterView()
    started: dict[str, str] = {}
    for name, row in nodes.items():
        view.nodes[name] = NodeView(name, row["ready"], row["condition"], None)
        if row["robot"] and row["rtt_ms"]:
            view.measured[row["robot"]] = row["rtt_ms"]
    images: dict[str, str] = {}  # "namespace/pod" -> first container's image
    for pod in snapshot.pods:
        found = pod_view(pod, names)
        if found is None:
            continue
        meta = pod["metadata"]
        key = f"{found.namespace}/{found.instance}"
        view.pods.setdefault(key, []).append(found)
        containers = pod.get("spec", {}).get("containers") or [{}]
        images[f"{found.namespace}/{found.name}"] = containers[0].get("image", "")
        if found.ready and found.phase == "Running" and not found.deleting:
            started[key] = max(started.get(key, ""), meta.get("creationTimestamp") or "")
    return view, images, started


# The timeline's kinds of the controller's Events (anything else: "event").
EVENT_KINDS = {
    "ModuleMoved": "move",
    "ModuleStranded": "stranded",
    "ModuleScaledUp": "scale",
    "ModuleScaledDown": "scale",
    "ModuleInstanceStopped": "scale",
    "ModuleScaleBlocked": "scale",
}


def pod_view(pod: dict, names: dict[str, str]) -> PodView | None:
    """What the reconciler needs of a KubeROS pod (None for a pod of no module instance); ``names`` maps Kubernetes node
    names to inventory names."""
    meta = pod["metadata"]
    instance = (meta.get("labels") or {}).get(INSTANCE)
    if not instance:
        return None
    status = pod.get("status", {})
    statuses = status.get("containerStatuses") or []
    node = pod.get("spec", {}).get("nodeName") or ""
    return PodView(
        meta["name"],
        meta.get("namespace", ""),
        instance,
        names.get(node, node),
        status.get("phase", ""),
        any(c.get("type") == "Ready" and c.get("status") == "True" for c in status.get("conditions") or []),
        sum(int(s.get("restartCount", 0)) for s in statuses),
        next((s["state"]["waiting"].get("reason", "") for s in statuses if "waiting" in (s.get("state") or {})), ""),
        bool(meta.get("deletionTimestamp")),
    )


def _status_of(snapshot: Snapshot) -> dict[tuple[str, str], dict]:
    """(namespace, deployment) -> {"moves": instance -> last move, "notes": instance -> why it is stranded}."""
    found = {}
    for configmap in snapshot.statuses:
        data = configmap.get("data") or {}
        try:
            status = json.loads(data.get("status.json") or "{}")
            moves = json.loads(data.get("moves.json") or "{}")
        except ValueError:
            continue
        if not isinstance(status, dict) or not isinstance(moves, dict):
            continue
        notes = {r.get("instance"): r.get("note") for r in status.get("rows") or [] if isinstance(r, dict) and r.get("note")}
        found[(configmap["metadata"].get("namespace", ""), str(status.get("deployment", "")))] = {"moves": moves, "notes": notes}
    return found


def _module_rows(record: Record, view: ClusterView, images: dict[str, str], status: dict, modules: list[dict]) -> list[dict]:
    spec = {m.name: m for m in record.spec.modules}
    prefix = record.namespace + "/"
    stranded = status.get("notes", {})
    for inst in record.placement.instances:
        pods = view.pods.get(prefix + inst.name, [])
        offline = offline_note(inst.node, inst.tier, view)
        phase, pod = instance_phase(inst, pods, inst.name in stranded, bool(offline))
        module = spec.get(inst.module)
        image = images.get(prefix + pod, "") if pod else ""
        planned = (module.version or _image_version(module.image)) if module else ""
        limit = module.requirements.max_latency_ms if module else None
        for robot in inst.robots:
            rtt = view.measured.get(robot, {}).get(inst.node)
            modules.append(
                {
                    "namespace": record.namespace,
                    "deployment": record.deployment,
                    "fleet": inst.fleet,
                    "robot": robot,
                    "module": inst.module,
                    "instance": inst.name,
                    "node": inst.node,
                    "tier": inst.tier,
                    "phase": phase,
                    "pod": pod,
                    "version": _image_version(image) if image else planned,
                    "planned": planned,
                    "shared": inst.shared,
                    "reason": inst.reason,
                    "last_move": status.get("moves", {}).get(inst.name) or {},
                    "note": offline or stranded.get(inst.name, ""),
                    "rtt_ms": rtt,
                    "max_latency_ms": limit,
                    "over_latency": rtt is not None and limit is not None and rtt > limit,
                }
            )
    return modules


def _graphs(snapshot: Snapshot) -> dict[str, dict]:
    """Each deployment's last live graph check per robot (kuberos_ros.graph_check writes them), by
    "namespace/deployment"; a ConfigMap that cannot be read shows nothing."""
    found = {}
    for configmap in snapshot.graphs:
        meta = configmap.get("metadata") or {}
        try:
            data = json.loads((configmap.get("data") or {}).get("graph.json", ""))
        except ValueError:
            continue
        if isinstance(data, dict) and isinstance(data.get("robots"), dict):
            found[f"{meta.get('namespace', '')}/{data.get('deployment', '')}"] = data["robots"]
    return found


def _reservations(snapshot: Snapshot, built_at: float) -> dict[str, list[dict]]:
    """The robot pool's reservations by fleet, each with ``active`` (false once its time has passed)."""
    now = datetime.datetime.fromtimestamp(built_at or time.time(), datetime.UTC)
    found: dict[str, list[dict]] = {}
    for reservation in robot_pool.readable(snapshot.reservations):
        found.setdefault(reservation.fleet, []).append(reservation.to_dict(now))
    return {fleet: sorted(rows, key=lambda r: r["robot"]) for fleet, rows in found.items()}


def _fleet_rows(snapshot: Snapshot, usable: list[Record], view: ClusterView, nodes: dict[str, dict],
                built_at: float = 0.0) -> list[dict]:  # fmt: skip
    fleets: dict[str, dict] = {}
    reservations = _reservations(snapshot, built_at)
    for fleet in reservations:
        fleets.setdefault(fleet, {"fleet": fleet, "robots": set(), "nodes": set()})
    for row in nodes.values():
        if row["fleet"]:
            entry = fleets.setdefault(row["fleet"], {"fleet": row["fleet"], "robots": set(), "nodes": set()})
            (entry["robots"] if row["robot"] else entry["nodes"]).add(row["robot"] or row["name"])
    servers: dict[str, dict] = {}
    bridges: dict[str, dict] = {}
    for record in usable:
        entry = fleets.setdefault(record.spec.fleet, {"fleet": record.spec.fleet, "robots": set(), "nodes": set()})
        entry.setdefault("deployments", set()).add(record.deployment)
        entry["namespace"] = record.namespace
        entry["nodes"] |= {i.node for i in record.placement.instances if i.tier != "onboard" and not i.cluster}
        entry["nodes"] |= {s.node for servers in record.placement.discovery.values() for s in servers}
        for fleet_servers in record.placement.discovery.values():
            for server in fleet_servers:
                pods = view.pods.get(f"{server.namespace}/{server.name}", [])
                live = [p for p in pods if not p.deleting]
                on_node = [p for p in live if p.node == server.node]
                running = any(p.phase == "Running" and p.ready for p in on_node)
                phase = "Running" if running else ("Pending" if live else "Missing")
                servers[f"{server.namespace}/{server.name}"] = {
                    "fleet": server.fleet,
                    "name": server.name,
                    "id": server.server_id,
                    "node": server.node,
                    "tier": server.tier,
                    "port": server.port,
                    "phase": phase,
                    "ready": nodes.get(server.node, {}).get("ready", False),
                }
        for fleet_bridges in record.placement.bridges.values():
            for bridge in fleet_bridges:
                bridges[f"{bridge.namespace}/{bridge.name}"] = {
                    "fleet": bridge.fleet,
                    "name": bridge.name,
                    "cluster": bridge.cluster,
                    "node": bridge.node,
                    "port": bridge.node_port,
                }
    offline: dict[str, list[dict]] = {}  # fleet -> its robots that are offline (docs/connectivity.md)
    for row in nodes.values():
        if row["fleet"] and row["robot"] and not row["ready"]:
            offline.setdefault(row["fleet"], []).append(
                {"robot": row["robot"], "node": row["name"], "since": row["since"], "condition": row["condition"]}
            )
    rows = []
    for name, entry in sorted(fleets.items()):
        rows.append(
            {
                "fleet": name,
                "namespace": entry.get("namespace", ""),
                "robots": sorted(entry["robots"]),
                "offline": sorted(offline.get(name, []), key=lambda r: r["robot"]),
                "nodes": sorted(entry["nodes"]),
                "deployments": sorted(entry.get("deployments", ())),
                "discovery": sorted((s for s in servers.values() if s["fleet"] == name), key=lambda s: s["id"]),
                "bridges": sorted((b for b in bridges.values() if b["fleet"] == name), key=lambda b: b["name"]),
                "reservations": reservations.get(name, []),
            }
        )
    return rows


def _software(snapshot: Snapshot, usable: list[Record], modules: list[dict], started: dict[str, str]) -> dict:
    catalog: dict[str, dict] = {}
    for configmap in snapshot.catalogs:
        try:
            parsed = catalog_of(configmap)
        except KuberosError:
            continue
        if parsed is None:
            continue
        for module in parsed.to_dict().get("modules", []):
            entry = catalog.setdefault(module["name"], {"module": module["name"], "description": "", "versions": {}})
            entry["description"] = module.get("description", entry["description"])
            for version in module.get("versions", []):
                entry["versions"][version["version"]] = {"version": version["version"], "image": version.get("image", "")}
    running: dict[str, dict[str, set]] = {}
    for row in modules:
        running.setdefault(row["module"], {}).setdefault(row["version"], set()).add(row["robot"])
    rows = []
    for name in sorted(set(catalog) | set(running)):
        entry = catalog.get(name, {"module": name, "description": "", "versions": {}})
        versions = dict(entry["versions"])
        for version in running.get(name, {}):
            versions.setdefault(version, {"version": version, "image": ""})
        rows.append(
            {
                "module": name,
                "description": entry["description"],
                "in_catalog": name in catalog,
                "versions": [
                    {
                        **v,
                        "robots": len(running.get(name, {}).get(key, ())),
                        "robot_names": sorted(running.get(name, {}).get(key, ()))[:20],
                    }
                    for key, v in sorted(versions.items())
                ],
            }
        )
    rollouts = []
    for record in usable:
        if not record.rollout:
            continue
        instances = [str(i) for i in record.rollout.get("instances") or []]
        since = str(record.rollout.get("started") or "")
        done = {i for i in instances if since and started.get(f"{record.namespace}/{i}", "") >= since}
        rollouts.append(
            {
                "namespace": record.namespace,
                "deployment": record.deployment,
                "from": record.rollout.get("from"),
                "to": record.rollout.get("revision"),
                "started": record.rollout.get("started", ""),
                "instances": len(instances),
                "done": len([i for i in instances if i in done]),
            }
        )
    revisions = [
        {"namespace": r.namespace, "deployment": r.deployment, "revision": r.revision, "fleet": r.spec.fleet} for r in usable
    ]
    revisions.sort(key=lambda r: (r["namespace"], r["deployment"]))
    return {"modules": rows, "rollouts": rollouts, "revisions": revisions}


def _events(snapshot: Snapshot, usable: list[Record], nodes: list[dict]) -> list[dict]:
    timeline = []
    for event in snapshot.events:
        meta = event.get("metadata", {})
        involved = event.get("involvedObject") or {}
        timeline.append(
            {
                "at": event.get("lastTimestamp") or event.get("eventTime") or meta.get("creationTimestamp") or "",
                "kind": EVENT_KINDS.get(event.get("reason", ""), "event"),
                "reason": event.get("reason", ""),
                "namespace": meta.get("namespace", ""),
                "object": involved.get("name", ""),
                "message": str(event.get("message", ""))[:1000],
                "warning": event.get("type") == "Warning",
                "count": event.get("count") or 1,
            }
        )
    for entry in snapshot.node_log:
        timeline.append(dict(entry))
    seen_failures = {(e["object"], e["at"]) for e in timeline if e["kind"] == "node"}
    for row in nodes:
        if not row["ready"] and (row["name"], row["since"]) not in seen_failures:
            # a robot's computer off the network is a robot offline, not a failed server: its modules stay
            robot = row["robot"] if row["tier"] == "onboard" else ""
            timeline.append(
                {
                    "at": row["since"],
                    "kind": "node",
                    "reason": "RobotOffline" if robot else "NodeNotReady",
                    "namespace": "",
                    "object": row["name"],
                    "message": f"robot {robot} is offline (node {row['name']}: {row['condition']}); its modules stay on it"
                    if robot
                    else f"node {row['name']} is NotReady: {row['condition']}",
                    "warning": True,
                    "count": 1,
                }
            )
    for record in usable:
        if record.rollout:
            timeline.append(
                {
                    "at": record.rollout.get("started", ""),
                    "kind": "rollout",
                    "reason": "RolloutStarted",
                    "namespace": record.namespace,
                    "object": record.deployment,
                    "message": f"rollout of {record.deployment} from revision {record.rollout.get('from')} "
                    f"to {record.rollout.get('revision')} in progress",
                    "warning": False,
                    "count": 1,
                }
            )
    order = {id(entry): index for index, entry in enumerate(timeline)}  # at the same second, the later noted first
    timeline.sort(key=lambda e: (e["at"] or "", order[id(e)]), reverse=True)
    return timeline[:MAX_EVENTS]


def build_view(snapshot: Snapshot, generation: int = 0, built_at: float = 0.0) -> View:
    names = {
        n["metadata"]["name"]: (n["metadata"].get("labels") or {}).get(node_labels.HOSTNAME, n["metadata"]["name"])
        for n in snapshot.nodes
    }
    resources, by_name = _node_rows(snapshot, names)
    view, images, started = _cluster_view(snapshot, names, by_name)
    statuses = _status_of(snapshot)
    usable = sorted((r for _c, r, _e in snapshot.records if r is not None), key=lambda r: (r.namespace, r.deployment))
    modules: list[dict] = []
    placements = {}
    limits = []
    for record in usable:
        _module_rows(record, view, images, statuses.get((record.namespace, record.deployment), {}), modules)
        placements[f"{record.namespace}/{record.deployment}"] = record.placement
        for module in record.spec.modules:
            if module.requirements.max_latency_ms is not None:
                limits.append(
                    {
                        "namespace": record.namespace,
                        "deployment": record.deployment,
                        "module": module.name,
                        "max_latency_ms": module.requirements.max_latency_ms,
                    }
                )
    modules.sort(key=lambda r: (r["namespace"], r["deployment"], r["robot"], r["module"]))
    phases: dict[str, int] = {}
    for row in modules:
        phases[row["phase"]] = phases.get(row["phase"], 0) + 1
    unreadable = [
        {"namespace": c["metadata"].get("namespace", ""), "name": c["metadata"].get("name", ""), "error": e}
        for c, r, e in snapshot.records
        if r is None
    ]
    summary = {
        "nodes": len(resources),
        "ready": sum(1 for r in resources if r["ready"]),
        "robots": len({r["robot"] for r in resources if r["robot"]}),
        "tiers": {t: sum(1 for r in resources if r["tier"] == t) for t in ("onboard", "edge", "cloud")},
        "deployments": len(usable),
        "rows": len(modules),
        "instances": len({(r["namespace"], r["instance"]) for r in modules}),
        "phases": phases,
        "stranded": sum(1 for r in modules if r["phase"] == "Stranded"),
        "over_latency": sum(1 for r in modules if r["over_latency"]),
        "unreadable_records": unreadable,
        "unreadable_reservations": robot_pool.read(snapshot.reservations)[1],  # each holds nothing; the others show
        "leader": snapshot.leader,
        "controller": snapshot.controller,
    }
    return View(
        generation=generation,
        built_at=built_at,
        leader=snapshot.leader,
        summary=summary,
        resources=resources,
        modules=modules,
        fleets=_fleet_rows(snapshot, usable, view, by_name, built_at),
        software=_software(snapshot, usable, modules, started),
        events=_events(snapshot, usable, resources),
        placements=placements,
        graphs=_graphs(snapshot),
        max_latency=limits,
    )


def instance_counts(view: View) -> dict[tuple[str, str, str, str, str], int]:
    """(namespace, deployment, module, tier, phase) -> instances (a shared instance counts once)."""
    seen: dict[tuple, tuple] = {}
    for row in view.modules:
        key = (row["namespace"], row["deployment"], row["module"], row["tier"], row["phase"])
        seen[(row["namespace"], row["instance"])] = key
    counts: dict[tuple, int] = {}
    for key in seen.values():
        counts[key] = counts.get(key, 0) + 1
    return counts


def select(rows: list[dict], query: dict, fields: tuple[str, ...]) -> list[dict]:
    """The rows matching the query's filters: ``q`` (a substring of any of ``fields``, case-insensitive) and exact
    matches on the other keys given (empty values are ignored; booleans as "true"/"false")."""
    text = str(query.get("q") or "").strip().lower()
    exact = {k: str(v) for k, v in query.items() if k not in ("q", "page", "size", "sort") and v not in (None, "")}
    found = []
    for row in rows:
        if text and not any(text in str(row.get(f, "")).lower() for f in fields):
            continue
        if any(_text(row.get(k)) != v for k, v in exact.items()):
            continue
        found.append(row)
    return found


def _text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return "" if value is None else str(value)


def page(rows: list[dict], number, size, largest: int = 1000) -> dict:
    """One page of rows: {"total", "page", "size", "pages", "rows"} (bad numbers fall back to the first page)."""
    try:
        size = max(1, min(int(size), largest))
    except (TypeError, ValueError):
        size = 100
    pages = max(1, -(-len(rows) // size))
    try:
        number = max(0, min(int(number), pages - 1))
    except (TypeError, ValueError):
        number = 0
    return {"total": len(rows), "page": number, "size": size, "pages": pages, "rows": rows[number * size : (number + 1) * size]}


def live_placement(view: View, key: str, robots: set[str] | None = None) -> Placement | None:
    """A deployment's placement as it stands, for the map: its instances (only those serving ``robots`` when
    given, for a readable map of a large fleet) on the nodes they use, with those nodes' live capacity."""
    placement = view.placements.get(key)
    if placement is None:
        return None
    instances = [i for i in placement.instances if robots is None or set(i.robots) & robots]
    shown = {r for i in instances for r in i.robots}
    used = {i.node for i in instances} | {s.node for servers in placement.discovery.values() for s in servers}
    nodes = []
    for row in view.resources:
        if row["name"] not in used and not (row["robot"] and row["robot"] in (shown if robots is None else robots)):
            continue
        total, taken = row["allocatable"], row["allocated"]
        nodes.append(
            {
                "name": row["name"],
                "tier": row["tier"] or "edge",
                "robot": row["robot"],
                "fleet": row["fleet"],
                "cpu_millis": int(total["cpu"] * 1000),
                "memory_bytes": int(total["memory"]),
                "gpu": int(total["gpu"]),
                "free_cpu_millis": int((total["cpu"] - taken["cpu"]) * 1000),
                "free_memory_bytes": int(total["memory"] - taken["memory"]),
                "free_gpu": int(total["gpu"] - taken["gpu"]),
            }
        )
    return Placement(instances, placement.discovery, placement.deployments, nodes, placement.bridges, placement.robot_servers)
