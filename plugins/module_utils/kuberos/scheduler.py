"""The scheduler: placement of every module of every robot, and of each fleet's discovery servers.

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

from . import naming, pool
from .catalog import catalog_problems_against_inventory
from .errors import PlacementError, Problem, SpecError, did_you_mean
from .inventory import Inventory, Node
from .placement import (
    BRIDGE_CPU_MILLIS,
    BRIDGE_MEMORY_BYTES,
    DISCOVERY_CPU_MILLIS,
    DISCOVERY_MEMORY_BYTES,
    BridgeServer,
    DiscoveryServer,
    Instance,
    Placement,
    RobotServer,
    initial_free,
    node_summaries,
    robot_server_hosts,
)
from .spec import RosDeployment, RosModule, name_clash_problems


def _fmt_cpu(millis: int) -> str:
    return f"{millis / 1000:g}"


def _fmt_mem(size: int) -> str:
    return f"{size / 1024**3:.3g}Gi" if size >= 1024**3 else f"{size / 1024**2:.3g}Mi"


class Scheduler:
    """The placer's state during one placement: free capacity per node, ruled-out nodes, and failures."""

    def __init__(self, inventory: Inventory, allocated: dict | None, unavailable: dict[str, str] | None = None):
        self.inventory = inventory
        self.free = initial_free(inventory, allocated)
        self.failures: list[str] = []
        # Nodes nothing may be placed on (e.g. NotReady), and for the instance being placed, nodes it must avoid.
        self.unavailable = dict(unavailable or {})
        self.avoid: dict[str, str] = {}
        # Instances that keep the node they run on (sticky placement): name -> previous Instance, resources taken.
        self.kept: dict[str, Instance] = {}

    @classmethod
    def around(cls, inventory: Inventory, placement: Placement, allocated: dict | None = None, unavailable=None):
        """A scheduler for adding to ``placement``: what its instances and discovery servers hold is taken first
        (``allocated``: what other pods hold)."""
        scheduler = cls(inventory, allocated, unavailable)
        for inst in placement.instances:
            if not inst.cluster and inst.node in scheduler.free:
                scheduler.take(inst.node, inst.cpu_millis, inst.memory_bytes, inst.gpu)
        for server in (s for servers in placement.discovery.values() for s in servers):
            if server.node in scheduler.free:
                scheduler.take(server.node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
        return scheduler

    # -- feasibility -------------------------------------------------------------------------
    def rejection(
        self, node: Node, module: RosModule, robots, cpu: int, memory: int, gpu: int, keeping: bool = False
    ) -> str | None:
        """Why ``node`` cannot run this instance for ``robots``, or None when it can. ``keeping``: the instance runs
        there already, and a robot's computer that is offline keeps what runs on it (docs/connectivity.md): being
        unavailable is no reason to move it, only to place nothing new there."""
        offline_robot = keeping and node.tier == "onboard"
        why = (None if offline_robot else self.unavailable.get(node.name)) or self.avoid.get(node.name)
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
            if req.resource_groups and node.tier != "onboard" and node.resource_group not in req.resource_groups:
                return f"resource group {node.resource_group}, not one of {', '.join(req.resource_groups)}"
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

    # -- robot discovery servers -------------------------------------------------------------
    def take_robot_server(self, dep: RosDeployment, robot: str, node: Node) -> bool:
        """Take room for ``dep``'s discovery server on ``robot``'s computer; a failure naming the field otherwise."""
        why = self.capacity_rejection(node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
        if why is None:
            self.take(node.name, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
            return True
        self.failures.append(
            f"the discovery server of deployment {dep.name} on robot {robot}'s computer "
            f"({_fmt_cpu(DISCOVERY_CPU_MILLIS)} cpu, {_fmt_mem(DISCOVERY_MEMORY_BYTES)}) has no room: free room there, or "
            f"set discovery.robotServers: false in {dep.source} (its onboard modules then meet only through the fleet's "
            f"servers)\n    {node.name} (onboard): {why}"
        )
        return False

    def place_robot_servers(self, deployments: list[RosDeployment], instances: list[Instance]) -> list[RobotServer]:
        """A discovery server on each robot that runs an onboard instance of a deployment that has them, its room
        taken once the modules are placed (a robot without room is a failure that names the way out)."""
        by_name = {d.name: d for d in deployments}
        servers = []
        for (dep, robot), node in robot_server_hosts({d.name for d in deployments if d.uses_robot_servers}, instances).items():
            if self.take_robot_server(by_name[dep], robot, self.inventory.nodes[node]):
                servers.append(RobotServer(dep, robot, node, naming.robot_discovery_server_name(dep, robot)))
        return servers

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


def _keep_previous(scheduler: Scheduler, deployments: list[RosDeployment], targets: dict[str, tuple], previous: Placement):
    """Sticky placement: every instance of ``previous`` that still fits where it runs stays there.

    An instance stays when its deployment and module still exist, it still serves one of the targeted robots, its
    node is in the inventory and available (a robot's computer that is offline counts as available for what already
    runs there), serves the fleet, is of a tier the module may use, meets the module's
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
        if scheduler.rejection(node, module, robots, res.cpu_millis, res.memory_bytes, res.gpu, keeping=True) is not None:
            continue
        scheduler.take(node.name, res.cpu_millis, res.memory_bytes, res.gpu)
        scheduler.kept[inst.name] = _kept_instance(inst, module, robots)


def _kept_discovery(scheduler: Scheduler, previous: Placement | None, fleet: str) -> dict[int, DiscoveryServer]:
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


def check_against_inventory(deployments: list[RosDeployment], inventory: Inventory) -> list[Problem]:
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
                Problem(
                    dep.source, dep.field(path), f"'{robot}' is not a robot of fleet {dep.fleet} ({detail})", dep.line_of(path)
                )
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
    reserved: dict | None = None,
) -> Placement:
    """Place every module instance of every deployment; see the module docstring. Nodes in ``unavailable``
    (node name -> why, e.g. NotReady in the cluster) take nothing; the reason shows in a failure's account.

    ``reserved`` (robot -> ``pool.Reservation``, the ones that hold now): production deployments leave those robots
    out (each deployment's ``left_out`` says why); a development deployment's robots must be its developer's. None
    (a render without a cluster): the pool is not known and not checked.

    ``previous`` is what runs now (the deployments' records and the fleets' live discovery servers): what still
    fits where it runs stays there (see ``_keep_previous``), and a fleet's discovery servers are the fleet's, kept
    on their nodes and never fewer than run now. ``allocated`` must then leave out what ``previous`` holds."""
    problems = check_against_inventory(deployments, inventory)
    if reserved is not None:  # the pool is known (a render without a cluster knows none)
        problems += pool.development_problems(deployments, reserved)
    reserved = reserved or {}
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
        raise SpecError(problems, title="the RosDeployment does not match the inventory or the robot pool")
    scheduler = Scheduler(inventory, allocated, unavailable)
    placement = Placement()
    fleets: dict[str, list[RosDeployment]] = {}
    for dep in deployments:
        fleets.setdefault(dep.fleet, []).append(dep)
    targets = {dep.name: (tuple(sorted(dep.robots)) if dep.robots else inventory.fleets[dep.fleet]) for dep in deployments}
    left_out = {dep.name: pool.left_out(dep, targets[dep.name], reserved) for dep in deployments}
    targets = {name: tuple(r for r in robots if r not in left_out[name]) for name, robots in targets.items()}
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
                **({"left_out": left_out[dep.name]} if left_out[dep.name] else {}),
                **({"developer": dep.developer} if dep.developer else {}),
            }
        )
        for module in dep.modules:
            scheduler.place_module(dep, module, robots, placement.instances)
    placement.robot_servers = scheduler.place_robot_servers(deployments, placement.instances)
    if scheduler.failures:
        raise PlacementError(scheduler.failures)
    placement.nodes = node_summaries(inventory, scheduler.free, placement)
    return placement
