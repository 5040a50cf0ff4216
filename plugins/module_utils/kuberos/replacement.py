"""Re-placement: what the controller moves when a node fails, a pod keeps failing or a link degrades (pure).

``replace_modules`` keeps every instance of a previous placement where it is unless its node is ruled out, and moves
only those, with the scheduler's own rules (``scheduler.Scheduler``).
"""

from __future__ import annotations

from .errors import SpecError
from .inventory import Inventory
from .placement import (
    DISCOVERY_CPU_MILLIS,
    DISCOVERY_MEMORY_BYTES,
    DiscoveryServer,
    Instance,
    Move,
    Placement,
    Replacement,
    Stranded,
    node_summaries,
)
from .scheduler import Scheduler, check_against_inventory
from .spec import RosDeployment, RosModule


class _Replacer:
    """One re-placement: what stays keeps its resources first, then what leaves goes to the best other node."""

    def __init__(self, deployments, inventory, previous, allocated, unavailable, avoid, hold):
        self.inventory = inventory
        self.previous = previous
        self.avoid = avoid or {}
        self.hold = hold
        self.scheduler = Scheduler(inventory, allocated, unavailable)
        self.modules = {(d.name, m.name): (d, m) for d in deployments for m in d.modules}
        self.result = Replacement(
            Placement(
                deployments=list(previous.deployments), bridges=dict(previous.bridges),
                robot_servers=list(previous.robot_servers),  # on robots' computers: never moved
            )
        )  # fmt: skip
        self.kept_discovery: dict[str, dict[int, DiscoveryServer]] = {}
        self.leaving_discovery: dict[str, dict[int, tuple[DiscoveryServer, str]]] = {}
        self.slots: list[Instance | None] = []  # the previous instances in order; None where one leaves
        self.leaving: list[tuple[int, Instance, str]] = []

    def ruled_out(self, name: str, node: str, module: RosModule | None, robots) -> str | None:
        """Why an instance may not stay on its node, or None."""
        if name in self.hold and node in self.inventory.nodes:
            return None
        if node not in self.inventory.nodes:
            return f"node {node} is no longer in the inventory"
        why = self.scheduler.unavailable.get(node) or self.avoid.get(name, {}).get(node)
        if why:
            return why
        return self.scheduler.requirement_rejection(self.inventory.nodes[node], module, robots)

    def keep_what_stays(self) -> None:
        for fleet, servers in self.previous.discovery.items():
            for server in servers:
                why = self.ruled_out(server.name, server.node, None, ())
                if why is None:
                    self.kept_discovery.setdefault(fleet, {})[server.server_id] = server
                    self.scheduler.take(server.node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
                else:
                    self.leaving_discovery.setdefault(fleet, {})[server.server_id] = (server, why)
        for inst in self.previous.instances:
            found = self.modules.get((inst.deployment, inst.module))
            if found is None:
                continue  # the module is gone from the spec: deploying again prunes it, moving is not our job
            if inst.cluster:
                self.slots.append(inst)  # a third-party cluster places it on its own nodes
                continue
            why = self.ruled_out(inst.name, inst.node, found[1], inst.robots)
            if why is None:
                self.slots.append(inst)
                if inst.node in self.scheduler.free:
                    self.scheduler.take(inst.node, inst.cpu_millis, inst.memory_bytes, inst.gpu)
            else:
                self.leaving.append((len(self.slots), inst, why))
                self.slots.append(None)

    def move_discovery(self, fleet: str, servers: list[DiscoveryServer]) -> list[DiscoveryServer]:
        moving = self.leaving_discovery.get(fleet, {})
        if not moving:
            return servers
        placed = self.scheduler.place_discovery(fleet, len(servers), servers[0].port, self.kept_discovery.get(fleet, {}))
        self.scheduler.failures.clear()
        by_id = {s.server_id: s for s in placed}
        final = []
        for server in servers:
            new = by_id.get(server.server_id)
            if server.server_id in moving and new is not None:
                why = moving[server.server_id][1]
                new = DiscoveryServer(
                    new.fleet, new.namespace, new.server_id, new.name, new.node, new.tier, new.port,
                    f"moved from {server.node} ({why}); {new.reason}",
                )  # fmt: skip
                self.result.moves.append(Move(new.namespace, new.name, "", "discovery-server", (), server.node, new.node, why))
            elif server.server_id in moving:
                new = server
                self.scheduler.take(server.node, DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, 0)
                self.result.stranded.append(
                    Stranded(
                        server.namespace, server.name, "", "discovery-server", (), server.node,
                        f"{moving[server.server_id][1]}; no other node",
                    )
                )  # fmt: skip
            final.append(new)
        return final

    def move_instance(self, index: int, inst: Instance, why: str) -> None:
        dep, module = self.modules[(inst.deployment, inst.module)]
        res = module.resources
        self.scheduler.avoid = dict(self.avoid.get(inst.name, {}))
        self.scheduler.avoid.setdefault(inst.node, why)
        node, tier, latency, detail = self.scheduler.choose(dep, module, inst.robots)
        self.scheduler.avoid = {}
        if node is None:
            if inst.node in self.scheduler.free:
                self.scheduler.take(inst.node, inst.cpu_millis, inst.memory_bytes, inst.gpu)
            stay = "onboard modules stay with their robot" if module.requirements.onboard else "no other feasible node"
            accounts = [a for a in detail if not a.startswith(f"{inst.node} ")]
            self.result.stranded.append(
                Stranded(
                    inst.namespace, inst.name, inst.deployment, inst.module, inst.robots, inst.node,
                    "; ".join([why, stay, *accounts[:5]]),
                )
            )  # fmt: skip
            self.slots[index] = inst
            return
        self.slots[index] = Instance(
            inst.name, inst.deployment, inst.fleet, inst.namespace, inst.module, node.name, tier, inst.robots,
            f"moved from {inst.node} ({why}); {detail}", latency, res.cpu_millis, res.memory_bytes, res.gpu, inst.shared,
        )  # fmt: skip
        self.result.moves.append(
            Move(inst.namespace, inst.name, inst.deployment, inst.module, inst.robots, inst.node, node.name, why)
        )

    def run(self) -> Replacement:
        # 1. What stays keeps its resources before anything moves.
        self.keep_what_stays()
        # 2. Discovery servers, then module instances, go to the best other node.
        for fleet, servers in self.previous.discovery.items():
            self.result.placement.discovery[fleet] = self.move_discovery(fleet, servers)
        for index, inst, why in self.leaving:
            self.move_instance(index, inst, why)
        self.result.placement.instances = [inst for inst in self.slots if inst is not None]
        self.result.placement.nodes = node_summaries(self.inventory, self.scheduler.free, self.result.placement)
        return self.result


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
    problems = check_against_inventory(deployments, inventory)
    if problems:
        raise SpecError(problems, title="the RosDeployment does not match the inventory")
    return _Replacer(deployments, inventory, previous, allocated, unavailable, avoid, hold).run()
