"""The resource model: robots, fleets, edge and cloud machines, and the links between them.

The Ansible inventory is the truth. ``load_inventory`` takes its plain-data form::

    {"hosts": {"fetch-1": {"kuberos_fleet": "test-fleet", "kuberos_cpu": 4, ...}, ...},
     "groups": {"robots": ["fetch-1", ...], "edge": [...], "cloud": [...]}}

and returns an ``Inventory`` or raises ``SpecError`` naming each host, variable and reason.
Host variables are documented in ``docs/inventory.md``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from . import naming, quantities
from .errors import Problem, SpecError, describe, did_you_mean
from .yaml_source import CONTROL_CHARACTERS, control_character_reason

TIER_GROUPS = {"robots": "onboard", "edge": "edge", "cloud": "cloud"}
CLUSTERS_GROUP = "clusters"  # third-party clusters, reached through the KubeROS-Bridge
DEFAULT_BRIDGE_NODE_PORT = naming.BRIDGE_NODE_PORT
# The host variables of the resource model (docs/inventory.md); other kuberos_* variables are site settings.
HOST_VARS = (
    "kuberos_arch", "kuberos_cpu", "kuberos_default_latency_ms", "kuberos_device_parameters", "kuberos_devices",
    "kuberos_fleet", "kuberos_fleets", "kuberos_gpu", "kuberos_latency_ms", "kuberos_link_bandwidth", "kuberos_link_latency_ms",
    "kuberos_link_loss", "kuberos_memory",
    "kuberos_node_name", "kuberos_pods", "kuberos_resource_group", "kuberos_robot", "kuberos_shared",
    # third-party clusters (their API server, CA and token are credentials, never part of the model)
    "kuberos_cluster_domain", "kuberos_bridge_endpoint", "kuberos_bridge_node_port",
)  # fmt: skip
DEFAULT_LATENCY_MS = {"onboard": 0.0, "edge": 5.0, "cloud": 50.0}
_NAME = re.compile(r"[a-z0-9]([-a-z0-9.]*[a-z0-9])?")  # fullmatch: no trailing line break
_LABEL_VALUE = re.compile(r"[A-Za-z0-9]([-A-Za-z0-9_.]*[A-Za-z0-9])?")


def _scalar_text(value) -> str:
    """A parameter value as a launch argument writes it (YAML's true/false for booleans)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


@dataclass(frozen=True)
class Node:
    """A machine that runs modules: a robot's onboard computer, an edge server or a cloud VM."""

    name: str
    tier: str
    cpu_millis: int
    memory_bytes: int
    gpu: int = 0
    pods: int = 110
    arch: str = "amd64"
    devices: frozenset = frozenset()
    # Per device, its parameters (kuberos_device_parameters): ((device, ((name, value), ...)), ...), sorted.
    device_parameters: tuple = ()
    robot: str | None = None
    fleet: str | None = None
    fleets: tuple[str, ...] = ()
    shared: bool = True
    resource_group: str = ""
    latency_ms: float = 0.0
    # Its network link (kuberos_link_bandwidth, kuberos_link_loss): bits per second (None: not limited) and the
    # fraction of packets lost, each way. The lab's links emulate them; the scheduler does not read them.
    link_bps: float | None = None
    link_loss: float = 0.0

    def serves_fleet(self, fleet: str) -> bool:
        if self.tier == "onboard":
            return self.fleet == fleet
        return self.shared or fleet in self.fleets


@dataclass(frozen=True)
class ExternalCluster:
    """A third-party cluster: modules run there unchanged, their topics cross the KubeROS-Bridge."""

    name: str
    latency_ms: float
    fleets: tuple[str, ...] = ()  # fleets that may use it; empty: every fleet
    cluster_domain: str = "cluster.local"
    bridge_endpoint: str = ""  # the main cluster's address, as the third-party cluster reaches it
    bridge_node_port: int = DEFAULT_BRIDGE_NODE_PORT

    def serves_fleet(self, fleet: str) -> bool:
        return not self.fleets or fleet in self.fleets


@dataclass(frozen=True)
class Robot:
    name: str
    fleet: str
    node: str
    link_latency_ms: tuple[tuple[str, float], ...] = ()


class Inventory:
    """Nodes, robots and fleets with the latency between each robot and each node."""

    def __init__(self, nodes: dict[str, Node], robots: dict[str, Robot], clusters: dict[str, ExternalCluster] | None = None):
        self.clusters = dict(sorted((clusters or {}).items()))
        self.nodes = dict(sorted(nodes.items()))
        self.robots = dict(sorted(robots.items()))
        fleets: dict[str, list[str]] = {}
        for robot in self.robots.values():
            fleets.setdefault(robot.fleet, []).append(robot.name)
        self.fleets = {name: tuple(sorted(members)) for name, members in sorted(fleets.items())}
        self._links = {robot.name: dict(robot.link_latency_ms) for robot in self.robots.values()}
        self._by_tier: dict[str, list[Node]] = {"onboard": [], "edge": [], "cloud": []}
        for node in self.nodes.values():
            self._by_tier[node.tier].append(node)
        self._tiers: dict[tuple[str, str], tuple[Node, ...]] = {}

    def latency_ms(self, robot: str, node: str) -> float:
        """One-way-agnostic network latency between a robot and a node, in milliseconds."""
        target = self.nodes[node]
        own = self.robots[robot].node
        if node == own:
            return 0.0
        override = self._links[robot].get(node)
        if override is not None:
            return override
        if target.tier == "onboard":
            return math.inf
        return target.latency_ms

    def with_measured_latency(self, measured: dict[str, dict[str, float]]) -> Inventory:
        """A copy in which measured robot-to-node round-trip times replace the configured latencies."""
        robots = {}
        for name, robot in self.robots.items():
            links = dict(robot.link_latency_ms)
            links.update({node: float(ms) for node, ms in measured.get(name, {}).items() if node in self.nodes})
            robots[name] = Robot(robot.name, robot.fleet, robot.node, tuple(sorted(links.items())))
        return Inventory(self.nodes, robots, self.clusters)

    def with_nodes(self, extra) -> Inventory:
        """A copy with ``extra`` nodes added (those already known are kept as they are): edge and cloud nodes that
        joined the cluster after deploy, such as cloud VMs provisioned for a peak (``labels.node_from_cluster``)."""
        added = {n.name: n for n in extra if n.name not in self.nodes and n.tier != "onboard"}
        if not added:
            return self
        return Inventory({**self.nodes, **added}, self.robots, self.clusters)

    def tier_nodes(self, tier: str, fleet: str) -> tuple[Node, ...]:
        """Edge or cloud nodes the fleet may use, by name."""
        key = (tier, fleet)
        if key not in self._tiers:
            self._tiers[key] = tuple(n for n in self._by_tier[tier] if n.serves_fleet(fleet))
        return self._tiers[key]


def _host_problem(source, host, var, message):
    return Problem(source, f"hosts.{host}.{var}" if var else f"hosts.{host}", message)


def _parse_number(value, parser, source, host, var, problems, default=None):
    if value is None:
        if default is None:
            problems.append(_host_problem(source, host, var, "is required; " + _EXPECTED[parser]))
            return 0
        value = default
    try:
        return _quantity(parser, value)
    except ValueError as exc:
        problems.append(_host_problem(source, host, var, f"{describe(value)} is not valid; {exc}"))
        return 0


def _quantity(parser, value):
    """``parser(value)``, a finite amount: ``ValueError`` saying what is expected also for a number beyond a float's
    range (400 digits, which the parser reads as infinity or cannot convert)."""
    try:
        amount = parser(value)
    except OverflowError:
        amount = math.inf
    if isinstance(amount, float) and not math.isfinite(amount):
        raise ValueError(_EXPECTED[parser])
    return amount


_EXPECTED = {
    quantities.parse_cpu: quantities.CPU_EXPECTED,
    quantities.parse_memory: quantities.MEMORY_EXPECTED,
    quantities.parse_latency_ms: quantities.LATENCY_EXPECTED,
    quantities.parse_bandwidth_bps: quantities.BANDWIDTH_EXPECTED,
    quantities.parse_loss_fraction: quantities.LOSS_EXPECTED,
}


def _count(value, source, host, var, problems, default):
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        if isinstance(value, str) and value.isdigit():
            return int(value)
        problems.append(_host_problem(source, host, var, f"{describe(value)} is not valid; expected a whole number >= 0"))
        return default
    return value


def _string_list(value, source, host, var, problems) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) and v for v in value):
        problems.append(_host_problem(source, host, var, f"{describe(value)} is not valid; expected a list of names"))
        return ()
    return tuple(value)


def _name(value, source, host, var, problems, what):
    if not isinstance(value, str) or not _NAME.fullmatch(value) or len(value) > 63:
        problems.append(
            _host_problem(
                source,
                host,
                var,
                f"{describe(value)} is not valid; expected a {what} of lowercase letters, digits, '-' and '.'",
            )
        )
    return str(value)


def _groups(groups, source, problems) -> dict[str, frozenset]:
    """The members of robots, edge and cloud as sets of host names."""
    if not isinstance(groups, dict):
        problems.append(Problem(source, "groups", f"{describe(groups)} is not valid; expected a mapping of group names to hosts"))
        groups = {}
    members = {}
    for group in TIER_GROUPS:
        names = groups.get(group) or []
        if not isinstance(names, (list, tuple)):
            problems.append(Problem(source, f"groups.{group}", f"{describe(names)} is not valid; expected a list of host names"))
            names = []
        for index, name in enumerate(names):
            if not isinstance(name, str) or not name:
                problems.append(
                    Problem(source, f"groups.{group}[{index}]", f"{describe(name)} is not valid; expected a host name")
                )
        members[group] = frozenset(n for n in names if isinstance(n, str) and n)
    return members


def _tier_of(host, groups, source, problems):
    names = [group for group in TIER_GROUPS if host in groups[group]]
    if len(names) > 1:
        problems.append(
            _host_problem(source, host, "", f"is in groups {', '.join(names)}; expected exactly one of robots, edge, cloud")
        )
    return TIER_GROUPS[names[0]]


def _control_character_problems(raw: dict, source: str, limit: int = 20) -> list[Problem]:
    """Host names, group members and variable values (keys and strings at any depth) holding a control character
    (``yaml_source.CONTROL_CHARACTERS``; Ansible reads an escape such as "\\x00" in a quoted YAML string)."""
    problems: list[Problem] = []
    stack = [
        (raw.get("hosts"), "hosts"),
        (raw.get("groups"), "groups"),
        (raw.get("default_latency_ms"), "kuberos_default_latency_ms"),
    ]
    while stack and len(problems) < limit:
        node, path = stack.pop()
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, (list, tuple)) else ()
        for key, value in items:
            where = f"{path}[{key}]" if isinstance(key, int) else f"{path}.{ascii(key)[1:-1] if isinstance(key, str) else key}"
            for text in (key, value):
                found = CONTROL_CHARACTERS.search(text) if isinstance(text, str) else None
                if found:
                    problems.append(Problem(source, where, control_character_reason(found.group())))
                    break
            else:
                stack.append((value, where))
    return problems


def model_groups(groups: dict) -> dict[str, list[str]]:
    """The groups of the resource model (tiers, and third-party clusters when there are any), sorted."""
    members = {group: sorted(groups.get(group) or []) for group in TIER_GROUPS}
    if groups.get(CLUSTERS_GROUP):
        members[CLUSTERS_GROUP] = sorted(groups[CLUSTERS_GROUP])
    return members


def raw_inventory(groups: dict, hostvars) -> dict:
    """The plain-data form ``load_inventory`` reads, from an inventory's groups (name -> host names, every
    descendant's hosts included) and its hosts' variables (host -> variables; only the resource model's are read,
    so a lazy mapping is asked for nothing else)."""
    members = model_groups(groups)
    hosts = {}
    defaults = {}
    for host in sorted({h for names in members.values() for h in names}):
        host_vars = hostvars[host]
        hosts[host] = {key: host_vars[key] for key in HOST_VARS if key in host_vars}
        defaults = hosts[host].pop("kuberos_default_latency_ms", defaults) or defaults
    return {"hosts": hosts, "groups": members, "default_latency_ms": defaults}


def _latency_defaults(raw: dict, source: str, problems: list[Problem]) -> dict[str, float]:
    """Each tier's latency to the robots (``kuberos_default_latency_ms``) over the built-in defaults."""
    defaults = dict(DEFAULT_LATENCY_MS)
    given = raw.get("default_latency_ms") or {}
    if not isinstance(given, dict):
        problems.append(
            Problem(
                source,
                "kuberos_default_latency_ms",
                f"{describe(given)} is not valid; expected a mapping of tier to latency, e.g. {{edge: 5, cloud: 40}}",
            )
        )
        given = {}
    for tier, value in given.items():
        if tier not in defaults:
            problems.append(
                Problem(
                    source,
                    f"kuberos_default_latency_ms.{tier}",
                    f"unknown tier{did_you_mean(tier, defaults)}; expected onboard, edge or cloud",
                )
            )
            continue
        try:
            defaults[tier] = _quantity(quantities.parse_latency_ms, value)
        except ValueError as exc:
            problems.append(Problem(source, f"kuberos_default_latency_ms.{tier}", f"{describe(value)} is not valid; {exc}"))
    return defaults


class _Loader:
    """One reading of an inventory: every host becomes a node (robots also a robot), every problem collected."""

    def __init__(self, source: str, groups: dict, defaults: dict, problems: list[Problem]):
        self.source = source
        self.groups = groups
        self.defaults = defaults
        self.problems = problems
        self.nodes: dict[str, Node] = {}
        self.robots: dict[str, Robot] = {}
        self.links: dict[str, tuple[str, dict]] = {}
        self.host_to_node: dict[str, str] = {}

    def problem(self, host: str, var: str, message: str) -> None:
        self.problems.append(_host_problem(self.source, host, var, message))

    def capacity(self, host: str, hv: dict) -> dict:
        """The node fields every tier has: name, tier, CPU, memory, GPUs, pods, architecture and devices."""
        source, problems = self.source, self.problems
        tier = _tier_of(host, self.groups, source, problems)
        node_name = _name(hv.get("kuberos_node_name", host), source, host, "kuberos_node_name", problems, "node name")
        if node_name in self.nodes:
            self.problem(
                host, "kuberos_node_name", f"'{node_name}' is already the node name of another host; expected unique node names"
            )
        self.host_to_node[host] = node_name
        cpu = _parse_number(hv.get("kuberos_cpu"), quantities.parse_cpu, source, host, "kuberos_cpu", problems)
        memory = _parse_number(hv.get("kuberos_memory"), quantities.parse_memory, source, host, "kuberos_memory", problems)
        gpu = _count(hv.get("kuberos_gpu"), source, host, "kuberos_gpu", problems, 0)
        for var, amount in (("kuberos_cpu", cpu), ("kuberos_memory", memory)):
            if amount == 0 and hv.get(var) is not None and not any(p.path == f"hosts.{host}.{var}" for p in problems):
                self.problem(host, var, "must be more than zero")
        pods = _count(hv.get("kuberos_pods"), source, host, "kuberos_pods", problems, 110)
        arch = hv.get("kuberos_arch", "amd64")
        if not isinstance(arch, str) or not _LABEL_VALUE.fullmatch(arch):
            self.problem(host, "kuberos_arch", f"{describe(arch)} is not valid; expected e.g. amd64 or arm64")
        devices = _string_list(hv.get("kuberos_devices"), source, host, "kuberos_devices", problems)
        for device in devices:
            if not _NAME.fullmatch(device):
                self.problem(
                    host, "kuberos_devices",
                    f"{describe(device)} is not valid; expected device names of lowercase letters, digits and '-'",
                )  # fmt: skip
        parameters = self.device_parameters(host, hv.get("kuberos_device_parameters"), devices)
        bandwidth = hv.get("kuberos_link_bandwidth")
        if bandwidth is not None:
            bandwidth = _parse_number(bandwidth, quantities.parse_bandwidth_bps, source, host, "kuberos_link_bandwidth", problems)
        loss = _parse_number(
            hv.get("kuberos_link_loss"), quantities.parse_loss_fraction, source, host, "kuberos_link_loss", problems, default=0
        )  # fmt: skip
        return dict(
            name=node_name, tier=tier, cpu_millis=cpu, memory_bytes=memory, gpu=gpu, pods=pods, arch=str(arch),
            devices=frozenset(devices), device_parameters=parameters, link_bps=bandwidth or None, link_loss=loss,
        )  # fmt: skip

    def device_parameters(self, host: str, raw, devices: list) -> tuple:
        """kuberos_device_parameters: a mapping of the host's devices to mappings of parameter names to scalars."""
        var = "kuberos_device_parameters"
        if raw is None:
            return ()
        if not isinstance(raw, dict):
            self.problem(host, var, f"{describe(raw)} is not valid; expected a mapping of device names to parameters")
            return ()
        out = []
        for device, params in raw.items():
            if device not in devices:
                self.problem(
                    host, f"{var}.{device}",
                    f"names a device the host does not carry; expected one of kuberos_devices ({', '.join(devices) or 'none'})",
                )  # fmt: skip
                continue
            if not isinstance(params, dict) or not all(
                isinstance(k, str) and k and isinstance(v, (str, int, float, bool)) for k, v in params.items()
            ):
                self.problem(
                    host, f"{var}.{device}", f"{describe(params)} is not valid; expected a mapping of parameter names to values"
                )
                continue
            out.append((device, tuple(sorted((k, _scalar_text(v)) for k, v in params.items()))))
        return tuple(sorted(out))

    def robot(self, host: str, hv: dict, common: dict) -> None:
        """A robot's own computer: an onboard node of its fleet, and the robot with its link overrides."""
        robot = _name(hv.get("kuberos_robot", host), self.source, host, "kuberos_robot", self.problems, "robot name")
        fleet = hv.get("kuberos_fleet")
        if fleet is None:
            self.problem(host, "kuberos_fleet", "is required for a robot; expected the name of its fleet")
        else:
            fleet = _name(fleet, self.source, host, "kuberos_fleet", self.problems, "fleet name")
        if robot in self.robots:
            self.problem(host, "kuberos_robot", f"'{robot}' names another robot already; expected unique robot names")
        name = common["name"]
        self.nodes[name] = Node(**common, robot=robot, fleet=fleet, shared=False, resource_group=str(fleet), latency_ms=0.0)
        self.robots[robot] = Robot(robot, str(fleet), name)
        link = hv.get("kuberos_link_latency_ms") or {}
        if not isinstance(link, dict):
            self.problem(
                host, "kuberos_link_latency_ms", f"{describe(link)} is not valid; expected a mapping of node names to latencies"
            )
            link = {}
        self.links[robot] = (host, link)

    def site_node(self, host: str, hv: dict, common: dict) -> None:
        """An edge server or cloud VM: the fleets it serves, whether it is shared, its latency and resource group."""
        tier = common["tier"]
        fleets = _string_list(hv.get("kuberos_fleets"), self.source, host, "kuberos_fleets", self.problems)
        shared = hv.get("kuberos_shared", not fleets)
        if not isinstance(shared, bool):
            self.problem(host, "kuberos_shared", f"{describe(shared)} is not valid; expected true or false")
            shared = False
        latency = _parse_number(
            hv.get("kuberos_latency_ms"), quantities.parse_latency_ms, self.source, host, "kuberos_latency_ms",
            self.problems, default=self.defaults[tier],
        )  # fmt: skip
        group = hv.get("kuberos_resource_group", tier)
        if not isinstance(group, str) or not _LABEL_VALUE.fullmatch(group):
            self.problem(
                host, "kuberos_resource_group",
                f"{describe(group)} is not valid; expected a name of letters, digits, '-', '_' and '.'",
            )  # fmt: skip
        self.nodes[common["name"]] = Node(**common, fleets=fleets, shared=shared, resource_group=str(group), latency_ms=latency)

    def host(self, host: str, hv) -> None:
        if not isinstance(hv, dict):
            self.problem(host, "", f"{describe(hv)} is not valid; expected a mapping of variables")
            return
        common = self.capacity(host, hv)
        if common["tier"] == "onboard":
            self.robot(host, hv, common)
        else:
            self.site_node(host, hv, common)

    def check_fleets(self, known_fleets: set) -> None:
        """Every fleet a server names is a fleet of some robot."""
        for node in self.nodes.values():
            for fleet in node.fleets:
                if fleet not in known_fleets:
                    host = next(h for h, n in self.host_to_node.items() if n == node.name)
                    self.problem(
                        host, "kuberos_fleets", f"'{fleet}' is not a fleet of any robot{did_you_mean(fleet, known_fleets)}"
                    )

    def resolved_robots(self) -> dict[str, Robot]:
        """The robots with their link overrides (``kuberos_link_latency_ms``) named by node."""
        resolved: dict[str, Robot] = {}
        for name, robot in self.robots.items():
            host, link = self.links[name]
            overrides = []
            for target, value in sorted(link.items(), key=lambda kv: str(kv[0])):
                node_name = self.host_to_node.get(target, target)
                var = f"kuberos_link_latency_ms.{target}"
                if node_name not in self.nodes:
                    known = list(self.host_to_node) + list(self.nodes)
                    self.problem(host, var, f"is not a host or node in the inventory{did_you_mean(target, known)}")
                    continue
                try:
                    overrides.append((node_name, _quantity(quantities.parse_latency_ms, value)))
                except ValueError as exc:
                    self.problem(host, var, f"{describe(value)} is not valid; {exc}")
            resolved[name] = Robot(robot.name, robot.fleet, robot.node, tuple(overrides))
        return resolved


def load_inventory(raw: dict, source: str = "inventory") -> Inventory:
    """Build the resource model from inventory data; every problem at once."""
    problems: list[Problem] = []
    if not isinstance(raw, dict):
        raise SpecError([Problem(source, "", f"{describe(raw)} is not an inventory; expected a mapping with hosts and groups")])
    control = _control_character_problems(raw, source)
    if control:
        raise SpecError(control, title=f"{source} is not a valid KubeROS inventory")
    hosts = raw.get("hosts") or {}
    if not isinstance(hosts, dict):
        problems.append(
            Problem(source, "hosts", f"{describe(hosts)} is not valid; expected a mapping of host names to variables")
        )
        hosts = {}
    groups = _groups(raw.get("groups") or {}, source, problems)
    defaults = _latency_defaults(raw, source, problems)
    members = sorted({h for g in TIER_GROUPS for h in groups[g]})
    if not members:
        problems.append(Problem(source, "groups", "no hosts in the groups robots, edge or cloud; expected at least one robot"))
    loader = _Loader(source, groups, defaults, problems)
    for host in members:
        loader.host(host, hosts.get(host) or {})
    known_fleets = {r.fleet for r in loader.robots.values()}
    loader.check_fleets(known_fleets)
    robots = loader.resolved_robots()
    clusters = _clusters(raw, hosts, source, defaults, known_fleets, set(loader.nodes), problems)
    if problems:
        raise SpecError(problems, title=f"{source} is not a valid KubeROS inventory")
    return Inventory(loader.nodes, robots, clusters)


def _clusters(raw, hosts, source, defaults, known_fleets, node_names, problems) -> dict[str, ExternalCluster]:
    """The hosts of the group ``clusters``: third-party clusters and how the bridge reaches them."""
    names = (raw.get("groups") or {}).get(CLUSTERS_GROUP) if isinstance(raw.get("groups"), dict) else None
    if names is None:
        return {}
    if not isinstance(names, (list, tuple)):
        problems.append(Problem(source, f"groups.{CLUSTERS_GROUP}", f"{describe(names)} is not valid; expected a list of names"))
        return {}
    clusters = {}
    for index, host in enumerate(names):
        if not isinstance(host, str) or not host:
            problems.append(
                Problem(source, f"groups.{CLUSTERS_GROUP}[{index}]", f"{describe(host)} is not valid; expected a host name")
            )
            continue
        hv = hosts.get(host) or {}
        if not isinstance(hv, dict):
            problems.append(_host_problem(source, host, "", f"{describe(hv)} is not valid; expected a mapping of variables"))
            continue
        name = _name(host, source, host, "", problems, "cluster name")
        if name in node_names:
            problems.append(_host_problem(source, host, "", "is also a node; expected a cluster name that is not a node"))
        latency = _parse_number(
            hv.get("kuberos_latency_ms"),
            quantities.parse_latency_ms,
            source,
            host,
            "kuberos_latency_ms",
            problems,
            defaults["cloud"],
        )
        fleets = _string_list(hv.get("kuberos_fleets"), source, host, "kuberos_fleets", problems)
        for fleet in fleets:
            if fleet not in known_fleets:
                message = f"'{fleet}' is not a fleet of any robot{did_you_mean(fleet, known_fleets)}"
                problems.append(_host_problem(source, host, "kuberos_fleets", message))
        endpoint = hv.get("kuberos_bridge_endpoint", "")
        if not isinstance(endpoint, str) or not endpoint or any(c.isspace() for c in endpoint):
            problems.append(
                _host_problem(
                    source, host, "kuberos_bridge_endpoint",
                    f"{describe(endpoint)} is not valid; expected the address (host name or IP) at which this cluster reaches "
                    "the main cluster's bridge servers",
                )
            )  # fmt: skip
        port = hv.get("kuberos_bridge_node_port", DEFAULT_BRIDGE_NODE_PORT)
        if isinstance(port, bool) or not isinstance(port, int) or not 30000 <= port <= 32767:
            problems.append(
                _host_problem(
                    source,
                    host,
                    "kuberos_bridge_node_port",
                    f"{describe(port)} is not valid; expected a NodePort from 30000 to 32767",
                )
            )
            port = DEFAULT_BRIDGE_NODE_PORT
        domain = _name(
            hv.get("kuberos_cluster_domain", "cluster.local"), source, host, "kuberos_cluster_domain", problems, "DNS domain"
        )
        clusters[name] = ExternalCluster(name, latency, tuple(fleets), domain, str(endpoint), int(port))
    return clusters
