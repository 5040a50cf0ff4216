"""The latency probe's filters: ping's summary read into round-trip times, and what each robot pings."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.filter.ping_rtt import parse_ping
from ansible_collections.kuberos.platform.plugins.filter.rtt_targets import rtt_targets

# Captured from iputils ping 20221126 (Debian 12) with `ping -n -q -c N -i 0.2 -W 1 ADDRESS`, between network
# namespaces joined by a veth pair; the address of the 100% loss sample has no host behind it.
REACHABLE = """PING 10.213.9.2 (10.213.9.2) 56(84) bytes of data.

--- 10.213.9.2 ping statistics ---
3 packets transmitted, 3 received, 0% packet loss, time 411ms
rtt min/avg/max/mdev = 0.038/0.043/0.047/0.003 ms
"""
ALL_LOST = """PING 10.213.9.99 (10.213.9.99) 56(84) bytes of data.

--- 10.213.9.99 ping statistics ---
5 packets transmitted, 0 received, 100% packet loss, time 819ms

"""
HOST_UNKNOWN_STDERR = "ping: nohost.invalid: Name or service not known\n"
NO_RESOLVER_STDERR = "ping: nohost.invalid: Temporary failure in name resolution\n"
NO_ROUTE_STDERR = "ping: connect: Network is unreachable\n"
IPV6 = """PING ::1(::1) 56 data bytes

--- ::1 ping statistics ---
3 packets transmitted, 3 received, 0% packet loss, time 406ms
rtt min/avg/max/mdev = 0.030/0.032/0.035/0.002 ms
"""
# The same summary lines as iputils prints them with errors (ICMP host unreachable after failed ARP),
# with partial loss, and in the BusyBox and BSD/macOS formats.
ERRORS = """--- 10.0.0.7 ping statistics ---
5 packets transmitted, 0 received, +5 errors, 100% packet loss, time 4081ms
pipe 3
"""
PARTIAL = """--- 10.0.0.2 ping statistics ---
10 packets transmitted, 7 received, +1 duplicates, 30% packet loss, time 1837ms
rtt min/avg/max/mdev = 3.104/4.200/9.871/1.002 ms, pipe 2
"""
BUSYBOX = """PING 10.0.0.2 (10.0.0.2): 56 data bytes

--- 10.0.0.2 ping statistics ---
3 packets transmitted, 3 packets received, 0% packet loss
round-trip min/avg/max = 0.069/0.087/0.105 ms
"""
BSD = """--- 10.0.0.2 ping statistics ---
5 packets transmitted, 5 packets received, 0.0% packet loss
round-trip min/avg/max/stddev = 37.912/38.514/39.020/0.402 ms
"""


def command_result(stdout="", stderr="", rc=0, msg=""):
    """What ansible.builtin.command registers."""
    return {"stdout": stdout.rstrip("\n"), "stderr": stderr.rstrip("\n"), "rc": rc, "msg": msg, "cmd": ["ping", "-n", "x"]}


def test_reachable_target_gives_the_average_round_trip_time():
    parsed = parse_ping(command_result(REACHABLE))
    assert parsed["status"] == "ok" and parsed["reachable"] is True
    assert (parsed["min_ms"], parsed["avg_ms"], parsed["max_ms"]) == (0.038, 0.043, 0.047)
    assert (parsed["transmitted"], parsed["received"], parsed["loss_percent"]) == (3, 3, 0.0)
    assert parsed["message"] == "0.043 ms (3/3 replies)"


def test_plain_text_is_read_like_a_command_result():
    assert parse_ping(REACHABLE) == parse_ping(command_result(REACHABLE))
    assert parse_ping(IPV6)["avg_ms"] == 0.032


def test_all_lost_is_missing_not_zero():
    parsed = parse_ping(command_result(ALL_LOST, rc=1, msg="non-zero return code"))
    assert parsed["status"] == "lost" and parsed["reachable"] is False
    assert parsed["avg_ms"] is None  # never 0: a lost target must not look like the robot's own computer
    assert (parsed["transmitted"], parsed["received"], parsed["loss_percent"]) == (5, 0, 100.0)
    assert parsed["message"] == "100% packet loss, 5 sent"


def test_errors_in_the_summary_are_lost_too():
    parsed = parse_ping(ERRORS)
    assert parsed["status"] == "lost" and parsed["avg_ms"] is None and parsed["transmitted"] == 5


@pytest.mark.parametrize("stderr", [HOST_UNKNOWN_STDERR, NO_RESOLVER_STDERR, "ping: bad address 'nohost'\n"])
def test_unknown_host_is_unresolved(stderr):
    parsed = parse_ping(command_result(stderr=stderr, rc=2, msg="non-zero return code"))
    assert parsed["status"] == "unresolved" and parsed["avg_ms"] is None and parsed["transmitted"] is None
    assert parsed["message"] == stderr.strip()


def test_no_route_is_unreachable():
    parsed = parse_ping(command_result(stderr=NO_ROUTE_STDERR, rc=2))
    assert parsed["status"] == "unreachable" and parsed["message"] == "ping: connect: Network is unreachable"


def test_partial_loss_keeps_the_average_of_the_replies():
    parsed = parse_ping(PARTIAL)
    assert parsed["status"] == "ok" and parsed["avg_ms"] == 4.2 and parsed["loss_percent"] == 30.0
    assert parsed["received"] == 7


@pytest.mark.parametrize(("text", "avg"), [(BUSYBOX, 0.087), (BSD, 38.514)])
def test_other_ping_formats(text, avg):
    parsed = parse_ping(text)
    assert parsed["status"] == "ok" and parsed["avg_ms"] == avg


@pytest.mark.parametrize(
    ("result", "message"),
    [
        (command_result(rc=2, msg="Error executing command."), "Error executing command: ping -n x"),  # no such program
        (command_result(stderr="ping: socket: Operation not permitted\n", rc=2), "ping: socket: Operation not permitted"),
        (command_result(), "ping printed nothing"),
        (command_result("3 packets transmitted, 3 received, 0% packet loss\n"), "3/3 replies but no round-trip times in"),
    ],
)
def test_ping_that_did_not_run_is_an_error(result, message):
    parsed = parse_ping(result)
    assert parsed["status"] == "error" and parsed["avg_ms"] is None and parsed["reachable"] is False
    assert parsed["message"].startswith(message)


def test_anything_else_is_refused():
    with pytest.raises(AnsibleFilterError, match="expected a command result"):
        parse_ping(42)


# --- rtt_targets ------------------------------------------------------------------------------------------


def hostvars_of(raw, **extra):
    return {host: {**values, **extra.get(host.replace("-", "_"), {})} for host, values in raw["hosts"].items()}


def test_targets_are_the_edge_and_cloud_nodes_the_fleet_may_use(local_raw):
    plan = rtt_targets(local_raw, hostvars_of(local_raw), "fetch-1")
    assert (plan["robot"], plan["fleet"], plan["node"]) == ("fetch-1", "test-fleet", "fetch-1")
    # edge-3 serves warehouse-fleet only; other robots' computers are never targets.
    assert [(t["name"], t["tier"]) for t in plan["targets"]] == [
        ("cloud-1", "cloud"),
        ("cloud-2", "cloud"),
        ("edge-1", "edge"),
        ("edge-2", "edge"),
    ]
    assert {t["name"] for t in rtt_targets(local_raw, hostvars_of(local_raw), "tiago-1")["targets"]} >= {"edge-3"}


def test_target_address_is_kuberos_address_else_ansible_host_else_the_name(local_raw):
    hostvars = hostvars_of(
        local_raw, edge_1={"kuberos_address": "10.0.0.2", "ansible_host": "edge-1.site"}, edge_2={"ansible_host": "192.0.2.5"}
    )
    addresses = {t["name"]: t["address"] for t in rtt_targets(local_raw, hostvars, "fetch-2")["targets"]}
    assert addresses == {"edge-1": "10.0.0.2", "edge-2": "192.0.2.5", "cloud-1": "cloud-1", "cloud-2": "cloud-2"}


def test_chosen_targets(local_raw):
    plan = rtt_targets(local_raw, hostvars_of(local_raw), "fetch-2", ["edge-2", "cloud-1"])
    assert [t["name"] for t in plan["targets"]] == ["cloud-1", "edge-2"]


def test_unknown_target_or_robot_is_named(local_raw):
    with pytest.raises(AnsibleFilterError, match=r"'edge-9' is not a host of the edge or cloud groups; did you mean 'edge-\d'"):
        rtt_targets(local_raw, hostvars_of(local_raw), "fetch-2", ["edge-9"])
    with pytest.raises(AnsibleFilterError, match="'fetch-1' is not a host of the edge or cloud groups"):
        rtt_targets(local_raw, hostvars_of(local_raw), "fetch-2", ["fetch-1"])
    with pytest.raises(AnsibleFilterError, match="edge-1 is not a host of the robots group"):
        rtt_targets(local_raw, hostvars_of(local_raw), "edge-1")


def test_node_names_key_the_measurements(local_raw):
    raw = {**local_raw, "hosts": {**local_raw["hosts"], "edge-1": {**local_raw["hosts"]["edge-1"], "kuberos_node_name": "srv-a"}}}
    names = {t["host"]: t["name"] for t in rtt_targets(raw, hostvars_of(raw), "fetch-1")["targets"]}
    assert names["edge-1"] == "srv-a"
