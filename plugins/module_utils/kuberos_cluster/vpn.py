"""The WireGuard VPN between the site and cloud VMs: a hub (the site's edge gateway) and spokes (cloud VMs).

Pure: takes the VPN's hosts (name, tunnel address, public key, underlay endpoint) and returns the wg-quick
configuration of one host as text, after checking the whole VPN. The private key is never part of it:
the configuration loads it from its own file (``PostUp = wg set %i private-key <file>``), so the file can
be shown in a diff and the key never leaves the host that generated it.

- The hub has a ``[Peer]`` per spoke, allowed that spoke's tunnel address only (/32 or /128).
- A spoke has one ``[Peer]``: the hub, at its endpoint, allowed the whole tunnel network and the networks
  routed behind the hub (the site network with the control plane), so spokes reach the site and one another
  through the hub, which forwards.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, did_you_mean

SOURCE = "wireguard"
INTERFACE_NAME = re.compile(r"^[A-Za-z0-9_=+.-]{1,15}\Z")
PUBLIC_KEY = re.compile(r"^[A-Za-z0-9+/]{42}[AEIMQUYcgkosw048]=\Z")  # 32 bytes, base64


@dataclass(frozen=True)
class VpnHost:
    name: str
    address: str  # inside the tunnel
    public_key: str
    endpoint: str = ""  # host:port on the underlay (the hub's is what spokes dial)


@dataclass(frozen=True)
class Vpn:
    interface: str
    network: ipaddress.IPv4Network | ipaddress.IPv6Network
    hub: VpnHost
    spokes: tuple[VpnHost, ...]
    listen_port: int
    routed_networks: tuple[str, ...]
    keepalive: int
    mtu: int
    key_file: str

    @property
    def hosts(self) -> tuple[VpnHost, ...]:
        return (self.hub, *self.spokes)


def _check_port(value, path: str, problems: list[Problem]) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        problems.append(Problem(SOURCE, path, f"{value!r} is not a UDP port; expected 1-65535"))
        return 0
    return value


def build_vpn(
    hosts: dict[str, dict],
    hub: str,
    *,
    interface: str = "wg-kuberos",
    network: str = "10.100.0.0/24",
    listen_port: int = 51820,
    routed_networks: list[str] | tuple[str, ...] = (),
    keepalive: int = 25,
    mtu: int = 1420,
    key_file: str = "/etc/wireguard/wg-kuberos.key",
) -> Vpn:
    """Check the VPN described by ``hosts`` (name -> {address, public_key, endpoint}) and ``hub``."""
    problems: list[Problem] = []
    if not isinstance(interface, str) or not INTERFACE_NAME.match(interface):
        problems.append(
            Problem(
                SOURCE, "wireguard_interface", f"{interface!r} is not an interface name; expected 1-15 letters, digits or _=+.-"
            )
        )
    try:
        net = ipaddress.ip_network(str(network), strict=True)
    except ValueError as error:
        problems.append(Problem(SOURCE, "wireguard_network", f"{network!r} is not a network: {error}"))
        net = None
    _check_port(listen_port, "wireguard_listen_port", problems)
    if isinstance(keepalive, bool) or not isinstance(keepalive, int) or not 0 <= keepalive <= 65535:
        problems.append(Problem(SOURCE, "wireguard_persistent_keepalive", f"{keepalive!r}: expected seconds, 0-65535 (0: off)"))
    if isinstance(mtu, bool) or not isinstance(mtu, int) or not 1280 <= mtu <= 9000:
        problems.append(Problem(SOURCE, "wireguard_mtu", f"{mtu!r}: expected 1280-9000"))
    routed = []
    for index, value in enumerate(routed_networks or ()):
        try:
            routed.append(str(ipaddress.ip_network(str(value), strict=True)))
        except ValueError as error:
            problems.append(Problem(SOURCE, f"wireguard_hub_routed_networks[{index}]", f"{value!r} is not a network: {error}"))
    if not hosts:
        problems.append(Problem(SOURCE, "wireguard_peers", "no hosts: expected the hub and at least one spoke"))
    if hub not in hosts:
        hint = did_you_mean(hub, hosts) if hub else "; put the edge gateway in the inventory group vpn_gateway"
        problems.append(
            Problem(SOURCE, "wireguard_hub", f"{hub!r} is not a host of the VPN ({', '.join(sorted(hosts)) or 'none'}){hint}")
        )
    checked: dict[str, VpnHost] = {}
    seen_addresses: dict[str, str] = {}
    for name in sorted(hosts):
        values = hosts[name] or {}
        where = f"hosts.{name}"
        address = str(values.get("address") or "")
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            problems.append(
                Problem(
                    SOURCE,
                    f"{where}.kuberos_vpn_address",
                    f"{address!r} is not an IP address; every host of the VPN needs its tunnel address",
                )
            )
        else:
            if net is not None and ip not in net:
                problems.append(Problem(SOURCE, f"{where}.kuberos_vpn_address", f"{address} is outside wireguard_network {net}"))
            elif net is not None and ip in (net.network_address, net.broadcast_address):
                problems.append(
                    Problem(SOURCE, f"{where}.kuberos_vpn_address", f"{address} is the network or broadcast address of {net}")
                )
            if address in seen_addresses:
                problems.append(
                    Problem(SOURCE, f"{where}.kuberos_vpn_address", f"{address} is also the address of {seen_addresses[address]}")
                )
            seen_addresses[address] = name
        key = str(values.get("public_key") or "")
        if not PUBLIC_KEY.match(key):
            problems.append(
                Problem(SOURCE, f"{where}.public_key", f"{key[:60]!r} is not a WireGuard public key (44 characters of base64)")
            )
        endpoint = str(values.get("endpoint") or "")
        if name == hub:
            host_part, _sep, port = endpoint.rpartition(":")
            if not host_part or not port.isdigit():
                problems.append(
                    Problem(
                        SOURCE,
                        "wireguard_hub_endpoint",
                        f"{endpoint!r}: expected host:port that the spokes dial to reach the hub",
                    )
                )
            else:
                _check_port(int(port), "wireguard_hub_endpoint", problems)
        checked[name] = VpnHost(name, address, key, endpoint)
    if hub in hosts and len(hosts) < 2:
        problems.append(Problem(SOURCE, "wireguard_peers", f"only the hub {hub}: expected at least one spoke (a cloud VM)"))
    if problems:
        raise SpecError(problems, title="the WireGuard VPN is not valid")
    return Vpn(
        interface=interface, network=net, hub=checked[hub], spokes=tuple(h for n, h in checked.items() if n != hub),
        listen_port=listen_port, routed_networks=tuple(routed), keepalive=keepalive, mtu=mtu, key_file=key_file,
    )  # fmt: skip


def _host_route(address: str) -> str:
    return f"{address}/{ipaddress.ip_address(address).max_prefixlen}"


def wg_quick_config(vpn: Vpn, host: str) -> str:
    """The wg-quick configuration of ``host``: its interface and its peers, no private key."""
    me = next((h for h in vpn.hosts if h.name == host), None)
    if me is None:
        raise SpecError(
            [
                Problem(
                    SOURCE,
                    "inventory_hostname",
                    f"{host!r} is not a host of the VPN{did_you_mean(host, [h.name for h in vpn.hosts])}",
                )
            ]
        )
    is_hub = me.name == vpn.hub.name
    lines = [
        f"# WireGuard interface {vpn.interface} of {me.name}, {'hub' if is_hub else 'spoke'} of the KubeROS VPN.",
        "# Written by the kuberos.platform.wireguard role; the private key stays in its own file.",
        "[Interface]",
        f"Address = {me.address}/{vpn.network.prefixlen}",
        f"MTU = {vpn.mtu}",
    ]
    if is_hub:
        lines.append(f"ListenPort = {vpn.listen_port}")
    lines.append(f"PostUp = wg set %i private-key {vpn.key_file}")
    if is_hub:
        for spoke in vpn.spokes:
            lines += [
                "",
                f"# {spoke.name}",
                "[Peer]",
                f"PublicKey = {spoke.public_key}",
                f"AllowedIPs = {_host_route(spoke.address)}",
            ]
    else:
        allowed = ", ".join([str(vpn.network), *vpn.routed_networks])
        lines += [
            "",
            f"# {vpn.hub.name} (hub)",
            "[Peer]",
            f"PublicKey = {vpn.hub.public_key}",
            f"Endpoint = {vpn.hub.endpoint}",
            f"AllowedIPs = {allowed}",
        ]
        if vpn.keepalive:
            lines.append(f"PersistentKeepalive = {vpn.keepalive}")
    return "\n".join(lines) + "\n"
