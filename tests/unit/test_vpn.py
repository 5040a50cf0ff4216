"""The VPN model: wg-quick configurations of the hub and the spokes, and every problem of a bad VPN at once."""

from __future__ import annotations

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.vpn import build_vpn, wg_quick_config

KEYS = {
    "edge-1": "Ej8k9GLVGs4akKTXsu7XF60Qj95y6GfVkshIMlYy2Q0=",
    "cloud-1": "xTIBA5rboUvnH4htodjb6e697QjLERt1NAB4mZqp8Dg=",
    "cloud-2": "TrMvSoP4jYQlY6RIzBgbssQqY3vxI2Pi+y71lOWWXX0=",
}


def hosts(**changes):
    base = {
        "edge-1": {"address": "10.100.0.1", "public_key": KEYS["edge-1"], "endpoint": "192.0.2.10:51820"},
        "cloud-1": {"address": "10.100.0.11", "public_key": KEYS["cloud-1"]},
        "cloud-2": {"address": "10.100.0.12", "public_key": KEYS["cloud-2"]},
    }
    for name, values in changes.items():
        base[name] = {**base.get(name, {}), **values}
    return base


def test_hub_has_a_peer_per_spoke_allowed_its_address_only():
    config = wg_quick_config(build_vpn(hosts(), "edge-1"), "edge-1")
    assert "Address = 10.100.0.1/24" in config and "ListenPort = 51820" in config
    assert config.count("[Peer]") == 2
    assert f"PublicKey = {KEYS['cloud-1']}\nAllowedIPs = 10.100.0.11/32" in config
    assert f"PublicKey = {KEYS['cloud-2']}\nAllowedIPs = 10.100.0.12/32" in config
    assert "Endpoint" not in config and "PersistentKeepalive" not in config


def test_spoke_reaches_the_tunnel_and_the_site_through_the_hub():
    vpn = build_vpn(hosts(), "edge-1", routed_networks=["192.168.10.0/24"], keepalive=15, mtu=1380)
    config = wg_quick_config(vpn, "cloud-1")
    assert config.count("[Peer]") == 1 and "ListenPort" not in config
    assert f"PublicKey = {KEYS['edge-1']}" in config
    assert "Endpoint = 192.0.2.10:51820" in config
    assert "AllowedIPs = 10.100.0.0/24, 192.168.10.0/24" in config
    assert "PersistentKeepalive = 15" in config and "MTU = 1380" in config


def test_no_private_key_in_any_configuration():
    vpn = build_vpn(hosts(), "edge-1", key_file="/etc/wireguard/wg-kuberos.key")
    for name in KEYS:
        config = wg_quick_config(vpn, name)
        assert "PrivateKey" not in config
        assert "PostUp = wg set %i private-key /etc/wireguard/wg-kuberos.key" in config


def test_keepalive_zero_is_off():
    assert "PersistentKeepalive" not in wg_quick_config(build_vpn(hosts(), "edge-1", keepalive=0), "cloud-2")


BAD = [
    (
        {"cloud-1": {"address": "10.200.0.11"}},
        {},
        "hosts.cloud-1.kuberos_vpn_address: 10.200.0.11 is outside wireguard_network 10.100.0.0/24",
    ),
    (
        {"cloud-2": {"address": "10.100.0.11"}},
        {},
        "hosts.cloud-2.kuberos_vpn_address: 10.100.0.11 is also the address of cloud-1",
    ),
    ({"cloud-1": {"address": ""}}, {}, "hosts.cloud-1.kuberos_vpn_address: '' is not an IP address"),
    ({"cloud-1": {"address": "10.100.0.255"}}, {}, "is the network or broadcast address"),
    ({"cloud-1": {"public_key": "not-a-key"}}, {}, "hosts.cloud-1.public_key: 'not-a-key' is not a WireGuard public key"),
    ({"edge-1": {"endpoint": "192.0.2.10"}}, {}, "wireguard_hub_endpoint: '192.0.2.10': expected host:port"),
    ({}, {"network": "10.100.0.1/24"}, "wireguard_network: '10.100.0.1/24' is not a network"),
    ({}, {"interface": "wireguard-kuberos-vpn"}, "wireguard_interface: 'wireguard-kuberos-vpn' is not an interface name"),
    ({}, {"listen_port": 70000}, "wireguard_listen_port: 70000 is not a UDP port"),
    ({}, {"mtu": 500}, "wireguard_mtu: 500: expected 1280-9000"),
    ({}, {"routed_networks": ["192.168.10.5/24"]}, "wireguard_hub_routed_networks[0]: '192.168.10.5/24' is not a network"),
]


@pytest.mark.parametrize(("changes", "options", "expected"), BAD, ids=[b[2][:40] for b in BAD])
def test_bad_vpn_is_refused_with_the_field_and_reason(changes, options, expected):
    with pytest.raises(SpecError) as caught:
        build_vpn(hosts(**changes), "edge-1", **options)
    assert expected in str(caught.value)
    assert str(caught.value).startswith("the WireGuard VPN is not valid")


def test_unknown_hub_suggests_a_name():
    with pytest.raises(SpecError, match=r"wireguard_hub: 'edge1' is not a host of the VPN .*did you mean 'edge-1'"):
        build_vpn(hosts(), "edge1")


def test_missing_hub_points_at_the_group():
    with pytest.raises(SpecError, match="put the edge gateway in the inventory group vpn_gateway"):
        build_vpn(hosts(), "")


def test_a_hub_alone_is_not_a_vpn():
    with pytest.raises(SpecError, match="only the hub edge-1: expected at least one spoke"):
        build_vpn({"edge-1": hosts()["edge-1"]}, "edge-1")


def test_every_problem_is_reported_at_once():
    with pytest.raises(SpecError) as caught:
        build_vpn(hosts(**{"cloud-1": {"address": "10.9.9.9"}, "cloud-2": {"public_key": "x"}}), "edge-1", mtu=10)
    assert len(caught.value.problems) == 3


def test_a_host_outside_the_vpn_has_no_configuration():
    with pytest.raises(SpecError, match="'cloud-9' is not a host of the VPN"):
        wg_quick_config(build_vpn(hosts(), "edge-1"), "cloud-9")
