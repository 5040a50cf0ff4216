"""A site described in the reference KubeROS format (kuberos-io), imported as an inventory of this collection.

The reference implementation describes a site with two YAML kinds: one ``ClusterInventory`` (the cluster's machines:
their role, the robot each onboard computer sits in, the devices attached with their parameters) and ``Fleet``
documents (the robots of each fleet). ``import_site`` turns them into the Ansible inventory ``docs/inventory.md``
describes (groups robots, edge, cloud and control_plane, ``kuberos_*`` host variables) and lists, as notes, what the
reference format does not say (CPU and memory: placeholders are written) and what was left out. ``import_files``
reads the files (through ``yaml_source``: bounded, checked, every field's line remembered) and ``ImportedSite.text``
is the inventory file. Bad input raises ``SpecError`` naming file, line, field and reason, every problem at once.
The mapping, field by field, is in docs/inventory.md ("Importing a reference KubeROS site").
"""

from __future__ import annotations

import ipaddress
import math
import re
import textwrap
from dataclasses import dataclass, field

from . import quantities
from .errors import Problem, SpecError, describe, did_you_mean, printable
from .inventory import load_inventory, raw_inventory
from .third_party import require, yaml
from .yaml_source import Document, format_path, load_documents, read_text

API_VERSION = "v1alpha"
CLUSTER_KIND = "ClusterInventory"
FLEET_KIND = "Fleet"
# kuberosRole -> the inventory groups of such a host (the first is its tier group).
ROLE_GROUPS = {
    "onboard": ("robots",),
    "control-plane": ("edge", "control_plane"),
    "edge": ("edge",),
    "cloud": ("cloud",),
}
# Placeholders for what the reference format does not say; the notes and the file's comments say so.
DEFAULT_CPU = {"onboard": 2, "control-plane": 4, "edge": 8, "cloud": 8}
DEFAULT_MEMORY = {"onboard": "4Gi", "control-plane": "8Gi", "edge": "16Gi", "cloud": "32Gi"}
DEFAULT_SHARED = False  # the reference's default: an edge or cloud machine without ``shared`` serves no fleet
HEADER = "# Imported from a reference KubeROS site (a ClusterInventory, Fleets) by kuberos.platform.reference_inventory_import."
GROUP_ORDER = ("robots", "edge", "cloud", "control_plane")

_TOP_FIELDS = {CLUSTER_KIND: ("apiVersion", "kind", "metadata", "hosts"), FLEET_KIND: ("apiVersion", "kind", "metadata", "robot")}
_METADATA_FIELDS = {CLUSTER_KIND: ("clusterName",), FLEET_KIND: ("name", "description", "mainCluster")}
_HOST_FIELDS = (
    "hostname", "alias", "accessIp", "kuberosRole", "onboardComputerGroup", "locatedInRobot", "peripheralDevices",
    "shared", "resourceGroup",
)  # fmt: skip
_ROBOT_FIELDS = ("name", "robotId")
_DEVICE_FIELDS = ("deviceName", "parameter")
_NAME = re.compile(r"[a-z0-9]([-a-z0-9.]*[a-z0-9])?")  # as the inventory's names (inventory.py)
_GROUP_NAME = re.compile(r"[A-Za-z0-9]([-A-Za-z0-9_.]*[A-Za-z0-9])?")  # a label value (kuberos_resource_group)
_DNS_NAME = re.compile(r"[A-Za-z0-9]([-A-Za-z0-9.]*[A-Za-z0-9])?")
_PARAMETER_NAME = re.compile(r"[^\s]+")
_NAME_EXPECTED = "lowercase letters, digits, '-' and '.', starting and ending with a letter or digit, at most 63 characters"


@dataclass
class Device:
    name: str
    parameters: dict


@dataclass
class Host:
    """One host of the ClusterInventory, checked."""

    index: int
    name: str
    role: str
    address: str | None = None
    alias: str | None = None
    computer_group: str | None = None
    robot: str | None = None
    robot_id: object = None
    devices: list[Device] = field(default_factory=list)
    shared: bool | None = None
    resource_group: str | None = None

    @property
    def where(self) -> str:
        return f"hosts[{self.index}] ({self.name})"


@dataclass
class Fleet:
    name: str
    description: str
    main_cluster: str | None
    robots: list[str]
    doc: Document

    @property
    def source(self) -> str:
        return self.doc.source


@dataclass
class ImportedSite:
    """The inventory (Ansible's YAML inventory structure), the notes for the user, and what the file says about it."""

    inventory: dict
    notes: list[str]
    comments: dict  # host -> a comment for its line (what the reference said that has no variable)
    placeholders: dict  # host -> the variables that hold placeholders
    cluster_name: str = ""
    sources: tuple = ()  # (what, display) of the files read, for the header
    fleets: tuple = ()  # (name, description, source)

    @property
    def hosts(self) -> dict:
        """Host name -> its variables (a host in two groups appears once, with its variables)."""
        found: dict = {}
        for group in self.inventory["all"]["children"].values():
            for name, variables in group["hosts"].items():
                if variables or name not in found:
                    found[name] = variables
        return found

    @property
    def groups(self) -> dict:
        return {name: list(group["hosts"]) for name, group in self.inventory["all"]["children"].items()}

    def __iter__(self):  # inventory, notes = import_site(...)
        return iter((self.inventory, self.notes))

    def text(self) -> str:
        """The inventory file: a header saying where it came from and what to fill in, then the groups."""
        require("PyYAML")
        lines = ["---", HEADER, "# Importing again rewrites this file: keep your own values in host_vars/<host>.yml."]
        for what, display in self.sources:
            lines.append(printable(f"# {what}: {display}"))
        if self.cluster_name:
            lines.append(printable(f"# Cluster: {self.cluster_name}"))
        for name, description, source in self.fleets:
            lines.append(printable(f"# Fleet {name} ({source})" + (f": {description}" if description else "")))
        if self.notes:
            lines += ["#", "# To check and fill in (the import's notes):"]
            for note in self.notes:
                wrapped = textwrap.wrap(printable(note), width=114, break_long_words=False, break_on_hyphens=False)
                lines.extend(f"#   {'-' if i == 0 else ' '} {part}" for i, part in enumerate(wrapped))
        lines += ["all:", "  children:"]
        for group, members in self.inventory["all"]["children"].items():
            lines += [f"    {group}:", "      hosts:"]
            for host, variables in members["hosts"].items():
                comment = self.comments.get(host) if variables else None
                lines.append(f"        {_key(host)}:" + (f"  # {printable(comment)}" if comment else ""))
                for key, value in variables.items():
                    dumped = _dump({key: value}, flow=isinstance(value, list)).split("\n")
                    if key in self.placeholders.get(host, ()) and len(dumped) == 1:
                        dumped[0] += "  # placeholder: write the machine's own"
                    lines.extend("          " + line for line in dumped)
        return "\n".join(lines) + "\n"


def _dump(data, flow: bool = False) -> str:
    """YAML of ``data``: block style, or a list of names on one line (``[camera, lidar]``) with ``flow``."""
    style = None if flow else False
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=style, width=1000, allow_unicode=True).rstrip("\n")


def _key(name: str) -> str:
    """``name`` as a YAML mapping key (quoted when YAML would read it as another type: 'null', '123')."""
    return _dump({name: 0})[: -len(": 0")]


# ---------------------------------------------------------------------------------------------------------------
# Reading the documents
# ---------------------------------------------------------------------------------------------------------------


class _Checker:
    """Checks of one document's fields; every problem names the document's source, the field and its line."""

    def __init__(self, doc: Document, problems: list[Problem]):
        self.doc = doc
        self.problems = problems

    def problem(self, parts, message: str) -> None:
        self.problems.append(Problem(self.doc.source, format_path(parts), message, self.doc.line_of(parts)))

    def mapping(self, value, parts, what: str, fields, required=()) -> dict | None:
        """``value`` when it is a mapping with known fields and the required ones; None (and problems) otherwise."""
        if not isinstance(value, dict):
            self.problem(parts, f"{describe(value)} is not valid; expected {what}")
            return None
        for key in value:
            if key not in fields:
                hint = did_you_mean(key, fields)
                self.problem((*parts, str(key)), f"unknown field{hint}; expected one of {', '.join(fields)}")
        for key in required:
            if key not in value:
                self.problem(parts, f"{key} is required")
            elif value[key] is None:
                self.problem((*parts, key), "is required; it has no value")
        return value

    def name(self, value, parts, what: str) -> str | None:
        if not isinstance(value, str) or not _NAME.fullmatch(value) or len(value) > 63:
            self.problem(parts, f"{describe(value)} is not a valid {what}; expected {_NAME_EXPECTED}")
            return None
        return value

    def text(self, value, parts, what: str) -> str | None:
        """A single line of text (a comment of the written file or a note)."""
        if not isinstance(value, str) or not value.strip() or "\n" in value or "\r" in value or len(value) > 253:
            self.problem(parts, f"{describe(value)} is not valid; expected {what} (one line of text)")
            return None
        return value

    def header(self, kind: str, parts=()) -> dict | None:
        """The document's apiVersion, kind and fields; its metadata when all is well."""
        data = self.doc.data
        fields = _TOP_FIELDS[kind]
        data = self.mapping(data, parts, f"a {kind} (a mapping with {', '.join(fields)})", fields)
        if data is None:
            return None
        found = data.get("kind")
        if found != kind:
            other = {CLUSTER_KIND: "cluster_inventory", FLEET_KIND: "fleets"}
            hint = f" (a {found} file belongs in {other[found]})" if isinstance(found, str) and found in other else ""
            reason = "kind is required" if found is None else f"{describe(found)} is not valid{hint}"
            self.problem(("kind",) if "kind" in data else (), f"{reason}; expected {kind}")
            return None
        version = data.get("apiVersion")
        if version != API_VERSION:
            reason = "apiVersion is required" if version is None else f"{describe(version)} is not supported"
            self.problem(("apiVersion",) if "apiVersion" in data else (), f"{reason}; expected {API_VERSION}")
        expected = f"a mapping with {', '.join(_METADATA_FIELDS[kind])}"
        if data.get("metadata") is None:
            self.problem(("metadata",) if "metadata" in data else (), f"metadata is required; expected {expected}")
            return None
        metadata = self.mapping(data["metadata"], ("metadata",), expected, _METADATA_FIELDS[kind])
        return data if metadata is not None else None


def _check_address(checker: _Checker, value, parts) -> str | None:
    if isinstance(value, str) and value:
        try:
            return str(ipaddress.ip_address(value))
        except ValueError:
            if _DNS_NAME.fullmatch(value) and len(value) <= 253:
                return value
    checker.problem(parts, f"{describe(value)} is not valid; expected the machine's IP address or DNS name")
    return None


def _parameter_problem(value) -> str | None:
    if isinstance(value, (bool, int, str)):
        return None
    if isinstance(value, float):
        return None if math.isfinite(value) else f"{describe(value)} is not valid; expected a finite number"
    if value is None:
        return "has no value; expected a string, a number or true/false"
    return f"{describe(value)} is not valid; expected a string, a number or true/false (quote other values)"


def _devices(checker: _Checker, value, parts) -> list[Device]:
    if value is None:
        return []
    if not isinstance(value, list):
        checker.problem(parts, f"{describe(value)} is not valid; expected a list of devices (deviceName, parameter)")
        return []
    devices: list[Device] = []
    seen: dict[str, int] = {}
    for index, item in enumerate(value):
        where = (*parts, index)
        item = checker.mapping(item, where, "a device: a mapping with deviceName and parameter", _DEVICE_FIELDS, ("deviceName",))
        if item is None:
            continue
        name = item.get("deviceName")
        if name is not None:
            name = checker.name(name, (*where, "deviceName"), "device name")
        if name is not None and name in seen:
            first = format_path((*parts, seen[name]))
            checker.problem((*where, "deviceName"), f"'{name}' is already the device {first}; expected each device once per host")
            name = None
        parameters = {}
        given = item.get("parameter")
        if given is not None and not isinstance(given, dict):
            checker.problem(
                (*where, "parameter"), f"{describe(given)} is not valid; expected a mapping of parameter names to values"
            )
        for key, setting in (given or {}).items() if isinstance(given, dict) else ():
            at = (*where, "parameter", str(key))
            if not isinstance(key, str) or not _PARAMETER_NAME.fullmatch(key) or len(key) > 253:
                checker.problem(at, f"{describe(key)} is not a valid parameter name; expected a name without spaces (quote it)")
                continue
            why = _parameter_problem(setting)
            if why:
                checker.problem(at, why)
                continue
            parameters[key] = setting
        if name is not None:
            seen[name] = index
            devices.append(Device(name, parameters))
    return devices


def _host(checker: _Checker, item, index: int) -> Host | None:
    parts = ("hosts", index)
    count = len(checker.problems)
    item = checker.mapping(
        item, parts, "a host: a mapping with hostname, accessIp, kuberosRole...", _HOST_FIELDS, ("hostname", "kuberosRole")
    )
    if item is None:
        return None
    name = checker.name(item["hostname"], (*parts, "hostname"), "hostname") if item.get("hostname") is not None else None
    role = item.get("kuberosRole")
    known = isinstance(role, str) and role in ROLE_GROUPS
    if role is not None and not known:
        checker.problem(
            (*parts, "kuberosRole"),
            f"{describe(role)} is not valid{did_you_mean(role, ROLE_GROUPS) if isinstance(role, str) else ''}; "
            f"expected {' | '.join(ROLE_GROUPS)}",
        )
    host = Host(index, str(name), str(role))
    if item.get("accessIp") is not None:
        host.address = _check_address(checker, item["accessIp"], (*parts, "accessIp"))
    if item.get("alias") is not None:
        host.alias = checker.text(item["alias"], (*parts, "alias"), "another name of the machine")
    if item.get("onboardComputerGroup") is not None:
        host.computer_group = checker.text(item["onboardComputerGroup"], (*parts, "onboardComputerGroup"), "a group name")
    robot = item.get("locatedInRobot")
    if robot is not None:
        where = (*parts, "locatedInRobot")
        robot = checker.mapping(robot, where, "a mapping with name and robotId", _ROBOT_FIELDS, ("name",))
        if robot is not None and robot.get("name") is not None:
            host.robot = checker.name(robot["name"], (*where, "name"), "robot name")
        if robot is not None and robot.get("robotId") is not None:
            robot_id = robot["robotId"]
            if isinstance(robot_id, bool) or not isinstance(robot_id, (int, str)) or "\n" in str(robot_id):
                checker.problem((*where, "robotId"), f"{describe(robot_id)} is not valid; expected a number or a name")
            else:
                host.robot_id = robot_id
        if known and role != "onboard":
            checker.problem(where, f"is only for an onboard computer, but kuberosRole is {role}; expected kuberosRole onboard")
    elif role == "onboard":
        checker.problem(
            parts, "locatedInRobot is required for an onboard computer (kuberosRole onboard); expected the robot's name"
        )
    host.devices = _devices(checker, item.get("peripheralDevices"), (*parts, "peripheralDevices"))
    shared = item.get("shared")
    if shared is not None:
        if isinstance(shared, bool):
            host.shared = shared
        else:
            checker.problem((*parts, "shared"), f"{describe(shared)} is not valid; expected true or false")
    group = item.get("resourceGroup")
    if group is not None:
        if isinstance(group, str) and _GROUP_NAME.fullmatch(group) and len(group) <= 63:
            host.resource_group = group
        else:
            checker.problem(
                (*parts, "resourceGroup"),
                f"{describe(group)} is not valid; expected a name of letters, digits, '-', '_' and '.', at most 63 characters",
            )
    return host if len(checker.problems) == count else None


def _cluster(doc: Document, problems: list[Problem]) -> tuple[str, list[Host]]:
    checker = _Checker(doc, problems)
    data = checker.header(CLUSTER_KIND)
    if data is None:
        return "", []
    cluster_name = data["metadata"].get("clusterName")
    if cluster_name is None:
        checker.problem(("metadata",), "clusterName is required; expected the name of the cluster")
    else:
        cluster_name = checker.text(cluster_name, ("metadata", "clusterName"), "the name of the cluster") or ""
    entries = data.get("hosts")
    if not isinstance(entries, list) or not entries:
        reason = "hosts is required" if entries is None else f"{describe(entries)} is not valid"
        checker.problem(("hosts",) if "hosts" in data else (), f"{reason}; expected a list of hosts (hostname, kuberosRole...)")
        return str(cluster_name or ""), []
    hosts: list[Host] = []
    names: dict[str, Host] = {}
    for index, item in enumerate(entries):
        host = _host(checker, item, index)
        if host is None:
            continue
        if host.name in names:
            first = names[host.name]
            line = doc.line_of(("hosts", first.index, "hostname"))
            at = f" (line {line})" if line else ""
            checker.problem(
                ("hosts", index, "hostname"),
                f"'{host.name}' is already the hostname of hosts[{first.index}]{at}; expected unique hostnames (node names)",
            )
            continue
        names[host.name] = host
        hosts.append(host)
    return str(cluster_name or ""), hosts


def _fleet(doc: Document, problems: list[Problem]) -> Fleet | None:
    checker = _Checker(doc, problems)
    count = len(problems)
    data = checker.header(FLEET_KIND)
    if data is None:
        return None
    metadata = data["metadata"]
    name = metadata.get("name")
    if name is None:
        checker.problem(("metadata",), "name is required; expected the fleet's name")
    else:
        name = checker.name(name, ("metadata", "name"), "fleet name")
    description = metadata.get("description")
    if description is not None and not isinstance(description, str):
        checker.problem(("metadata", "description"), f"{describe(description)} is not valid; expected text")
    main = metadata.get("mainCluster")
    if main is not None:
        main = checker.text(main, ("metadata", "mainCluster"), "the name of the fleet's cluster")
    entries = data.get("robot")
    robots: list[str] = []
    if entries is not None and not isinstance(entries, list):
        checker.problem(("robot",), f"{describe(entries)} is not valid; expected a list of robots (each a mapping with name)")
        entries = []
    seen: dict[str, int] = {}
    for index, item in enumerate(entries or []):
        where = ("robot", index)
        item = checker.mapping(item, where, "a robot: a mapping with name", ("name",), ("name",))
        if item is None or item.get("name") is None:
            continue
        robot = checker.name(item["name"], (*where, "name"), "robot name")
        if robot is None:
            continue
        if robot in seen:
            checker.problem(
                (*where, "name"), f"'{robot}' is already robot[{seen[robot]}] of this fleet; expected each robot once"
            )
            continue
        seen[robot] = index
        robots.append(robot)
    if len(problems) != count:
        return None
    return Fleet(str(name), " ".join(str(description or "").split()), main, robots, doc)


def _as_document(value, source: str) -> Document:
    return value if isinstance(value, Document) else Document(value, source)


def _options_problems(default_cpu, default_memory, default_shared, default_fleet) -> tuple[dict, dict, list[Problem]]:
    """The placeholders per role (the built-in ones under those given), checked."""
    problems: list[Problem] = []
    chosen = {}
    for option, given, builtin, parser in (
        ("default_cpu", default_cpu, DEFAULT_CPU, quantities.parse_cpu),
        ("default_memory", default_memory, DEFAULT_MEMORY, quantities.parse_memory),
    ):
        values = dict(builtin)
        if given is not None and not isinstance(given, dict):
            problems.append(
                Problem("options", option, f"{describe(given)} is not valid; expected a mapping of kuberosRole to value")
            )
            given = {}
        for role, value in (given or {}).items():
            if role not in ROLE_GROUPS:
                hint = did_you_mean(role, ROLE_GROUPS)
                problems.append(Problem("options", f"{option}.{role}", f"unknown role{hint}; expected {', '.join(ROLE_GROUPS)}"))
                continue
            try:
                if parser(value) <= 0:
                    raise ValueError("expected more than zero")
            except ValueError as exc:
                problems.append(Problem("options", f"{option}.{role}", f"{describe(value)} is not valid; {exc}"))
                continue
            values[role] = value
        chosen[option] = values
    if not isinstance(default_shared, bool):
        problems.append(Problem("options", "default_shared", f"{describe(default_shared)} is not valid; expected true or false"))
    if default_fleet is not None and (not isinstance(default_fleet, str) or not _NAME.fullmatch(default_fleet)):
        problems.append(
            Problem("options", "default_fleet", f"{describe(default_fleet)} is not a valid fleet name; expected {_NAME_EXPECTED}")
        )
    return chosen["default_cpu"], chosen["default_memory"], problems


def _names(hosts) -> str:
    return ", ".join(hosts)


# ---------------------------------------------------------------------------------------------------------------
# The import
# ---------------------------------------------------------------------------------------------------------------


def import_site(
    cluster_inventory,
    fleets,
    default_cpu: dict | None = None,
    default_memory: dict | None = None,
    default_shared: bool = DEFAULT_SHARED,
    default_fleet: str | None = None,
) -> ImportedSite:
    """The inventory of a ClusterInventory and Fleets (each a ``yaml_source.Document``, or plain data: then problems
    have no line and name the cluster inventory ``cluster_inventory`` and the fleets ``fleets[i]``).

    ``default_cpu`` and ``default_memory`` map a kuberosRole to the placeholder its hosts get (over ``DEFAULT_CPU``,
    ``DEFAULT_MEMORY``); ``default_shared`` is what an edge or cloud host without ``shared`` gets; ``default_fleet``
    is the fleet of robots no Fleet lists (unset: they are left out). ``SpecError`` with every problem otherwise."""
    cpu, memory, problems = _options_problems(default_cpu, default_memory, default_shared, default_fleet)
    cluster_doc = _as_document(cluster_inventory, "cluster_inventory")
    fleet_docs = [_as_document(doc, f"fleets[{i}]") for i, doc in enumerate(fleets)]
    cluster_name, hosts = _cluster(cluster_doc, problems)
    parsed = [_fleet(doc, problems) for doc in fleet_docs]
    robots = _robot_names(cluster_doc)  # also those of hosts with a problem: a fleet naming them is not wrong
    fleet_of = _fleet_membership([f for f in parsed if f is not None], robots, cluster_doc.source, problems)
    if problems:
        raise SpecError(problems, title="cannot import the reference KubeROS site")
    site = _Builder(hosts, fleet_of, cpu, memory, default_shared, default_fleet).build()
    site.cluster_name = cluster_name
    site.fleets = tuple((f.name, f.description, f.source) for f in parsed if f is not None)
    for fleet in parsed:
        if fleet is not None and fleet.main_cluster and cluster_name and fleet.main_cluster != cluster_name:
            site.notes.append(
                f"Fleet {fleet.name} ({fleet.source}) names mainCluster {fleet.main_cluster}, but the ClusterInventory "
                f"describes cluster {cluster_name}: its robots were imported all the same."
            )
        if fleet is not None and not fleet.robots:
            site.notes.append(f"Fleet {fleet.name} ({fleet.source}) has no robots: the inventory knows a fleet by its robots.")
    _check_inventory(site)
    return site


def _robot_names(doc: Document) -> set | None:
    """Every robot name the ClusterInventory's hosts give (``locatedInRobot.name``); None when it has no host list."""
    entries = doc.data.get("hosts") if isinstance(doc.data, dict) else None
    if not isinstance(entries, list):
        return None
    robots = (entry.get("locatedInRobot") for entry in entries if isinstance(entry, dict))
    return {robot.get("name") for robot in robots if isinstance(robot, dict) and isinstance(robot.get("name"), str)}


def _fleet_membership(fleets: list[Fleet], robots: set | None, cluster_source: str, problems) -> dict:
    """Robot -> its fleet: each fleet name once, each robot in one fleet and in the ClusterInventory (unless ``robots``
    is None: the ClusterInventory is unusable, and says so)."""
    fleet_of: dict[str, str] = {}
    where: dict[str, tuple] = {}
    names: dict[str, Document] = {}
    for fleet in fleets:
        doc = fleet.doc
        checker = _Checker(doc, problems)
        if fleet.name in names:
            first = names[fleet.name]
            line = first.line_of(("metadata", "name"))
            at = f"{first.source}:{line}" if line else first.source
            checker.problem(
                ("metadata", "name"), f"'{fleet.name}' is already the name of the fleet in {at}; expected unique fleet names"
            )
            continue
        names[fleet.name] = doc
        for index, robot in enumerate(fleet.robots):
            parts = ("robot", index, "name")  # a fleet with a problem in its list was refused before
            if robots is not None and robot not in robots:
                hint = did_you_mean(robot, sorted(robots))
                checker.problem(
                    parts,
                    f"'{robot}' is not a robot of the ClusterInventory {cluster_source} (no host is locatedInRobot "
                    f"with that name){hint}; expected the name of a robot the cluster inventory lists",
                )
            elif robot in fleet_of:
                first_doc, first_parts = where[robot]
                line = first_doc.line_of(first_parts)
                at = f"{first_doc.source}:{line}" if line else first_doc.source
                checker.problem(
                    parts, f"'{robot}' is already in fleet {fleet_of[robot]} ({at}); expected each robot in one fleet"
                )
            else:
                fleet_of[robot] = fleet.name
                where[robot] = (doc, parts)
    return fleet_of


class _Builder:
    def __init__(self, hosts, fleet_of, cpu, memory, default_shared, default_fleet):
        self.hosts = hosts
        self.fleet_of = fleet_of
        self.cpu = cpu
        self.memory = memory
        self.default_shared = default_shared
        self.default_fleet = default_fleet
        self.groups: dict[str, dict] = {group: {} for group in GROUP_ORDER}
        self.comments: dict[str, str] = {}
        self.placeholders: dict[str, tuple] = {}
        self.notes: list[str] = []

    def build(self) -> ImportedSite:
        computers: dict[str, Host] = {}
        extra: list[tuple[Host, Host]] = []
        unlisted: list[Host] = []
        defaulted: list[str] = []
        ignored: dict[str, list[str]] = {}
        placeholders: dict[str, list[str]] = {}
        private: list[str] = []
        for host in self.hosts:
            if host.role == "onboard":
                if any(h.robot == host.robot for h in unlisted):
                    continue  # another computer of a robot in no fleet: the robot's note says it
                if host.robot in computers:
                    extra.append((host, computers[host.robot]))
                    continue
                fleet = self.fleet_of.get(host.robot, self.default_fleet)
                if fleet is None:
                    unlisted.append(host)
                    continue
                computers[host.robot] = host
                variables = self.variables(host)
                variables = {
                    **{k: v for k, v in variables.items() if k == "ansible_host"},
                    "kuberos_robot": host.robot,
                    "kuberos_fleet": fleet,
                    **{k: v for k, v in variables.items() if k != "ansible_host"},
                }
                if host.robot not in self.fleet_of:
                    defaulted.append(host.robot)
                for reference, kept in (("shared", host.shared), ("resourceGroup", host.resource_group)):
                    if kept is not None:
                        ignored.setdefault(reference, []).append(host.name)
                self.groups["robots"][host.name] = variables
            else:
                variables = self.variables(host)
                shared = self.default_shared if host.shared is None else host.shared
                variables["kuberos_shared"] = shared
                if not shared:
                    private.append(host.name)
                if host.resource_group is not None:
                    variables["kuberos_resource_group"] = host.resource_group
                if host.computer_group is not None:
                    ignored.setdefault("onboardComputerGroup", []).append(host.name)
                tier = ROLE_GROUPS[host.role][0]
                self.groups[tier][host.name] = variables
                for group in ROLE_GROUPS[host.role][1:]:
                    self.groups[group][host.name] = {}
            self.comments[host.name] = self.comment(host)
            self.placeholders[host.name] = ("kuberos_cpu", "kuberos_memory")
            placeholders.setdefault(host.role, []).append(host.name)
        self.add_notes(placeholders, extra, unlisted, defaulted, ignored, private)
        children = {group: {"hosts": members} for group, members in self.groups.items() if members}
        return ImportedSite({"all": {"children": children}}, self.notes, self.comments, self.placeholders)

    def variables(self, host: Host) -> dict:
        variables: dict = {}
        if host.address is not None:
            variables["ansible_host"] = host.address
        variables["kuberos_cpu"] = self.cpu[host.role]
        variables["kuberos_memory"] = self.memory[host.role]
        if host.devices:
            variables["kuberos_devices"] = [device.name for device in host.devices]
        parameters = {device.name: dict(device.parameters) for device in host.devices if device.parameters}
        if parameters:
            variables["kuberos_device_parameters"] = parameters
        return variables

    @staticmethod
    def comment(host: Host) -> str:
        said = []
        if host.alias is not None:
            said.append(f"alias {host.alias}")
        if host.robot_id is not None:
            said.append(f"robotId {host.robot_id}")
        if host.computer_group is not None:
            said.append(f"onboardComputerGroup {host.computer_group}")
        return "reference: " + ", ".join(said) if said else ""

    def add_notes(self, placeholders, extra, unlisted, defaulted, ignored, private) -> None:
        notes = self.notes
        if placeholders:
            where = "; ".join(
                f"{role} {self.cpu[role]} and {self.memory[role]} on {_names(names)}" for role, names in placeholders.items()
            )
            notes.append(
                "kuberos_cpu and kuberos_memory are placeholders, as the reference format has no CPU or memory (options "
                f"default_cpu, default_memory per kuberosRole): {where}. Write each machine's own."
            )
        for host, first in extra:
            notes.append(
                f"{host.where} is a second onboard computer of robot {host.robot}, whose computer is {first.where}: an "
                "inventory robot has one onboard computer (the first the ClusterInventory lists), so this host was not "
                "imported" + (f" (nor its devices {', '.join(d.name for d in host.devices)})" if host.devices else "") + "."
            )
        for host in unlisted:
            notes.append(
                f"robot {host.robot} ({host.where}) is in no Fleet: not imported (a robot needs kuberos_fleet); list it in "
                "a Fleet file, or give default_fleet, and import again."
            )
        if defaulted:
            notes.append(f"robots {_names(defaulted)} are in no Fleet: put in fleet {self.default_fleet} (default_fleet).")
        for reference, names in (("shared", ignored.get("shared")), ("resourceGroup", ignored.get("resourceGroup"))):
            if names:
                notes.append(
                    f"{reference} of the onboard hosts {_names(names)} was ignored: a robot's computer serves only its "
                    "robot, and its resource group is its fleet."
                )
        if ignored.get("onboardComputerGroup"):
            notes.append(
                f"onboardComputerGroup of {_names(ignored['onboardComputerGroup'])} was ignored: they are not onboard computers."
            )
        grouped = sorted({h.name for h in self.hosts if h.computer_group is not None and h.role == "onboard"})
        if grouped:
            notes.append(
                f"onboardComputerGroup of {_names(grouped)} has no inventory variable (kept as a comment): a RosDeployment "
                "places a module with its requirements, not by computer group."
            )
        if private:
            notes.append(
                f"not shared: {_names(private)} (shared: false, the reference's default when absent; option "
                "default_shared): such a host serves no fleet until its kuberos_fleets lists some, or kuberos_shared is true."
            )
        if self.groups["cloud"]:
            notes.append(
                f"cloud hosts {_names(self.groups['cloud'])} need kuberos_vpn_address, and the site a vpn_gateway group, "
                "before playbooks/site.yml sets up the cluster (docs/cluster-setup.md)."
            )
        if not self.groups["control_plane"]:
            notes.append("no host has kuberosRole control-plane: playbooks/site.yml needs the group control_plane.")


def _check_inventory(site: ImportedSite) -> None:
    """The scheduler's inventory reader accepts the result (``load_inventory``), as Ansible will hand it over."""
    groups = {name: list(members) for name, members in site.groups.items()}
    hosts = site.hosts
    try:
        load_inventory(raw_inventory(groups, hosts), source="imported inventory")
    except SpecError as exc:
        raise SpecError(exc.problems, title="the imported inventory would not be valid") from None


def load_site_documents(text: str, source: str, kind: str) -> list[Document]:
    """The non-empty documents of a ClusterInventory (exactly one) or Fleet file (one or more)."""
    documents = [doc for doc in load_documents(text, source) if doc.data is not None]
    if not documents:
        raise SpecError([Problem(source, "", f"no {kind} found; the file is empty")], title=f"{source} is not valid")
    if len(documents) > 1:
        for doc in documents:
            doc.source = f"{source} (document {doc.index + 1})"
        if kind == CLUSTER_KIND:
            extra = documents[1]
            problem = Problem(extra.source, "", f"a second document; expected one {kind} per file", extra.line_of(()))
            raise SpecError([problem], title=f"{source} is not valid")
    return documents


def import_files(cluster_inventory: str, fleets, displays: dict | None = None, **options) -> ImportedSite:
    """Read the ClusterInventory file and the Fleet files, then ``import_site``; files are named by ``displays``
    (path -> name in messages), else by their path. ``SpecError`` for unreadable or invalid files."""
    displays = displays or {}
    problems: list[Problem] = []

    def read(path, kind):
        display = displays.get(path, path)
        try:
            return load_site_documents(read_text(path, display), display, kind)
        except SpecError as exc:
            problems.extend(exc.problems)
            return []

    cluster_docs = read(cluster_inventory, CLUSTER_KIND)
    fleet_docs = [doc for path in fleets for doc in read(path, FLEET_KIND)]
    if problems:
        raise SpecError(problems, title="cannot import the reference KubeROS site")
    site = import_site(cluster_docs[0], fleet_docs, **options)
    site.sources = (
        ("ClusterInventory", displays.get(cluster_inventory, cluster_inventory)),
        *(("Fleet file", displays.get(path, path)) for path in fleets),
    )
    return site


__all__ = [
    "API_VERSION",
    "DEFAULT_CPU",
    "DEFAULT_MEMORY",
    "DEFAULT_SHARED",
    "HEADER",
    "ROLE_GROUPS",
    "ImportedSite",
    "import_files",
    "import_site",
    "load_site_documents",
]
