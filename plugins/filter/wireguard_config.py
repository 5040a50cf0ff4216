# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The wg-quick configuration of one host of the KubeROS VPN (hub or spoke), after checking the whole VPN."""

from __future__ import annotations

DOCUMENTATION = r"""
name: wireguard_config
short_description: The wg-quick configuration of one host of the hub-and-spoke VPN, without its private key
version_added: 0.2.0
description:
  - Checks the whole VPN (every host's tunnel address inside the tunnel network and unique, public keys well
    formed, the hub known and reachable at host:port, at least one spoke) and reports every problem at once.
  - Returns the configuration of one host. The hub gets a peer per spoke, allowed that spoke's address only;
    a spoke gets the hub as its only peer, allowed the tunnel network and the networks routed behind the hub.
  - The private key is never in the configuration; C(PostUp) loads it from O(key_file) on the host.
options:
  _input:
    description: Inventory names of every host of the VPN (the hub and the spokes).
    type: list
    elements: str
    required: true
  hostvars:
    description: The C(hostvars) magic variable; each host of the VPN carries C(wireguard__self) (address, public_key, endpoint).
    type: raw
    required: true
  host:
    description: The host whose configuration is returned (C(inventory_hostname)).
    type: str
    required: true
  hub:
    description: Inventory name of the hub.
    type: str
    required: true
  interface:
    description: The interface name.
    type: str
    default: wg-kuberos
  network:
    description: The tunnel network.
    type: str
    default: 10.100.0.0/24
  listen_port:
    description: The hub's UDP port.
    type: int
    default: 51820
  routed_networks:
    description: Networks behind the hub that spokes route through the tunnel.
    type: list
    elements: str
    default: []
  keepalive:
    description: Spokes' persistent keepalive in seconds (0 off).
    type: int
    default: 25
  mtu:
    description: The interface MTU.
    type: int
    default: 1420
  key_file:
    description: Path of the private key on the host.
    type: str
    default: /etc/wireguard/wg-kuberos.key
"""

EXAMPLES = r"""
- name: Write this host's tunnel configuration
  ansible.builtin.copy:
    dest: /etc/wireguard/wg-kuberos.conf
    mode: "0600"
    content: >-
      {{ wireguard_peers | kuberos.platform.wireguard_config(hostvars, inventory_hostname, hub=wireguard_hub) }}
"""

RETURN = r"""
_value:
  description: The wg-quick configuration text of the host.
  type: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.vpn import build_vpn, wg_quick_config
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def wireguard_config(peers, hostvars, host, hub, interface="wg-kuberos", network="10.100.0.0/24", listen_port=51820,
                     routed_networks=None, keepalive=25, mtu=1420, key_file="/etc/wireguard/wg-kuberos.key"):  # fmt: skip
    hosts = {name: dict(hostvars[name].get("wireguard__self") or {}) for name in peers}
    vpn = build_vpn(
        hosts, hub, interface=interface, network=network, listen_port=int(listen_port), routed_networks=routed_networks or [],
        keepalive=int(keepalive), mtu=int(mtu), key_file=key_file,
    )  # fmt: skip
    return wg_quick_config(vpn, host)


class FilterModule:
    def filters(self):
        return {"wireguard_config": wireguard_config}
