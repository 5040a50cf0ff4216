"""The placement model: where every instance of every module runs, each fleet's discovery servers and bridge
servers, the capacity left on every node, and the moves and stranded instances of a re-placement (pure data).

``Placement.to_dict``/``from_dict`` are its plain-data form (a record, a filter's result, placement.json).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from . import naming, quantities
from .errors import Problem, SpecError
from .inventory import Inventory

DISCOVERY_CPU_MILLIS = 100
DISCOVERY_MEMORY_BYTES = 64 * 1024**2
BRIDGE_CPU_MILLIS = 200
BRIDGE_MEMORY_BYTES = 256 * 1024**2
PLACEMENT_API_VERSION = "kuberos.io/v1alpha1"


@dataclass
class Free:
    """What is left on a node: CPU millicores, memory bytes, GPUs and pod slots."""

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


@dataclass(frozen=True)
class RobotServer:
    """A deployment's discovery server on one robot's computer (its onboard modules list it after the fleet's)."""

    deployment: str
    robot: str
    node: str
    name: str


@dataclass
class Placement:
    instances: list[Instance] = field(default_factory=list)
    discovery: dict[str, list[DiscoveryServer]] = field(default_factory=dict)
    deployments: list[dict] = field(default_factory=list)
    # Nodes the deployments could use, with capacity and what is left free after this placement.
    nodes: list[dict] = field(default_factory=list)
    bridges: dict[str, list[BridgeServer]] = field(default_factory=dict)  # fleet -> its bridge servers
    robot_servers: list[RobotServer] = field(default_factory=list)  # the deployments' servers on robots' computers

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

    def pinned(self) -> dict[str, str]:
        """Deployment name -> node of every pod KubeROS pins here: module instances (not those of third-party
        clusters), the fleets' discovery servers and the robots' own."""
        where = {i.name: i.node for i in self.instances if not i.cluster}
        where.update({s.name: s.node for servers in self.discovery.values() for s in servers})
        where.update({r.name: r.node for r in self.robot_servers})
        return where

    def on_node(self, node: str) -> list[str]:
        """What this placement runs on ``node``, by name: module instances (of this cluster), the fleets' discovery
        and bridge servers, the robots' own servers. Removing the node needs a pass of every deployment whose
        placement names one (a fleet's servers are in every record of the fleet)."""
        names = [name for name, where in self.pinned().items() if where == node]
        names += [b.name for servers in self.bridges.values() for b in servers if b.node == node]
        return sorted(set(names))

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
            "robot_discovery": [asdict(r) for r in self.robot_servers],
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
            robot_servers = [RobotServer(**entry) for entry in data.get("robot_discovery", [])]  # none before they existed
        except (KeyError, TypeError) as exc:
            raise SpecError([Problem("placement", "", f"not a placement produced by place_modules ({exc!r})")]) from None
        return cls(instances, discovery, list(data.get("deployments", [])), list(data.get("nodes", [])), bridges, robot_servers)


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


def initial_free(inventory: Inventory, allocated: dict | None) -> dict[str, Free]:
    free = {n.name: Free(n.cpu_millis, n.memory_bytes, n.gpu, n.pods) for n in inventory.nodes.values()}
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


def robot_server_hosts(uses_robot_servers: set[str] | frozenset[str], instances: list[Instance]) -> dict[tuple[str, str], str]:
    """(deployment, robot) -> the robot's computer, for each robot that runs an onboard instance of a deployment in
    ``uses_robot_servers``: where that deployment's robot discovery servers run (one per robot)."""
    hosts = {}
    for inst in instances:
        if inst.deployment in uses_robot_servers and inst.tier == "onboard" and not inst.cluster and len(inst.robots) == 1:
            hosts[(inst.deployment, inst.robots[0])] = inst.node
    return dict(sorted(hosts.items()))


def node_summaries(inventory: Inventory, free: dict[str, Free], placement: Placement) -> list[dict]:
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
