"""Placement of every module of every robot, and of each fleet's discovery servers.

``place_modules(deployments, inventory, allocated)`` is pure and deterministic:

1. hard requirements filter the nodes (onboard pins to the robot's own computer; max_latency;
   cpu, memory, GPU and pod slots against what remains after every earlier placement and
   what ``allocated`` says is already used; arch; devices);
2. tiers are tried in preference order, falling back only when a tier has no feasible node;
3. among feasible nodes of a tier the one left with the most free capacity wins (spreading
   load), ties broken by lower latency and then by name.

Shared modules pack robots onto instances up to ``robotsPerInstance``. Every placement
carries a short reason; an infeasible module raises ``PlacementError`` with a per-node
account of why each candidate was rejected.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from . import naming, quantities
from .catalog import catalog_problems_against_inventory
from .errors import PlacementError, Problem, SpecError, did_you_mean
from .inventory import Inventory, Node
from .spec import RosDeployment, RosModule, name_clash_problems

DISCOVERY_CPU_MILLIS = 100
DISCOVERY_MEMORY_BYTES = 64 * 1024**2
BRIDGE_CPU_MILLIS = 200
BRIDGE_MEMORY_BYTES = 256 * 1024**2
PLACEMENT_API_VERSION = "kuberos.io/v1alpha1"


@dataclass
class _Free:
    cpu: int
    memory: int
    gpu: int
    pods: int


@dataclass(frozen=True)
class Instance:
    """One running copy of a module: where it runs and which robots it serves."""

    name: str
    deployment: str
    fleet: str
    namespace: str
    module: str
    node: str
    tier: str
    robots: tuple[str, ...]
    reason: str
    latency_ms: float
    cpu_millis: int
    memory_bytes: int
    gpu: int
    shared: bool = False
    cluster: str = ""  # a third-party cluster it runs in (then ``node`` is that cluster's name)


@dataclass(frozen=True)
class BridgeServer:
    """The main cluster's end of the KubeROS-Bridge to one third-party cluster, for one fleet."""

    fleet: str
    namespace: str
    cluster: str
    name: str
    node: str
    tier: str
    reason: str
    node_port: int = naming.BRIDGE_NODE_PORT  # the NodePort the third-party cluster connects to


@dataclass(frozen=True)
class DiscoveryServer:
    fleet: str
    namespace: str
    server_id: int
    name: str
    node: str
    tier: str
    port: int
    reason: str


@dataclass
class Placement:
    instances: list[Instance] = field(default_factory=list)
    discovery: dict[str, list[DiscoveryServer]] = field(default_factory=dict)
    deployments: list[dict] = field(default_factory=list)
    # Nodes the deployments could use, with capacity and what is left free after this placement.
    nodes: list[dict] = field(default_factory=list)
    bridges: dict[str, list[BridgeServer]] = field(default_factory=dict)  # fleet -> its bridge servers

    def rows(self) -> list[dict]:
        """One row per (robot, module): the answer to 'where does this run for that robot?'."""
        rows = []
        for inst in self.instances:
            for robot in inst.robots:
                rows.append(
                    {
                        "deployment": inst.deployment,
                        "fleet": inst.fleet,
                        "robot": robot,
                        "module": inst.module,
                        "instance": inst.name,
                        "node": inst.node,
                        "tier": inst.tier,
                        "robots": list(inst.robots),
                        "shared": inst.shared,
                        "reason": inst.reason,
                        "cluster": inst.cluster,
                    }
                )
        rows.sort(key=lambda r: (r["deployment"], r["robot"], r["module"]))
        return rows

    def to_dict(self) -> dict:
        return {
            "apiVersion": PLACEMENT_API_VERSION,
            "kind": "Placement",
            "deployments": self.deployments,
            "discovery": [
                {
                    "fleet": fleet,
                    "namespace": servers[0].namespace,
                    "port": servers[0].port,
                    "servers": [
                        {"id": s.server_id, "name": s.name, "node": s.node, "tier": s.tier, "reason": s.reason} for s in servers
                    ],
                }
                for fleet, servers in self.discovery.items()
            ],
            "instances": [
                {**{k: v for k, v in asdict(inst).items() if k not in ("robots",)}, "robots": list(inst.robots)}
                for inst in self.instances
            ],
            "placements": self.rows(),
            "nodes": self.nodes,
            "bridges": [asdict(b) for servers in self.bridges.values() for b in servers],
        }

    @classmethod
    def from_dict(cls, data: dict) -> Placement:
        """Read back ``to_dict`` output (e.g. a placement.json, or a filter result)."""
        try:
            instances = [Instance(**{**inst, "robots": tuple(inst["robots"])}) for inst in data["instances"]]
            discovery = {
                entry["fleet"]: [
                    DiscoveryServer(
                        entry["fleet"], entry["namespace"], s["id"], s["name"], s["node"], s["tier"], entry["port"], s["reason"]
                    )
                    for s in entry["servers"]
                ]
                for entry in data["discovery"]
            }
            bridges: dict[str, list[BridgeServer]] = {}
            for entry in data.get("bridges", []):
                bridges.setdefault(entry["fleet"], []).append(BridgeServer(**entry))
        except (KeyError, TypeError) as exc:
            raise SpecError([Problem("placement", "", f"not a placement produced by place_modules ({exc!r})")]) from None
        return cls(instances, discovery, list(data.get("deployments", [])), list(data.get("nodes", [])), bridges)


def _initial_free(inventory: Inventory, allocated: dict | None) -> dict[str, _Free]:
    free = {n.name: _Free(n.cpu_millis, n.memory_bytes, n.gpu, n.pods) for n in inventory.nodes.values()}
    problems = []
    for node, used in sorted((allocated or {}).items()):
        if node not in free:
            continue  # workloads on nodes outside the inventory do not constrain placement
        try:
            free[node].cpu -= quantities.parse_cpu(used.get("cpu", 0))
            free[node].memory -= quantities.parse_memory(used.get("memory", 0))
            free[node].gpu -= int(used.get("gpu", 0))
            free[node].pods -= int(used.get("pods", 0))
        except (ValueError, AttributeError, TypeError) as exc:
            problems.append(Problem("allocated", node, f"{used!r} is not valid; expected cpu, memory, gpu and pods ({exc})"))
    if problems:
        raise SpecError(problems, title="invalid allocation data")
    return free


def _fmt_cpu(millis: int) -> str:
    return f"{millis / 1000:g}"


def _fmt_mem(size: int) -> str:
    return f"{size / 1024**3:.3g}Gi" if size >= 1024**3 else f"{size / 1024**2:.3g}Mi"


class _Scheduler:
    def __init__(self, inventory: Inventory, allocated: dict | None, unavailable: dict[str, str] | None = None):
        self.inventory = inventory
        self.free = _initial_free(inventory, allocated)
        self.failures: list[str] = []
        # Nodes nothing may be placed on (e.g. NotReady), and for the instance being placed, nodes it must avoid.
        self.unavailable = dict(unavailable or {})
        self.avoid: dict[str, str] = {}
        # Instances that keep the node they run on (sticky placement): name -> previous Instance, resources taken.
        self.kept: dict[str, Instance] = {}

    # -- feasibility -------------------------------------------------------------------------
    def rejection(self, node: Node, module: RosModule, robots, cpu: int, memory: int, gpu: int) -> str | None:
        """Why ``node`` cannot run this instance for ``robots``, or None when it can."""
        why = self.unavailable.get(node.name) or self.avoid.get(node.name)
        if why:
            return why
        return self.requirement_rejection(node, module, robots) or self.capacity_rejection(node, cpu, memory, gpu)

    def requirement_rejection(self, node: Node, module: RosModule | None, robots) -> str | None:
        """Why the module's hard requirements (arch, devices, max_latency) rule ``node`` out, or None."""
        req = module.requirements if module is not None else None
        if req is not None:
            if req.arch and node.arch not in req.arch:
                return f"arch {node.arch}, needs {'/'.join(req.arch)}"
            missing = [d for d in req.devices if d not in node.devices]
            if missing:
                return f"lacks device(s) {', '.join(missing)}"
            if req.max_latency_ms is not None:
                for robot in robots:
                    latency = self.inventory.latency_ms(robot, node.name)
                    if latency > req.max_latency_ms:
                        return f"latency {latency:g} ms to {robot} > max_latency {req.max_latency_ms:g} ms"
        return None

    def capacity_rejection(self, node: Node, cpu: int, memory: int, gpu: int) -> str | None:
        free = self.free[node.name]
        if free.pods < 1:
            return "no pod slots left"
        if free.cpu < cpu:
            return f"cpu: needs {_fmt_cpu(cpu)}, {_fmt_cpu(max(free.cpu, 0))} free of {_fmt_cpu(node.cpu_millis)}"
        if free.memory < memory:
            return f"memory: needs {_fmt_mem(memory)}, {_fmt_mem(max(free.memory, 0))} free of {_fmt_mem(node.memory_bytes)}"
        if free.gpu < gpu:
            if not node.gpu:
                return f"gpu: needs {gpu}, node has none"
            return f"gpu: needs {gpu}, {max(free.gpu, 0)} free of {node.gpu}"
        return None

    def score(self, node: Node, cpu: int, memory: int, gpu: int) -> float:
        """Fraction of the node left free after this placement, on its scarcest resource."""
        free = self.free[node.name]
        parts = [(free.cpu - cpu) / node.cpu_millis if node.cpu_millis else 0.0]
        parts.append((free.memory - memory) / node.memory_bytes if node.memory_bytes else 0.0)
        if gpu:
            parts.append((free.gpu - gpu) / node.gpu)
        return min(parts)

    def take(self, node: str, cpu: int, memory: int, gpu: int):
        free = self.free[node]
        free.cpu -= cpu
        free.memory -= memory
        free.gpu -= gpu
        free.pods -= 1

    def candidates(self, tier: str, fleet: str, robot: str | None) -> tuple[Node, ...]:
        if tier == "onboard":
            return (self.inventory.nodes[self.inventory.robots[robot].node],) if robot else ()
        return self.inventory.tier_nodes(tier, fleet)

    def choose(self, deployment: RosDeployment, module: RosModule, robots: tuple[str, ...]):
        """Pick a node for one instance serving ``robots`` and take its resources.

        Returns ``(node, tier, latency, reason)``, or ``(None, None, None, accounts)`` where
        ``accounts`` says why each candidate node of each tier was rejected.
        """
        res = module.resources
        accounts: list[str] = []
        skipped: list[str] = []
        robot = robots[0] if len(robots) == 1 else None
        for tier in module.tiers:
            best = None
            feasible = 0
            candidates = self.candidates(tier, deployment.fleet, robot)
            if not candidates:
                accounts.append(f"({tier}): no {tier} nodes available to fleet {deployment.fleet}")
            for node in candidates:
                why = self.rejection(node, module, robots, res.cpu_millis, res.memory_bytes, res.gpu)
                if why is not None:
                    accounts.append(f"{node.name} ({tier}): {why}")
                    continue
                feasible += 1
                latency = max(self.inventory.latency_ms(r, node.name) for r in robots)
                key = (-self.score(node, res.cpu_millis, res.memory_bytes, res.gpu), latency, node.name)
                if best is None or key < best[0]:
                    best = (key, node, latency)
            if best is not None:
                _key, node, latency = best
                self.take(node.name, res.cpu_millis, res.memory_bytes, res.gpu)
                return node, tier, latency, self._reason(module, tier, skipped, feasible, latency)
            skipped.append(tier)
        return None, None, None, accounts

    @staticmethod
    def _reason(module: RosModule, tier: str, skipped: list[str], feasible: int, latency: float) -> str:
        if module.requirements.onboard:
            head = "onboard required"
        elif skipped:
            head = f"fallback to {tier} ({', '.join(skipped)}: no feasible node)"
        else:
            head = f"preferred tier {tier}"
        parts = [head]
        if tier != "onboard":
            parts.append(f"most free of {feasible} feasible")
        if module.requirements.max_latency_ms is not None:
            parts.append(f"{latency:g} ms <= {module.requirements.max_latency_ms:g} ms")
        return "; ".join(parts)

    def fail(self, deployment: RosDeployment, module: RosModule, robots, accounts):
        line = deployment.line_of(module.path)
        where = f"{deployment.source}:{line}" if line else deployment.source
        who = f"robot {robots[0]}" if len(robots) == 1 else f"robots {', '.join(robots)}"
        head = (
            f"{where}: {module.path} '{module.name}' of {deployment.name} has no feasible node for {who} "
            f"(tiers tried: {', '.join(module.tiers)})"
        )
        self.failures.append("\n".join([head] + [f"    {a}" for a in accounts]))

    # -- modules -----------------------------------------------------------------------------
    def place_module(self, deployment: RosDeployment, module: RosModule, robots: tuple[str, ...], out: list[Instance]):
        namespace = naming.fleet_namespace(deployment.fleet)
        res = module.resources
        if module.cluster:
            self.place_in_cluster(deployment, module, robots, out)
            return
        if module.strategy != "shared":
            for robot in robots:
                name = naming.dedicated_instance_name(deployment.name, module.name, robot)
                if name in self.kept:
                    out.append(_kept_instance(self.kept[name], module))
                    continue
                node, tier, latency, detail = self.choose(deployment, module, (robot,))
                if node is None:
                    self.fail(deployment, module, (robot,), detail)
                    continue
                out.append(
                    Instance(
                        naming.dedicated_instance_name(deployment.name, module.name, robot),
                        deployment.name,
                        deployment.fleet,
                        namespace,
                        module.name,
                        node.name,
                        tier,
                        (robot,),
                        detail,
                        latency,
                        res.cpu_millis,
                        res.memory_bytes,
                        res.gpu,
                    )
                )
            return
        open_instances: list[dict] = []  # every instance, in creation order
        with_room: list[dict] = []  # those that can still take a robot
        limit = module.requirements.max_latency_ms
        kept = sorted(
            (k for k in self.kept.values() if k.deployment == deployment.name and k.module == module.name and k.shared),
            key=lambda k: k.name,
        )
        covered = set()
        for inst in kept:
            entry = {
                "kept": inst,
                "node": self.inventory.nodes[inst.node],
                "robots": list(inst.robots),
                "latency": inst.latency_ms,
            }
            open_instances.append(entry)
            covered.update(inst.robots)
            if len(inst.robots) < module.robots_per_instance:
                with_room.append(entry)
        used_names = {k.name for k in kept}
        for robot in (r for r in robots if r not in covered):
            for inst in list(with_room):  # a copy: a full instance is removed (then the loop ends)
                latency = self.inventory.latency_ms(robot, inst["node"].name)
                if limit is None or latency <= limit:
                    inst["robots"].append(robot)
                    inst["latency"] = max(inst["latency"], latency)
                    if len(inst["robots"]) >= module.robots_per_instance:
                        with_room.remove(inst)
                    break
            else:
                node, tier, latency, detail = self.choose(deployment, module, (robot,))
                if node is None:
                    self.fail(deployment, module, (robot,), detail)
                    continue
                inst = {"node": node, "tier": tier, "robots": [robot], "latency": latency, "reason": detail}
                open_instances.append(inst)
                if module.robots_per_instance > 1:
                    with_room.append(inst)
        index = 0
        for inst in open_instances:
            if "kept" in inst:
                previous = inst["kept"]
                grown = len(inst["robots"]) > len(previous.robots)
                reason = previous.reason
                if grown:
                    reason = (
                        f"{reason.split('; shared by ')[0]}; shared by {len(inst['robots'])}/{module.robots_per_instance} robots"
                    )
                out.append(_kept_instance(previous, module, tuple(inst["robots"]), reason, inst["latency"]))
                continue
            while naming.shared_instance_name(deployment.name, module.name, index) in used_names:
                index += 1
            name = naming.shared_instance_name(deployment.name, module.name, index)
            used_names.add(name)
            out.append(
                Instance(
                    name,
                    deployment.name,
                    deployment.fleet,
                    namespace,
                    module.name,
                    inst["node"].name,
                    inst["tier"],
                    tuple(inst["robots"]),
                    f"{inst['reason']}; shared by {len(inst['robots'])}/{module.robots_per_instance} robots",
                    inst["latency"],
                    res.cpu_millis,
                    res.memory_bytes,
                    res.gpu,
                    shared=True,
                )
            )

    def place_in_cluster(self, deployment: RosDeployment, module: RosModule, robots: tuple[str, ...], out: list[Instance]):
        """A module of a third-party cluster: that cluster's scheduler picks its node; only max_latency is checked here."""
        cluster = self.inventory.clusters[module.cluster]
        limit = module.requirements.max_latency_ms
        res = module.resources
        for robot in robots:
            if limit is not None and cluster.latency_ms > limit:
                account = f"{cluster.name} (cluster): latency {cluster.latency_ms:g} ms to {robot} > max_latency {limit:g} ms"
                self.fail(deployment, module, (robot,), [account])
                continue
            reason = f"third-party cluster {cluster.name}; topics over the KubeROS-Bridge"
            if limit is not None:
                reason += f"; {cluster.latency_ms:g} ms <= {limit:g} ms"
            out.append(
                Instance(
                    naming.dedicated_instance_name(deployment.name, module.name, robot),
                    deployment.name, deployment.fleet, naming.fleet_namespace(deployment.fleet), module.name,
                    cluster.name, "cloud", (robot,), reason, cluster.latency_ms, res.cpu_millis, res.memory_bytes, res.gpu,
                    cluster=cluster.name,
                )
            )  # fmt: skip

    def place_bridge(self, fleet: str, cluster: str) -> BridgeServer | None:
        """The bridge server of a fleet to a third-party cluster: on the fleet's edge node with most room, else cloud."""
        for tier in ("edge", "cloud"):
            options = []
            for node in self.inventory.tier_nodes(tier, fleet):
                if self.rejection(node, None, (), BRIDGE_CPU_MILLIS, BRIDGE_MEMORY_BYTES, 0) is None:
                    options.append((-self.score(node, BRIDGE_CPU_MILLIS, BRIDGE_MEMORY_BYTES, 0), node.name, node))
            if options:
                _score, _name, node = min(options)
                self.take(node.name, BRIDGE_CPU_MILLIS, BRIDGE_MEMORY_BYTES, 0)
                return BridgeServer(
                    fleet, naming.fleet_namespace(fleet), cluster, naming.bridge_server_name(cluster), node.name, tier,
                    f"{tier} node with most room; bridge to cluster {cluster}", self.inventory.clusters[cluster].bridge_node_port,
                )  # fmt: skip
        self.failures.append(
            f"the bridge server of fleet {fleet} to cluster {cluster} has no edge or cloud node with room for it"
        )
        return None

    # -- discovery servers -------------------------------------------------------------------
    def place_discovery(self, fleet: str, count: int, port: int, keep: dict | None = None) -> list[DiscoveryServer]:
        """Place the fleet's discovery servers on distinct nodes; servers in ``keep`` (by id) stay where they are."""
        keep = keep or {}
        namespace = naming.fleet_namespace(fleet)
        robots = self.inventory.fleets[fleet]
        tiers = [
            ("edge", self.inventory.tier_nodes("edge", fleet)),
            ("cloud", self.inventory.tier_nodes("cloud", fleet)),
            ("onboard", tuple(self.inventory.nodes[self.inventory.robots[r].node] for r in robots)),
        ]
        servers: list[DiscoveryServer] = []
        used: set[str] = {s.node for s in keep.values()}
        accounts: list[str] = []
        for server_id in range(count):
            if server_id in keep:
                servers.append(keep[server_id])
                continue
            chosen = None
            for distinct in (True, False):
                for tier, nodes in tiers:
                    options = []
                    for node in nodes:
                        if distinct and node.name in used:
                            continue
                        why = self.rejection(node, None, (), DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
                        if why is None:
                            options.append(
                                (-self.score(node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0), node.name, node, tier)
                            )
                        elif distinct:
                            accounts.append(f"{node.name} ({tier}): {why}")
                    if options:
                        chosen = min(options)
                        break
                if chosen:
                    break
            if chosen is None:
                self.failures.append(
                    "\n".join(
                        [f"discovery server {server_id} of fleet {fleet} has no node with room for it"]
                        + [f"    {a}" for a in accounts]
                    )
                )
                continue
            _score, _name, node, tier = chosen
            shares = node.name in used
            used.add(node.name)
            self.take(node.name, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
            reason = (
                f"{tier} node; distinct from other servers"
                if not shares
                else f"{tier} node; shares it with another server (too few nodes)"
            )
            servers.append(
                DiscoveryServer(
                    fleet, namespace, server_id, naming.discovery_server_name(server_id), node.name, tier, port, reason
                )
            )
        return servers


def _kept_instance(previous: Instance, module: RosModule, robots=None, reason=None, latency=None) -> Instance:
    """A previous instance on the node it runs on, with the module's resources as the spec says them now."""
    res = module.resources
    return Instance(
        previous.name, previous.deployment, previous.fleet, previous.namespace, previous.module, previous.node,
        previous.tier, tuple(robots if robots is not None else previous.robots), reason or previous.reason,
        previous.latency_ms if latency is None else latency, res.cpu_millis, res.memory_bytes, res.gpu, previous.shared,
    )  # fmt: skip


def _keep_previous(scheduler: _Scheduler, deployments: list[RosDeployment], targets: dict[str, tuple], previous: Placement):
    """Sticky placement: every instance of ``previous`` that still fits where it runs stays there.

    An instance stays when its deployment and module still exist, it still serves one of the targeted robots, its
    node is in the inventory and available, serves the fleet, is of a tier the module may use, meets the module's
    hard requirements and has room for the module's resources as the spec says them now. An instance that ran on
    its preferred tier while the spec now prefers another tier is placed again (the developer asked for the move);
    one that ran on a fallback tier, or was moved there by the controller, stays. Kept instances take their
    resources before anything new is placed.
    """
    modules = {(d.name, m.name): (d, m) for d in deployments for m in d.modules}
    for inst in sorted(previous.instances, key=lambda i: i.name):
        found = modules.get((inst.deployment, inst.module))
        if found is None or inst.cluster:
            continue
        dep, module = found
        robots = tuple(r for r in inst.robots if r in targets.get(dep.name, ()))
        if module.cluster or not robots or inst.shared != (module.strategy == "shared"):
            continue
        robots = robots[: module.robots_per_instance]
        node = scheduler.inventory.nodes.get(inst.node)
        if node is None or node.tier not in module.tiers:
            continue
        if node.tier != module.tiers[0] and not inst.reason.startswith(("fallback", "moved from")):
            continue
        if node not in scheduler.candidates(node.tier, dep.fleet, robots[0]):
            continue
        res = module.resources
        if scheduler.rejection(node, module, robots, res.cpu_millis, res.memory_bytes, res.gpu) is not None:
            continue
        scheduler.take(node.name, res.cpu_millis, res.memory_bytes, res.gpu)
        scheduler.kept[inst.name] = _kept_instance(inst, module, robots)


def _kept_discovery(scheduler: _Scheduler, previous: Placement | None, fleet: str) -> dict[int, DiscoveryServer]:
    """The fleet's discovery servers that stay where they run (their node is in the inventory and available)."""
    kept = {}
    for server in previous.discovery.get(fleet, []) if previous else []:
        node = scheduler.inventory.nodes.get(server.node)
        if (
            node is None
            or scheduler.unavailable.get(node.name)
            or scheduler.capacity_rejection(node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
        ):
            continue
        scheduler.take(node.name, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
        kept[server.server_id] = server
    return kept


def _check_against_inventory(deployments: list[RosDeployment], inventory: Inventory) -> list[Problem]:
    problems = []
    ports: dict[str, tuple[int, str]] = {}
    for dep in deployments:
        if dep.fleet not in inventory.fleets:
            problems.append(
                Problem(
                    dep.source,
                    "metadata.targetFleet",
                    f"'{dep.fleet}' is not a fleet in the inventory{did_you_mean(dep.fleet, inventory.fleets)} "
                    f"(fleets: {', '.join(inventory.fleets) or 'none'})",
                    dep.line_of("metadata.targetFleet"),
                )
            )
            continue
        members = inventory.fleets[dep.fleet]
        for module in dep.modules:
            if not module.cluster:
                continue
            path = f"{module.path}.cluster"
            cluster = inventory.clusters.get(module.cluster)
            if cluster is None:
                known = list(inventory.clusters)
                problems.append(
                    Problem(
                        dep.source,
                        path,
                        f"'{module.cluster}' is not a cluster of the inventory's group clusters"
                        f"{did_you_mean(module.cluster, known)} (clusters: {', '.join(known) or 'none'})",
                        dep.line_of(path),
                    )
                )
            elif not cluster.serves_fleet(dep.fleet):
                problems.append(
                    Problem(
                        dep.source,
                        path,
                        f"cluster '{module.cluster}' does not serve fleet {dep.fleet} "
                        f"(its kuberos_fleets: {', '.join(cluster.fleets)})",
                        dep.line_of(path),
                    )
                )
        for index, robot in enumerate(dep.robots or ()):
            if robot in members:
                continue
            path = f"metadata.robotSelector.robot[{index}]"
            if robot in inventory.robots:
                detail = f"it belongs to fleet {inventory.robots[robot].fleet}"
            else:
                detail = f"robots of {dep.fleet}: {', '.join(members)}{did_you_mean(robot, members)}"
            problems.append(
                Problem(dep.source, path, f"'{robot}' is not a robot of fleet {dep.fleet} ({detail})", dep.line_of(path))
            )
        if dep.fleet in ports and ports[dep.fleet][0] != dep.discovery_port:
            problems.append(
                Problem(
                    dep.source,
                    "discovery.port",
                    f"{dep.discovery_port} differs from port {ports[dep.fleet][0]} set by {ports[dep.fleet][1]} "
                    f"for the same fleet; expected one port per fleet",
                    dep.line_of("discovery.port"),
                )
            )
        ports.setdefault(dep.fleet, (dep.discovery_port, dep.source))
    if not problems:
        # With the fleets' robots known, names that clash through a robot's name (module b of robot c-1 and module
        # b-c of robot 1) are found too; loading a spec alone knows the robots of a robotSelector only.
        problems += name_clash_problems(deployments, lambda dep: dep.robots or inventory.fleets.get(dep.fleet))
    return problems + catalog_problems_against_inventory(deployments, inventory)


def place_modules(
    deployments: list[RosDeployment],
    inventory: Inventory,
    allocated: dict | None = None,
    unavailable: dict[str, str] | None = None,
    previous: Placement | None = None,
) -> Placement:
    """Place every module instance of every deployment; see the module docstring. Nodes in ``unavailable``
    (node name -> why, e.g. NotReady in the cluster) take nothing; the reason shows in a failure's account.

    ``previous`` is what runs now (the deployments' records and the fleets' live discovery servers): what still
    fits where it runs stays there (see ``_keep_previous``), and a fleet's discovery servers are the fleet's, kept
    on their nodes and never fewer than run now. ``allocated`` must then leave out what ``previous`` holds."""
    problems = _check_against_inventory(deployments, inventory)
    running = {f: s[0].port for f, s in (previous.discovery.items() if previous else ()) if s}
    for dep in deployments:
        if dep.fleet in running and dep.discovery_port != running[dep.fleet]:
            problems.append(
                Problem(
                    dep.source,
                    "discovery.port",
                    f"{dep.discovery_port} differs from port {running[dep.fleet]}, which the discovery servers of fleet "
                    f"{dep.fleet} run on (they are the fleet's, shared by its deployments); expected {running[dep.fleet]}",
                    dep.line_of("discovery.port"),
                )
            )
    if problems:
        raise SpecError(problems, title="the RosDeployment does not match the inventory")
    scheduler = _Scheduler(inventory, allocated, unavailable)
    placement = Placement()
    fleets: dict[str, list[RosDeployment]] = {}
    for dep in deployments:
        fleets.setdefault(dep.fleet, []).append(dep)
    targets = {dep.name: (tuple(sorted(dep.robots)) if dep.robots else inventory.fleets[dep.fleet]) for dep in deployments}
    kept_servers = {fleet: _kept_discovery(scheduler, previous, fleet) for fleet in sorted(fleets)}
    if previous is not None:
        _keep_previous(scheduler, deployments, targets, previous)
    for fleet in sorted(fleets):
        count = max([d.discovery_servers for d in fleets[fleet]] + [len((previous.discovery if previous else {}).get(fleet, []))])
        port = (
            previous.discovery[fleet][0].port if previous and previous.discovery.get(fleet) else fleets[fleet][0].discovery_port
        )
        placement.discovery[fleet] = scheduler.place_discovery(fleet, count, port, kept_servers[fleet])
    for fleet in sorted(fleets):
        for cluster in sorted({m.cluster for d in fleets[fleet] for m in d.modules if m.cluster}):
            bridge = scheduler.place_bridge(fleet, cluster)
            if bridge is not None:
                placement.bridges.setdefault(fleet, []).append(bridge)
    for dep in deployments:
        robots = targets[dep.name]
        placement.deployments.append(
            {
                "name": dep.name,
                "fleet": dep.fleet,
                "namespace": naming.fleet_namespace(dep.fleet),
                "robots": list(robots),
                "source": dep.source,
            }
        )
        for module in dep.modules:
            scheduler.place_module(dep, module, robots, placement.instances)
    if scheduler.failures:
        raise PlacementError(scheduler.failures)
    placement.nodes = _node_summaries(inventory, scheduler.free, placement)
    return placement


@dataclass(frozen=True)
class Move:
    """An instance (or a discovery server) that left its node, and why."""

    namespace: str
    instance: str
    deployment: str
    module: str
    robots: tuple[str, ...]
    from_node: str
    to_node: str
    why: str


@dataclass(frozen=True)
class Stranded:
    """An instance whose node is ruled out but that has nowhere to go; it stays where it was."""

    namespace: str
    instance: str
    deployment: str
    module: str
    robots: tuple[str, ...]
    node: str
    why: str


@dataclass
class Replacement:
    placement: Placement
    moves: list[Move] = field(default_factory=list)
    stranded: list[Stranded] = field(default_factory=list)


def replace_modules(
    deployments: list[RosDeployment],
    inventory: Inventory,
    previous: Placement,
    allocated: dict | None = None,
    unavailable: dict[str, str] | None = None,
    avoid: dict[str, dict[str, str]] | None = None,
    hold: frozenset | set = frozenset(),
) -> Replacement:
    """Keep every instance of ``previous`` where it is unless its node is ruled out, and move only those.

    A node is ruled out for an instance when it is ``unavailable`` (node name -> why, e.g. NotReady),
    when ``avoid[instance]`` names it (e.g. the pod keeps failing there), when it left the inventory,
    or when the module's hard requirements no longer hold there (e.g. a measured latency above
    ``max_latency``). Kept instances keep their resources first; the others are placed again with the
    same rules as ``place_modules``. An instance that has no other feasible node (onboard modules of a
    robot whose computer is down, or no capacity anywhere) stays on its node and is reported as
    stranded, so one fault never removes a running module. Discovery servers move the same way.
    Instances named in ``hold`` stay where they are whatever their node (a fault not yet confirmed).
    """
    problems = _check_against_inventory(deployments, inventory)
    if problems:
        raise SpecError(problems, title="the RosDeployment does not match the inventory")
    avoid = avoid or {}
    scheduler = _Scheduler(inventory, allocated, unavailable)
    modules = {(d.name, m.name): (d, m) for d in deployments for m in d.modules}
    result = Replacement(Placement(deployments=list(previous.deployments), bridges=dict(previous.bridges)))

    def ruled_out(name: str, node: str, module: RosModule | None, robots) -> str | None:
        if name in hold and node in inventory.nodes:
            return None
        if node not in inventory.nodes:
            return f"node {node} is no longer in the inventory"
        why = scheduler.unavailable.get(node) or avoid.get(name, {}).get(node)
        if why:
            return why
        return scheduler.requirement_rejection(inventory.nodes[node], module, robots)

    # 1. What stays keeps its resources before anything moves.
    kept_discovery: dict[str, dict[int, DiscoveryServer]] = {}
    leaving_discovery: dict[str, dict[int, tuple[DiscoveryServer, str]]] = {}
    for fleet, servers in previous.discovery.items():
        for server in servers:
            why = ruled_out(server.name, server.node, None, ())
            if why is None:
                kept_discovery.setdefault(fleet, {})[server.server_id] = server
                scheduler.take(server.node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
            else:
                leaving_discovery.setdefault(fleet, {})[server.server_id] = (server, why)
    slots: list[Instance | None] = []
    leaving: list[tuple[int, Instance, str]] = []
    for inst in previous.instances:
        found = modules.get((inst.deployment, inst.module))
        if found is None:
            continue  # the module is gone from the spec: deploying again prunes it, moving is not our job
        if inst.cluster:
            slots.append(inst)  # a third-party cluster places it on its own nodes
            continue
        why = ruled_out(inst.name, inst.node, found[1], inst.robots)
        if why is None:
            slots.append(inst)
            if inst.node in scheduler.free:
                scheduler.take(inst.node, inst.cpu_millis, inst.memory_bytes, inst.gpu)
        else:
            leaving.append((len(slots), inst, why))
            slots.append(None)

    # 2. Discovery servers, then module instances, go to the best other node.
    for fleet, servers in previous.discovery.items():
        moving = leaving_discovery.get(fleet, {})
        if not moving:
            result.placement.discovery[fleet] = servers
            continue
        placed = scheduler.place_discovery(fleet, len(servers), servers[0].port, kept_discovery.get(fleet, {}))
        scheduler.failures.clear()
        by_id = {s.server_id: s for s in placed}
        final = []
        for server in servers:
            new = by_id.get(server.server_id)
            if server.server_id in moving and new is not None:
                why = moving[server.server_id][1]
                new = DiscoveryServer(
                    new.fleet,
                    new.namespace,
                    new.server_id,
                    new.name,
                    new.node,
                    new.tier,
                    new.port,
                    f"moved from {server.node} ({why}); {new.reason}",
                )
                result.moves.append(Move(new.namespace, new.name, "", "discovery-server", (), server.node, new.node, why))
            elif server.server_id in moving:
                new = server
                scheduler.take(server.node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
                result.stranded.append(
                    Stranded(
                        server.namespace,
                        server.name,
                        "",
                        "discovery-server",
                        (),
                        server.node,
                        f"{moving[server.server_id][1]}; no other node",
                    )
                )
            final.append(new)
        result.placement.discovery[fleet] = final
    for index, inst, why in leaving:
        dep, module = modules[(inst.deployment, inst.module)]
        res = module.resources
        scheduler.avoid = dict(avoid.get(inst.name, {}))
        scheduler.avoid.setdefault(inst.node, why)
        node, tier, latency, detail = scheduler.choose(dep, module, inst.robots)
        scheduler.avoid = {}
        if node is None:
            if inst.node in scheduler.free:
                scheduler.take(inst.node, inst.cpu_millis, inst.memory_bytes, inst.gpu)
            stay = "onboard modules stay with their robot" if module.requirements.onboard else "no other feasible node"
            accounts = [a for a in detail if not a.startswith(f"{inst.node} ")]
            result.stranded.append(
                Stranded(
                    inst.namespace,
                    inst.name,
                    inst.deployment,
                    inst.module,
                    inst.robots,
                    inst.node,
                    "; ".join([why, stay, *accounts[:5]]),
                )
            )
            slots[index] = inst
            continue
        slots[index] = Instance(
            inst.name,
            inst.deployment,
            inst.fleet,
            inst.namespace,
            inst.module,
            node.name,
            tier,
            inst.robots,
            f"moved from {inst.node} ({why}); {detail}",
            latency,
            res.cpu_millis,
            res.memory_bytes,
            res.gpu,
            inst.shared,
        )
        result.moves.append(Move(inst.namespace, inst.name, inst.deployment, inst.module, inst.robots, inst.node, node.name, why))
    result.placement.instances = [inst for inst in slots if inst is not None]
    result.placement.nodes = _node_summaries(inventory, scheduler.free, result.placement)
    return result


def _node_summaries(inventory: Inventory, free: dict[str, _Free], placement: Placement) -> list[dict]:
    robots = {r for dep in placement.deployments for r in dep["robots"]}
    fleets = {dep["fleet"] for dep in placement.deployments}
    summaries = []
    for node in inventory.nodes.values():
        if node.tier == "onboard" and node.robot not in robots:
            continue
        if node.tier != "onboard" and not any(node.serves_fleet(f) for f in fleets):
            continue
        left = free[node.name]
        summaries.append(
            {
                "name": node.name,
                "tier": node.tier,
                "robot": node.robot,
                "fleet": node.fleet,
                "cpu_millis": node.cpu_millis,
                "memory_bytes": node.memory_bytes,
                "gpu": node.gpu,
                "free_cpu_millis": left.cpu,
                "free_memory_bytes": left.memory,
                "free_gpu": left.gpu,
            }
        )
    return summaries


def placement_table(placement: Placement) -> str:
    """A fixed-width table of where every module of every robot runs, and the discovery servers."""
    header = ("DEPLOYMENT", "ROBOT", "MODULE", "TIER", "NODE", "REASON")
    rows = [(r["deployment"], r["robot"], r["module"], r["tier"], r["node"], r["reason"]) for r in placement.rows()]
    for fleet, servers in placement.discovery.items():
        for s in servers:
            rows.append((f"(fleet {fleet})", "-", s.name, s.tier, s.node, s.reason))
    widths = [max(len(str(row[i])) for row in [header, *rows]) for i in range(len(header) - 1)]
    lines = []
    for row in [header, *rows]:
        cells = [str(cell).ljust(width) for cell, width in zip(row, widths, strict=False)]
        lines.append("  ".join([*cells, str(row[-1])]).rstrip())
    return "\n".join(lines)
