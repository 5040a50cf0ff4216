"""Cloud VMs on demand: the budget, the request, the plan, and the inventory hosts a VM becomes.

Pure: plain data in, plain data out; no cloud client, no Ansible, no files. The role ``kuberos.platform.cloud_vms``
(``amazon.aws.ec2_instance``) reads the site's VMs, asks ``plan`` what to launch and release, carries it out and
writes ``inventory_hosts`` into an inventory file; the controller can call the same ``plan`` for a burst.

``plan(request, existing_vms, budget)``, the rules:

1. Only the VMs of the request's site count (tag ``kuberos.io/site``); of those, the fleet's are the ones tagged with
   the request's fleet. A stopped VM counts like a running one.
2. Release: the VMs of the fleet that ``request.release`` names, then, while the fleet would keep more than
   ``request.count``, the newest (highest number first). A name that is not a VM of the fleet is refused, with why.
3. Launch: ``request.count`` less what the fleet keeps, of ``request.instance_type``, cut to what the budget allows
   once the releases are done: ``max_vms`` VMs at the site, the type's own ``max``, and ``max_hourly_price`` (a VM
   whose type has no price in the budget counts 0). What is cut is refused, naming the limit that cut it.
4. A new VM takes the lowest number of the fleet no VM has (not even one released by the same plan), and is named
   ``<site>-<fleet>-cloud-<n>``: a DNS label, its inventory host and node name. With a VPN network, it also takes the
   lowest address of that network no VM of the site has (tag ``kuberos.io/vpn-address``).
5. Nothing else changes: a VM of a type the budget no longer lists is kept, with the capacity its tags recorded at
   launch, so that a budget edit never rewrites what runs.
"""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels, quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe, did_you_mean
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import Node

from .cluster_nodes import simulated_node

SOURCE = "cloud_vms"
PREFIX = "cloud_vms_"
MANAGED_BY = "kuberos"
# The tags every VM carries: who manages it, its site and fleet, its inventory host, and its capacity at launch.
TAG_NAME = "Name"
TAG_MANAGED_BY = "kuberos.io/managed-by"
TAG_SITE = "kuberos.io/site"
TAG_FLEET = "kuberos.io/fleet"
TAG_HOST = "kuberos.io/inventory-host"
TAG_CPU = "kuberos.io/cpu"
TAG_MEMORY = "kuberos.io/memory"
TAG_GPU = "kuberos.io/gpu"
TAG_ARCH = "kuberos.io/arch"
TAG_VPN = "kuberos.io/vpn-address"
# The states in which a VM exists (and counts against the budget); shutting-down and terminated ones do not.
LIVE_STATES = ("pending", "running", "stopping", "stopped")
MAX_NUMBER = 9999  # a fleet's VMs are numbered 1..9999: the name budget below keeps room for four digits
_LABEL = re.compile(r"[a-z0-9]([-a-z0-9]*[a-z0-9])?")
_LABEL_VALUE = re.compile(r"[A-Za-z0-9]([-A-Za-z0-9_.]*[A-Za-z0-9])?")
_INSTANCE_TYPE = re.compile(r"[a-z0-9][a-z0-9-]*\.[a-z0-9-]+")
_REGION = re.compile(r"[a-z0-9]+(-[a-z0-9]+)+")
_USER = re.compile(r"[a-z_][a-z0-9_-]{0,31}")
SETTINGS = ("site", "fleet", "count", "instance_type", "release", "region", "latency_ms", "resource_group", "ssh_user",
            "vpn_network", "budget")  # fmt: skip
BUDGET_KEYS = ("max_vms", "instance_types", "max_hourly_price")
TYPE_KEYS = ("cpu", "memory", "gpu", "arch", "hourly_price", "max")


@dataclass(frozen=True)
class InstanceType:
    """A kind of VM the budget allows, with the capacity a node of it offers."""

    name: str
    cpu_millis: int
    memory_bytes: int
    gpu: int = 0
    arch: str = "amd64"
    hourly_price: float | None = None
    max_vms: int | None = None


@dataclass(frozen=True)
class Budget:
    """Most VMs at a site, the instance types allowed (in the order given), and optionally a price cap per hour."""

    max_vms: int
    instance_types: tuple[InstanceType, ...]
    max_hourly_price: float | None = None

    def instance_type(self, name: str) -> InstanceType | None:
        return next((t for t in self.instance_types if t.name == name), None)

    def hourly_price(self, name: str) -> float:
        found = self.instance_type(name)
        return (found.hourly_price or 0.0) if found else 0.0


@dataclass(frozen=True)
class CloudSite:
    """Where the VMs run and how they show in the inventory."""

    name: str
    region: str
    latency_ms: float = 50.0
    resource_group: str = "cloud"
    ssh_user: str = ""
    vpn_network: str = ""  # empty: no VPN address is handed out


@dataclass(frozen=True)
class Request:
    """The fleet of a site wants ``count`` VMs (0: none); new ones are of ``instance_type``."""

    site: CloudSite
    fleet: str
    count: int
    instance_type: str
    release: tuple[str, ...] = ()


@dataclass(frozen=True)
class Vm:
    """A VM as the cloud reports it, with the tags KubeROS gave it."""

    name: str
    instance_id: str
    instance_type: str
    site: str
    fleet: str
    state: str = "running"
    private_ip: str = ""
    public_ip: str = ""
    tags: tuple[tuple[str, str], ...] = ()

    def tag(self, key: str, default: str = "") -> str:
        return dict(self.tags).get(key, default)


@dataclass(frozen=True)
class Launch:
    """A VM to launch: its name, type, tags and VPN address."""

    name: str
    instance_type: str
    tags: tuple[tuple[str, str], ...]
    vpn_address: str = ""


@dataclass(frozen=True)
class Refusal:
    """What a plan will not do, and why: ``count`` VMs of a type not launched, or the named VM not released."""

    action: str  # launch or release
    reason: str
    count: int = 0
    instance_type: str = ""
    name: str = ""


@dataclass(frozen=True)
class Plan:
    request: Request
    launch: tuple[Launch, ...]
    release: tuple[Vm, ...]
    keep: tuple[Vm, ...]
    refused: tuple[Refusal, ...]

    @property
    def changes(self) -> bool:
        return bool(self.launch or self.release)

    def summary(self) -> str:
        """One line a person reads: what is launched, released, kept and refused."""
        request = self.request
        parts = [f"site {request.site.name}, fleet {request.fleet}: {request.count} VM(s) wanted, {len(self.keep)} kept"]
        if self.launch:
            names = ", ".join(launch.name for launch in self.launch)
            parts.append(f"launch {len(self.launch)} {request.instance_type} ({names})")
        if self.release:
            parts.append(f"release {len(self.release)} ({', '.join(vm.name for vm in self.release)})")
        if not self.changes:
            parts.append("nothing to launch or release")
        for refusal in self.refused:
            what = f"{refusal.count} {refusal.instance_type}" if refusal.action == "launch" else refusal.name
            parts.append(f"refused to {refusal.action} {what}: {refusal.reason}")
        return "; ".join(parts)

    def as_dict(self) -> dict:
        """Plain data for Ansible: what to launch (with tags), release (with instance ids), keep, and refused."""
        return {
            "launch": [
                {"name": x.name, "instance_type": x.instance_type, "tags": dict(x.tags), "vpn_address": x.vpn_address}
                for x in self.launch
            ],
            "release": [
                {"name": vm.name, "instance_id": vm.instance_id, "instance_type": vm.instance_type} for vm in self.release
            ],
            "keep": [vm.name for vm in self.keep],
            "refused": [
                {"action": r.action, "count": r.count, "instance_type": r.instance_type, "name": r.name, "reason": r.reason}
                for r in self.refused
            ],
            "changes": self.changes,
            "summary": self.summary(),
        }


@dataclass(frozen=True)
class CloudSettings:
    request: Request
    budget: Budget


# ---------------------------------------------------------------------------------------------------- names and tags
def name_prefix(site: str, fleet: str) -> str:
    return f"{site}-{fleet}-cloud"


def vm_name(site: str, fleet: str, number: int) -> str:
    """``<site>-<fleet>-cloud-<n>``: the VM's Name tag, inventory host and node name (site and fleet are DNS labels,
    checked short enough by ``load_settings``)."""
    return f"{name_prefix(site, fleet)}-{number}"


def vm_number(vm: Vm) -> int | None:
    """The number in a VM's name, or None for a name KubeROS did not give."""
    match = re.fullmatch(re.escape(name_prefix(vm.site, vm.fleet)) + r"-([1-9][0-9]*)", vm.name)
    return int(match.group(1)) if match else None


def vm_tags(site: str, fleet: str, name: str, instance_type: InstanceType, vpn_address: str = "") -> dict[str, str]:
    """The tags of a new VM: who manages it, site, fleet, inventory host, and the capacity of its type at launch."""
    tags = {
        TAG_NAME: name,
        TAG_MANAGED_BY: MANAGED_BY,
        TAG_SITE: site,
        TAG_FLEET: fleet,
        TAG_HOST: name,
        TAG_CPU: quantities.format_cpu(instance_type.cpu_millis),
        TAG_MEMORY: quantities.format_memory(instance_type.memory_bytes),
        TAG_GPU: str(instance_type.gpu),
        TAG_ARCH: instance_type.arch,
    }
    if vpn_address:
        tags[TAG_VPN] = vpn_address
    return tags


def vms_from_instances(instances) -> tuple[Vm, ...]:
    """The VMs KubeROS manages among instances as ``amazon.aws.ec2_instance_info`` returns them (``instance_id``,
    ``instance_type``, ``state.name``, ``tags`` as a mapping, ``private_ip_address``, ``public_ip_address``), sorted
    by name; terminated and shutting-down ones are gone."""
    vms = []
    for item in instances or ():
        if not isinstance(item, dict):
            continue
        tags = item.get("tags") or {}
        state = (item.get("state") or {}).get("name", "")
        if not isinstance(tags, dict) or tags.get(TAG_MANAGED_BY) != MANAGED_BY or state not in LIVE_STATES:
            continue
        instance_id = str(item.get("instance_id") or "")
        vms.append(
            Vm(
                name=str(tags.get(TAG_NAME) or instance_id), instance_id=instance_id,
                instance_type=str(item.get("instance_type") or ""), site=str(tags.get(TAG_SITE, "")),
                fleet=str(tags.get(TAG_FLEET, "")), state=state, private_ip=str(item.get("private_ip_address") or ""),
                public_ip=str(item.get("public_ip_address") or ""),
                tags=tuple(sorted((str(k), str(v)) for k, v in tags.items())),
            )
        )  # fmt: skip
    return tuple(sorted(vms, key=lambda vm: (vm.name, vm.instance_id)))


# ------------------------------------------------------------------------------------------------------------ the plan
def plan(request: Request, existing_vms, budget: Budget) -> Plan:
    """What to launch, release and keep so that the request's fleet has ``request.count`` VMs within the budget; what
    is refused and why (the rules are in this module's docstring)."""
    site_vms = [vm for vm in existing_vms if vm.site == request.site.name]
    fleet_vms = [vm for vm in site_vms if vm.fleet == request.fleet]
    release, refused = _releases(request, fleet_vms)
    released = {vm.instance_id for vm in release}
    keep = [vm for vm in fleet_vms if vm.instance_id not in released]
    remaining = [vm for vm in site_vms if vm.instance_id not in released]
    launch, cut = _launches(request, fleet_vms, site_vms, remaining, budget)
    return Plan(request, tuple(launch), tuple(release), tuple(keep), tuple(refused + cut))


def _newest_first(vms: list[Vm]) -> list[Vm]:
    """Highest number first; VMs without a number (not named by KubeROS) last, so that they go last."""
    return sorted(vms, key=lambda vm: (vm_number(vm) is not None, vm_number(vm) or 0, vm.name), reverse=True)


def _releases(request: Request, fleet_vms: list[Vm]) -> tuple[list[Vm], list[Refusal]]:
    by_name = {vm.name: vm for vm in fleet_vms}
    release: list[Vm] = []
    refused: list[Refusal] = []
    for name in request.release:
        if name not in by_name:
            known = ", ".join(sorted(by_name)) or "none"
            hint = did_you_mean(name, by_name)
            reason = f"not a VM of fleet {request.fleet} at site {request.site.name} (its VMs: {known}){hint}"
            refused.append(Refusal("release", reason, name=name))
        elif by_name[name] not in release:
            release.append(by_name[name])
    for vm in _newest_first(fleet_vms):
        if len(fleet_vms) - len(release) <= request.count:
            break
        if vm not in release:
            release.append(vm)
    return release, refused


def _launches(request, fleet_vms, site_vms, remaining, budget):
    """New VMs up to the request, one at a time while every limit of the budget holds; the rest refused."""
    wanted = max(0, request.count - len([vm for vm in remaining if vm.fleet == request.fleet]))
    if wanted == 0:
        return [], []
    kind = budget.instance_type(request.instance_type)
    if kind is None:
        allowed = ", ".join(t.name for t in budget.instance_types) or "none"
        reason = f"{request.instance_type} is not an instance type of the budget (allowed: {allowed})"
        return [], [Refusal("launch", reason, wanted, request.instance_type)]
    taken_numbers = {vm_number(vm) for vm in fleet_vms}
    taken_addresses = {vm.tag(TAG_VPN) for vm in site_vms} - {""}
    count = len(remaining)
    of_type = len([vm for vm in remaining if vm.instance_type == kind.name])
    cost = sum(budget.hourly_price(vm.instance_type) for vm in remaining)
    launch: list[Launch] = []
    number = 0
    for done in range(wanted):
        reason = _limit(request, budget, kind, count, of_type, cost)
        address = ""
        if not reason and request.site.vpn_network:
            address = _free_address(request.site.vpn_network, taken_addresses)
            if not address:
                reason = f"no free address left in the VPN network {request.site.vpn_network}"
        number = next((n for n in range(number + 1, MAX_NUMBER + 1) if n not in taken_numbers), 0)
        if not reason and not number:
            reason = f"fleet {request.fleet} has used every VM number up to {MAX_NUMBER}"
        if reason:
            return launch, [Refusal("launch", reason, wanted - done, kind.name)]
        name = vm_name(request.site.name, request.fleet, number)
        tags = vm_tags(request.site.name, request.fleet, name, kind, address)
        launch.append(Launch(name, kind.name, tuple(sorted(tags.items())), address))
        taken_addresses.add(address)
        count, of_type, cost = count + 1, of_type + 1, cost + (kind.hourly_price or 0.0)
    return launch, []


def _limit(request: Request, budget: Budget, kind: InstanceType, count: int, of_type: int, cost: float) -> str:
    """Why one more VM of ``kind`` does not fit the budget, or an empty string."""
    site = request.site.name
    if count + 1 > budget.max_vms:
        return f"the budget allows at most {budget.max_vms} VM(s) at site {site}, and {count} run there"
    if kind.max_vms is not None and of_type + 1 > kind.max_vms:
        return f"the budget allows at most {kind.max_vms} VM(s) of type {kind.name}, and {of_type} run"
    price = kind.hourly_price or 0.0
    if budget.max_hourly_price is not None and cost + price > budget.max_hourly_price + 1e-9:
        return (
            f"the budget allows at most {budget.max_hourly_price:g}/h at site {site}: {cost:g}/h run there and a "
            f"{kind.name} costs {price:g}/h"
        )
    return ""


def _free_address(network: str, taken: set) -> str:
    for address in ipaddress.ip_network(network).hosts():
        if str(address) not in taken:
            return str(address)
    return ""


# -------------------------------------------------------------------------------------------- what a VM becomes
def inventory_hosts(vms, site: CloudSite, budget: Budget | None = None) -> dict[str, dict]:
    """The inventory host of every running VM of ``site`` (group ``cloud``), named like the VM, with the host variables
    of docs/inventory.md: capacity from the VM's tags (else from the budget's type), the site's latency and resource
    group, the fleet it serves, its address, and its VPN address when it has one."""
    hosts: dict[str, dict] = {}
    problems: list[Problem] = []
    for vm in vms:
        if vm.site != site.name or vm.state != "running":
            continue
        capacity = _capacity(vm, budget, problems)
        if capacity is None:
            continue
        variables = {
            **capacity,
            "kuberos_fleets": [vm.fleet],
            "kuberos_shared": False,
            "kuberos_latency_ms": _number(site.latency_ms),
            "kuberos_resource_group": site.resource_group,
            "kuberos_cloud_instance_id": vm.instance_id,
            "kuberos_cloud_instance_type": vm.instance_type,
            "kuberos_cloud_region": site.region,
        }
        address = vm.public_ip or vm.private_ip
        if address:
            variables["ansible_host"] = address
        if site.ssh_user:
            variables["ansible_user"] = site.ssh_user
        if vm.tag(TAG_VPN):
            variables["kuberos_vpn_address"] = vm.tag(TAG_VPN)
        hosts[vm.name] = dict(sorted(variables.items()))
    if problems:
        raise SpecError(problems, title="the cloud VMs cannot be written to the inventory")
    return dict(sorted(hosts.items()))


def _capacity(vm: Vm, budget: Budget | None, problems: list[Problem]) -> dict | None:
    kind = budget.instance_type(vm.instance_type) if budget else None
    try:
        cpu = quantities.parse_cpu(vm.tag(TAG_CPU) or (quantities.format_cpu(kind.cpu_millis) if kind else None))
        memory = quantities.parse_memory(vm.tag(TAG_MEMORY) or (quantities.format_memory(kind.memory_bytes) if kind else None))
        gpu = int(vm.tag(TAG_GPU) or (kind.gpu if kind else 0))
    except (TypeError, ValueError):
        problems.append(
            Problem(
                SOURCE, f"vms.{vm.name}",
                f"its capacity is unknown: no {TAG_CPU}/{TAG_MEMORY} tags, and its type {vm.instance_type} is not in the "
                f"budget; add the type to {PREFIX}budget.instance_types or release the VM",
            )
        )  # fmt: skip
        return None
    arch = vm.tag(TAG_ARCH) or (kind.arch if kind else "amd64")
    return {
        "kuberos_cpu": _number(cpu / 1000) if cpu % 1000 == 0 else quantities.format_cpu(cpu),
        "kuberos_memory": quantities.format_memory(memory),
        "kuberos_gpu": gpu,
        "kuberos_arch": arch,
    }


def _number(value: float):
    return int(value) if float(value).is_integer() else float(value)


def inventory_document(hosts: dict[str, dict]) -> dict:
    """A YAML inventory source holding the hosts in the group ``cloud``."""
    return {"all": {"children": {"cloud": {"hosts": dict(hosts)}}}}


def cloud_node(name: str, variables: dict) -> Node:
    """The resource model's node of a cloud VM's inventory host (as ``load_inventory`` would read it)."""
    return Node(
        name=name,
        tier="cloud",
        cpu_millis=quantities.parse_cpu(variables["kuberos_cpu"]),
        memory_bytes=quantities.parse_memory(variables["kuberos_memory"]),
        gpu=int(variables.get("kuberos_gpu", 0)),
        arch=str(variables.get("kuberos_arch", "amd64")),
        fleets=tuple(variables.get("kuberos_fleets") or ()),
        shared=bool(variables.get("kuberos_shared", not variables.get("kuberos_fleets"))),
        resource_group=str(variables.get("kuberos_resource_group", "cloud")),
        latency_ms=quantities.parse_latency_ms(variables.get("kuberos_latency_ms", 50)),
    )


def simulated_nodes(hosts: dict[str, dict]) -> list[dict]:
    """kwok Node objects for the local cluster: the cloud node labels and the capacity of each VM's type."""
    nodes = []
    for name, variables in sorted(hosts.items()):
        node = cloud_node(name, variables)
        obj = simulated_node(node)
        obj["metadata"].setdefault("annotations", {})[labels.LATENCY_ANNOTATION] = f"{node.latency_ms:g}"
        nodes.append(obj)
    return nodes


# ---------------------------------------------------------------------------------------------------- the settings
def load_settings(raw, source: str = SOURCE, prefix: str = PREFIX) -> CloudSettings:
    """The request and the budget from the role's variables (``raw``: their names without ``prefix``), or
    ``SpecError`` naming each variable, field and reason."""
    problems: list[Problem] = []

    def problem(key: str, message: str) -> None:
        problems.append(Problem(source, f"{prefix}{key}", message))

    if not isinstance(raw, dict):
        raise SpecError([Problem(source, "", f"{describe(raw)} is not valid; expected a mapping of the settings")])
    for key in raw:
        if key not in SETTINGS:
            problem(str(key), f"unknown setting{did_you_mean(key, SETTINGS)}")
    site = _label(raw.get("site"), "site", problem)
    fleet = _label(raw.get("fleet"), "fleet", problem)
    if site and fleet and len(vm_name(site, fleet, MAX_NUMBER)) > 63:
        problem(
            "fleet", f"site '{site}' and fleet '{fleet}' make VM names longer than 63 characters "
            f"({vm_name(site, fleet, MAX_NUMBER)}); expected shorter names",
        )  # fmt: skip
    budget = load_budget(raw.get("budget"), problems, source, f"{prefix}budget")
    count = _whole(raw.get("count"), "count", problem)
    instance_type = raw.get("instance_type")
    if budget is not None and budget.instance_type(str(instance_type)) is None:
        names = [t.name for t in budget.instance_types]
        problem(
            "instance_type", f"{describe(instance_type)} is not an instance type of {prefix}budget "
            f"(allowed: {', '.join(names) or 'none'}){did_you_mean(instance_type, names)}",
        )  # fmt: skip
    release = raw.get("release") or []
    if not isinstance(release, (list, tuple)) or not all(isinstance(n, str) and n for n in release):
        problem("release", f"{describe(release)} is not valid; expected a list of VM names")
        release = []
    cloud_site = _site(raw, site, problem)
    if problems:
        raise SpecError(problems, title="the cloud VM settings are not valid")
    request = Request(cloud_site, fleet, count, str(instance_type), tuple(release))
    return CloudSettings(request, budget)


def _label(value, key: str, problem) -> str:
    if not isinstance(value, str) or not _LABEL.fullmatch(value):
        problem(key, f"{describe(value)} is not valid; expected a name of lowercase letters, digits and '-' (a DNS label)")
        return ""
    return value


def _whole(value, key: str, problem, minimum: int = 0) -> int:
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        problem(key, f"{describe(value)} is not valid; expected a whole number >= {minimum}")
        return 0
    return value


def _price(value, key: str, problem) -> float | None:
    if value is None:
        return None
    try:
        price = float(value)
    except (TypeError, ValueError):
        price = -1.0
    if isinstance(value, bool) or not math.isfinite(price) or price < 0:
        problem(key, f"{describe(value)} is not valid; expected a price per hour >= 0, e.g. 0.0832")
        return None
    return price


def _site(raw: dict, site: str, problem) -> CloudSite:
    region = raw.get("region")
    region_ok = isinstance(region, str) and bool(_REGION.fullmatch(region))
    if not region_ok:
        problem("region", f"{describe(region)} is not valid; expected a region such as eu-central-1")
    try:
        latency = quantities.parse_latency_ms(raw.get("latency_ms", 50))
    except ValueError as exc:
        problem("latency_ms", f"{describe(raw.get('latency_ms'))} is not valid; {exc}")
        latency = 0.0
    group = raw.get("resource_group") or (f"cloud-{region}" if region_ok else "cloud")
    if not isinstance(group, str) or not _LABEL_VALUE.fullmatch(group) or len(group) > 63:
        problem("resource_group", f"{describe(group)} is not valid; expected a name of letters, digits, '-', '_' and '.'")
    user = raw.get("ssh_user") or ""
    if not isinstance(user, str) or (user and not _USER.fullmatch(user)):
        problem("ssh_user", f"{describe(user)} is not valid; expected a login name such as admin, or empty")
    network = raw.get("vpn_network") or ""
    if network:
        try:
            parsed = ipaddress.ip_network(str(network), strict=True)
            if parsed.num_addresses < 4:
                problem("vpn_network", f"{network} has no room for VMs; expected a network of 4 addresses or more")
        except ValueError as exc:
            problem("vpn_network", f"{describe(network)} is not a network: {exc}")
    return CloudSite(str(site), str(region), latency, str(group), str(user), str(network))


def load_budget(raw, problems: list[Problem], source: str = SOURCE, var: str = PREFIX + "budget") -> Budget | None:
    """The budget: ``{max_vms, instance_types: {name: {cpu, memory, gpu, arch, hourly_price, max}}, max_hourly_price}``;
    each problem goes to ``problems`` naming ``var`` and the field. None when it is not usable."""

    def problem(key: str, message: str) -> None:
        problems.append(Problem(source, f"{var}.{key}" if key else var, message))

    if not isinstance(raw, dict):
        problem("", f"{describe(raw)} is not valid; expected a mapping with max_vms and instance_types")
        return None
    for key in raw:
        if key not in BUDGET_KEYS:
            problem(str(key), f"unknown field{did_you_mean(key, BUDGET_KEYS)}; expected {', '.join(BUDGET_KEYS)}")
    before = len(problems)
    max_vms = _whole(raw.get("max_vms"), "max_vms", problem)
    max_price = _price(raw.get("max_hourly_price"), "max_hourly_price", problem)
    types_raw = raw.get("instance_types")
    if not isinstance(types_raw, dict) or not types_raw:
        problem("instance_types", f"{describe(types_raw)} is not valid; expected a mapping of instance type to capacity")
        types_raw = {}
    kinds = [_instance_type(name, spec, problem) for name, spec in types_raw.items()]
    if len(problems) > before:
        return None
    return Budget(max_vms, tuple(kinds), max_price)


def _instance_type(name, spec, problem) -> InstanceType | None:
    where = f"instance_types['{name}']"
    if not isinstance(name, str) or not _INSTANCE_TYPE.fullmatch(name):
        problem(where, "is not an instance type name; expected e.g. t3.large or g4dn.xlarge")
    if not isinstance(spec, dict):
        problem(where, f"{describe(spec)} is not valid; expected a mapping with cpu and memory")
        return None
    for key in spec:
        if key not in TYPE_KEYS:
            problem(f"{where}.{key}", f"unknown field{did_you_mean(key, TYPE_KEYS)}; expected {', '.join(TYPE_KEYS)}")
    values = {}
    for key, parser in (("cpu", quantities.parse_cpu), ("memory", quantities.parse_memory)):
        try:
            values[key] = parser(spec.get(key))
        except ValueError as exc:
            reason = "is required" if spec.get(key) is None else f"{describe(spec.get(key))} is not valid"
            problem(f"{where}.{key}", f"{reason}; {exc}")
            values[key] = 0
        else:
            if values[key] == 0:
                problem(f"{where}.{key}", "must be more than zero")
    gpu = _whole(spec.get("gpu", 0), f"{where}.gpu", problem)
    arch = spec.get("arch", "amd64")
    if not isinstance(arch, str) or not _LABEL_VALUE.fullmatch(arch):
        problem(f"{where}.arch", f"{describe(arch)} is not valid; expected e.g. amd64 or arm64")
    price = _price(spec.get("hourly_price"), f"{where}.hourly_price", problem)
    most = None if spec.get("max") is None else _whole(spec.get("max"), f"{where}.max", problem)
    return InstanceType(str(name), values["cpu"], values["memory"], gpu, str(arch), price, most)


# ------------------------------------------------------------------------------------------------------------- burst
@dataclass(frozen=True)
class Burst:
    """How many VMs a fleet should have now, and which idle ones go: from the controller's demand (docs/cloud.md)."""

    count: int
    release: tuple[str, ...]
    why: str

    def as_dict(self) -> dict:
        return {"count": self.count, "release": list(self.release), "why": self.why}


def _epoch(stamp: str) -> float | None:
    import datetime

    try:
        return datetime.datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()
    except (AttributeError, ValueError):
        return None


def burst(demand: dict | None, vms, busy: set, request: Request, budget: Budget, now: float, release_after_s: float) -> Burst:
    """The VM count for a fleet from the capacity it lacks (``demand``: the controller's ``demand.json``; ``busy``:
    the nodes that run KubeROS pods).

    - Demand: enough VMs of the request's type to hold what is lacking (CPU, memory, GPU), less the fleet's VMs that
      run nothing yet (they are joining, or their modules are being placed), on top of the VMs it has.
    - No demand: VMs that run nothing are released once the fleet has had no demand for ``release_after_s`` seconds
      (drained first by the role); the others stay.
    Budget limits apply afterwards, in ``plan``."""
    fleet_vms = sorted(
        (vm for vm in vms if vm.site == request.site.name and vm.fleet == request.fleet and vm.state in ("pending", "running")),
        key=lambda vm: vm.name,
    )
    idle = [vm.name for vm in fleet_vms if vm.name not in busy]
    demand = demand or {}
    if int(demand.get("instances") or 0) > 0:
        kind = budget.instance_type(request.instance_type)
        if kind is None:
            return Burst(len(fleet_vms), (), f"instance type {request.instance_type} is not in the budget")
        needs = [math.ceil(int(demand.get("cpu_millis") or 0) / max(kind.cpu_millis, 1)),
                 math.ceil(int(demand.get("memory_bytes") or 0) / max(kind.memory_bytes, 1)), 1]  # fmt: skip
        if int(demand.get("gpu") or 0):
            needs.append(math.ceil(int(demand["gpu"]) / kind.gpu) if kind.gpu else 10**6)
        wanted = max(0, max(needs) - len(idle))
        modules = ", ".join(demand.get("modules") or [])
        return Burst(
            len(fleet_vms) + wanted, (),
            f"{demand['instances']} instance(s) of {modules} lack room; {wanted} more VM(s) of {kind.name}"
            + (f" ({len(idle)} joining or not yet used)" if idle else ""),
        )  # fmt: skip
    quiet = _epoch(demand.get("quiet_since") or "")
    quiet_for = now - quiet if quiet is not None else 0.0
    if idle and quiet is not None and quiet_for >= release_after_s:
        return Burst(len(fleet_vms) - len(idle), tuple(idle), f"no demand for {quiet_for:.0f} s; {', '.join(idle)} run nothing")
    why = "no demand" + (f" for {quiet_for:.0f} of {release_after_s:g} s" if idle else "; every VM is in use")
    return Burst(len(fleet_vms), (), why)
