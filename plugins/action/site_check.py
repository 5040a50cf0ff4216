# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""site_check on the controller: the whole inventory checked before site.yml touches a machine, every problem once
(documented in plugins/modules/site_check.py)."""

from __future__ import annotations

import contextlib
import ipaddress

from ansible.plugins.action import ActionBase

from ansible_collections.kuberos.platform.plugins.filter.fleet_inventory import fleet_inventory
from ansible_collections.kuberos.platform.plugins.filter.kubeadm_config import kubeadm_config
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.plugin_utils.plain_data import plain

ARGUMENT_SPEC = {
    "kubernetes_version": {"type": "str", "default": "v1.34.4"},
    "pod_cidr": {"type": "str", "default": "10.244.0.0/16"},
    "service_cidr": {"type": "str", "default": "10.96.0.0/12"},
    "control_plane_endpoint": {"type": "str", "default": ""},
    "control_plane_vip": {"type": "str", "default": ""},
}
MACHINE_GROUPS = ("robots", "edge", "cloud")


def site_problems(groups: dict, hostvars, settings: dict) -> list[str]:
    """Every problem of the inventory as a site, each once: the resource model, each machine's kubeadm settings
    (control planes, networks, endpoint, addresses), and the VPN's hosts and tunnel addresses."""
    found: list[str] = []
    settings = dict(settings)
    vip = str(settings.pop("control_plane_vip", "") or "")
    if vip and not settings.get("control_plane_endpoint"):
        settings["control_plane_endpoint"] = f"{vip}:6443"  # as the kubeadm roles default it

    def add(exc: SpecError) -> None:
        found.extend(str(problem) for problem in exc.problems)

    try:
        raw = fleet_inventory.__wrapped__(groups, hostvars)
    except SpecError as exc:
        add(exc)
        return list(dict.fromkeys(found))
    control_planes = list(groups.get("control_plane", []))
    machines = [host for group in MACHINE_GROUPS for host in groups.get(group, [])]
    for host in dict.fromkeys(machines):
        try:
            kubeadm_config.__wrapped__(raw, hostvars, host, control_planes, **settings)
        except SpecError as exc:
            add(exc)
    found.extend(vip_problems(vip, control_planes, hostvars, settings["control_plane_endpoint"]))
    gateways, clouds = list(groups.get("vpn_gateway", [])), list(groups.get("cloud", []))
    if clouds and len(gateways) != 1:
        found.append(f"inventory: groups.vpn_gateway: has {len(gateways)} hosts; the VPN to the cloud VMs needs exactly one")
    seen: dict[str, str] = {}
    for host in dict.fromkeys(gateways + clouds):
        address = plain(hostvars[host].get("kuberos_vpn_address"))
        if address in (None, ""):  # for a cloud VM, the words of kubeadm_config's problem: reported once
            role = "a cloud host" if host in clouds else "the VPN's hub"
            found.append(
                f"inventory: hosts.{host}.kuberos_vpn_address: is required for {role}; "
                "expected its IP address inside the WireGuard tunnel"
            )
        elif address in seen:
            found.append(f"inventory: hosts.{host}.kuberos_vpn_address: {address} is also {seen[address]}'s; each needs its own")
        else:
            seen[str(address)] = host
    return list(dict.fromkeys(found))


def vip_problems(vip: str, control_planes: list[str], hostvars, endpoint: str) -> list[str]:
    """The API server's virtual IP (kuberos_control_plane_vip): an IPv4 address no host has, which the endpoint
    names when it names an address, on control planes that each have an IPv4 kuberos_address (VRRP's peers)."""
    if not vip:
        return []
    where = "inventory: vars.kuberos_control_plane_vip"
    try:
        address = ipaddress.ip_address(vip)
    except ValueError:
        return [f"{where}: '{vip}' is not an IP address; expected the API server's virtual IPv4 address"]
    if address.version != 4:
        return [f"{where}: '{vip}': keepalived's virtual IP is IPv4 here; use a load balancer for an IPv6 endpoint"]
    problems = []
    for host in control_planes:
        own = str(plain(hostvars[host].get("kuberos_address", "")) or "")
        if own == vip:
            problems.append(f"{where}: {vip} is also hosts.{host}.kuberos_address; the virtual IP must be free")
    host_part = endpoint.rsplit(":", 1)[0].strip("[]") if endpoint else ""
    with contextlib.suppress(ValueError):
        if host_part and ipaddress.ip_address(host_part) != address:
            problems.append(
                f"inventory: vars.kuberos_control_plane_endpoint: '{endpoint}' names {host_part}, not the virtual IP "
                f"{vip}; the endpoint must reach the API servers through it (or name a DNS name that resolves to it)"
            )
    if not control_planes:
        problems.append(f"{where}: is set but groups.control_plane is empty; the control planes share the address")
    return problems


class ActionModule(ActionBase):
    TRANSFERS_FILES = False
    _requires_connection = False
    _supports_check_mode = True
    _supports_async = False

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        _validation, args = self.validate_argument_spec(argument_spec=ARGUMENT_SPEC)
        task_vars = task_vars or {}
        problems = site_problems(task_vars.get("groups", {}), task_vars.get("hostvars", {}), args)
        if problems:
            noun = "problem" if len(problems) == 1 else "problems"
            result.update(
                failed=True,
                changed=False,
                msg=f"the inventory cannot make a site ({len(problems)} {noun}; nothing was touched)",
                problems="".join(f"  - {line}\n" for line in problems),
            )
        else:
            result.update(changed=False, msg="the inventory makes a site")
        return result
