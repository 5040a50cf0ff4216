"""Fast DDS discovery under faults, with real rclpy processes in network namespaces (tests/netlab.py).

Two procedures, each returning its figures: the test asserts on them (tests/integration/test_discovery_faults.py)
and the benchmark records them (bench/bench_discovery.py), so both measure the same thing.

- `restart_server`: the fleet's discovery server killed and started again, as a kubelet restarts its container.
  Participants that ran before keep talking; a participant that starts afterwards must meet one that ran before
  (new meets old), and one that ran before must meet one that starts afterwards (old meets new): the second needs the
  restarted server to know the participants it had before, which it does only from its backup (`-b`).
- `cut_off_robot`: a robot's link to the edge server dropped (the edge namespace's bridge port down; the cluster's
  DNS, on the edge, unreachable too), with or without a discovery server on the robot's own computer in the
  modules' ROS_DISCOVERY_SERVER. Onboard talker and listener matched before the cut; an onboard listener started
  during it; an edge listener that must hear the robot again after it.

The servers run the rendered discovery server's arguments (`manifests`), the processes a module container's
environment. Every wait is bounded; traffic stays on the namespaces' bridge.
"""

from __future__ import annotations

import os
import re
import signal
import time

from netlab import STARTUP_TIMEOUT, SUBNET, Lab, Process, Processes
from sshlab import run

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import fastdds, manifests, naming
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import DiscoveryServer

OTHER_TOPIC = "/kuberos_other"
FLEET = "fetch"
PORT = 11811
MEET_TIMEOUT = 30.0  # two participants that can meet do so within this, with a server up (test_discovery_netns)
REDISCOVERY_TIMEOUT = 60.0  # three default leases (20 s) after a fault: a participant not met by then never is
SERVER_ROLES = ("edge", "edge2")
MOVED_ROLES = ("edge3", "edge4")  # where server 0, 1 move to (a replaced pod: a new address behind its Service's)
RESTART_ROLES = ("edge", "edge2", "talk", "listen", "late", "talk2", *MOVED_ROLES)
CUT_ROLES = ("edge", "robot", "talk", "listen", "late")


def server_name(server_id: int) -> str:
    """The fleet server's cluster DNS name, as modules' ROS_DISCOVERY_SERVER names it."""
    return naming.discovery_server_address(naming.fleet_namespace(FLEET), server_id, PORT).rsplit(":", 1)[0]


def _server(server_id: int) -> DiscoveryServer:
    name = naming.discovery_server_name(server_id)
    return DiscoveryServer(FLEET, naming.fleet_namespace(FLEET), server_id, name, "edge", "edge", PORT, "")


def _service_links(addresses: dict[int, str]) -> dict[str, str]:
    """The Services' links as the kubelet sets them: server id -> the address standing for its Service's."""
    return {naming.service_host_variable(_server(i).name): address for i, address in addresses.items()}


def server_container(server_id: int) -> dict:
    """The rendered discovery server's container (its args and environment)."""
    objects = manifests._discovery_objects(_server(server_id), manifests.RenderOptions())
    (deployment,) = [o for o in objects if o["kind"] == "Deployment"]
    return deployment["spec"]["template"]["spec"]["containers"][0]


def server_command(server_id: int, backup: bool, delay_s: int | None = None) -> list[str]:
    """The rendered discovery server's container arguments, with or without its backup (``-b``); ``delay_s``
    replaces its start delay (0: a server that serves at once, as rendered before the delay)."""
    args = server_container(server_id)["args"] if delay_s is None else manifests.discovery_server_args(server_id, PORT, delay_s)
    return [a for a in args if a != "-b"] + (["-b"] if backup else [])


def server_env(server_id: int, address: str = "") -> dict[str, str]:
    """The rendered discovery server's environment (its Fast DDS profile, no links), its Service's link expanded to
    ``address``, the address it announces (empty: announcing every address of its namespace, as rendered before)."""
    env = {e["name"]: e["value"] for e in server_container(server_id)["env"]}
    links = _service_links({server_id: address})
    return {name: manifests.expand_references(value, links) for name, value in env.items()}


def discovery_servers(addresses: list[str], dns: bool = False) -> str:
    """ROS_DISCOVERY_SERVER for servers 0.. at ``addresses``: as rendered, the Services' links expanded as the kubelet
    does (to these addresses, standing for the cluster IPs), or with ``dns`` their cluster DNS names (what the
    collection rendered before, which /etc/hosts resolves here while the edge is reachable)."""
    if dns:
        return ";".join(f"{server_name(i)}:{PORT}" for i in range(len(addresses)))
    servers = [_server(i) for i in range(len(addresses))]
    links = _service_links(dict(enumerate(addresses)))
    return manifests.expand_references(manifests.discovery_server_list(servers), links)


def module_env(servers: str) -> dict[str, str]:
    """A module container's ROS environment with ROS_DISCOVERY_SERVER ``servers``."""
    return {
        "ROS_DISCOVERY_SERVER": servers,
        "RMW_IMPLEMENTATION": manifests.RMW,
        "ROS_DOMAIN_ID": "0",
        **dict(fastdds.TRANSPORT_ENV),
    }


def start_server(
    procs: Processes,
    name: str,
    role: str,
    server_id: int,
    backup: bool,
    peers: str = "",
    delay_s: int | None = None,
    address: str = "",
) -> Process:
    """A server in its own working directory (its backup file lives there, as in the pod's volume); started again
    under the same name it appends to the same log, and is up when it has said so once more. ``peers``: the other
    servers it connects to (ROS_DISCOVERY_SERVER with its own position empty), sharing what each knows; ``address``:
    the one it announces, its Service's (empty: every address of its namespace)."""
    directory = os.path.join(procs.directory, name)
    os.makedirs(directory, exist_ok=True)
    log = os.path.join(procs.directory, f"{name}.log")
    before = _server_lines(log)
    env = {**server_env(server_id, address), **({"ROS_DISCOVERY_SERVER": peers} if peers else {})}
    process = procs.start(name, role, server_command(server_id, backup, delay_s), env, cwd=directory)
    procs.wait_until(
        lambda: _server_lines(log) > before or process.popen.poll() is not None,
        STARTUP_TIMEOUT,
        f"{name} did not report itself running",
    )
    time.sleep(0.5)  # a server that fails at start fails here (a backup server reading its file: ServerCrashed)
    if process.popen.poll() is not None:
        raise ServerCrashed(f"{name} exited {process.popen.returncode} at start:\n{process.tail(5)}")
    return process


class ServerCrashed(RuntimeError):
    """A discovery server that exited while starting."""


def _server_lines(log: str) -> int:
    if not os.path.exists(log):
        return 0
    with open(log, encoding="utf-8", errors="replace") as handle:
        return len(re.findall(r"Server ID:\s+\d+", handle.read()))


def seconds_until(condition, timeout: float) -> float | None:
    """Seconds until condition() held, None if it did not within timeout."""
    return first_times({"it": condition}, timeout)["it"]


def first_times(conditions: dict, timeout: float, poll: float = 0.1) -> dict[str, float | None]:
    """Seconds from now until each condition first held, polled together (None: not within timeout)."""
    start, found = time.monotonic(), {}
    while time.monotonic() - start < timeout and len(found) < len(conditions):
        for name, condition in conditions.items():
            if name not in found and condition():
                found[name] = round(time.monotonic() - start, 2)
        time.sleep(poll)
    return {name: found.get(name) for name in conditions}


def lost(talker: Process, listener: Process, first: int, last: int) -> int:
    """Messages ``first``..``last`` the talker published that the listener never received."""
    received = set(listener.received())
    return sum(1 for n in talker.published() if first <= n <= last and n not in received)


def linked_peers(addresses: list[str], server_id: int) -> str:
    """What server ``server_id`` of servers at ``addresses`` connects to, as rendered (``manifests.linked_server_list``,
    the Services' links expanded to these addresses): every other one, its own position empty."""
    servers = [_server(i) for i in range(len(addresses))]
    links = _service_links(dict(enumerate(addresses)))
    return manifests.expand_references(manifests.linked_server_list(servers, servers[server_id]), links)


def service_address(server_id: int) -> str:
    """Server ``server_id``'s Service address (its cluster IP): on the lab's subnet, owned by no namespace."""
    return f"{SUBNET}.{250 + server_id}"


def route_service(lab: Lab, server_id: int, role: str) -> None:
    """What kube-proxy does on every node when a Service's endpoint changes, in every namespace of the lab: UDP to
    server ``server_id``'s Service address translated to the address of ``role`` (where its server now runs), and
    the flows tracked to the old one dropped."""
    chain, address = f"KR-SVC-{server_id}", service_address(server_id)
    for namespace in lab.namespaces.values():
        iptables = ["ip", "netns", "exec", namespace, "iptables", "-t", "nat"]
        if run(*iptables, "-F", chain, check=False).returncode != 0:
            run(*iptables, "-N", chain)
            run(*iptables, "-A", "OUTPUT", "-d", address, "-p", "udp", "-j", chain)
        run(*iptables, "-A", chain, "-p", "udp", "-j", "DNAT", "--to-destination", lab.addresses[role])
        run("ip", "netns", "exec", namespace, "conntrack", "-D", "-p", "udp", "--orig-dst", address, check=False)


def restart_server(
    lab: Lab,
    procs: Processes,
    backup: bool,
    down_s: float = 1.0,
    servers: int = 1,
    linked: bool = False,
    together: bool = False,
    wait_s: float = REDISCOVERY_TIMEOUT,
    delay_s: int | None = None,
    stop: signal.Signals = signal.SIGKILL,
    moved: bool = False,
    announce_service: bool = True,
) -> dict:
    """Each edge server in turn killed (``stop``: SIGKILL, or SIGTERM as a kubelet stops a pod: the server says
    goodbye) and started again after ``down_s`` seconds (then 3 s to settle), with or without its backup; with
    ``linked`` each server connects to the others; with ``together`` all are killed and started again at once (one
    node running every server of the fleet). A server started runs the rendered container: it waits its start delay
    (``delay_s`` replaces it; 0 serves at once, as rendered before), announces the rendered lease and its Service's
    address (``announce_service=False``: every address of its namespace, as rendered before). With ``moved`` everyone
    names the servers by their Services' addresses, and each server started again runs in another namespace (a
    replaced pod: a new address behind the same Service's)."""
    homes = list(SERVER_ROLES[:servers])
    if moved:
        addresses = [service_address(i) for i in range(servers)]
        for server_id, role in enumerate(homes):
            route_service(lab, server_id, role)
    else:
        addresses = [lab.addresses[role] for role in homes]
    env = module_env(discovery_servers(addresses))

    def start(server_id):
        peers = linked_peers(addresses, server_id) if linked else ""
        address = addresses[server_id] if announce_service else ""
        return start_server(procs, f"server-{server_id}", homes[server_id], server_id, backup, peers, delay_s, address)

    running = [start(i) for i in range(servers)]
    talker = procs.start_talker("talker", "talk", env, period="0.1")
    listener = procs.start_listener("listener", "listen", env)
    old_listener = procs.start_listener("listener-other", "listen", env, OTHER_TOPIC)  # nobody publishes it yet
    if seconds_until(lambda: len(listener.received()) >= 3, MEET_TIMEOUT) is None:
        raise AssertionError(f"talker and listener did not meet before the restart\n{procs.tails()}")
    time.sleep(1.0)  # the server has heard every participant's endpoints, and written them to its backup

    killed_at = (talker.published() or [0])[-1]
    rounds = [list(range(servers))] if together else [[i] for i in range(servers)]
    for ids in rounds:
        for server_id in ids:
            running[server_id].kill(stop)
        time.sleep(down_s)
        try:
            for server_id in ids:
                if moved:
                    homes[server_id] = (MOVED_ROLES if homes[server_id] in SERVER_ROLES else SERVER_ROLES)[server_id]
                    route_service(lab, server_id, homes[server_id])
                start(server_id)
        except ServerCrashed as crash:
            return {"backup": backup, "servers": servers, "linked": linked, "down_s": down_s, "delay_s": delay_s,
                    "crashed": str(crash)}  # fmt: skip
        time.sleep(3.0)
    late = procs.start_listener("listener-late", "late", env)
    new_meets_old = seconds_until(lambda: bool(late.received()), wait_s)
    new_talker = procs.start_talker("talker-new", "talk2", env, OTHER_TOPIC, period="0.1")
    old_meets_new = seconds_until(lambda: bool(old_listener.received()), wait_s)
    settled = talker.published()[-1] - 10  # in flight at the end: not lost
    return {
        "backup": backup,
        "servers": servers,
        "linked": linked,
        "together": together,
        "down_s": down_s,
        "stop": stop.name,
        "moved": moved,
        "announce_service": announce_service,
        "delay_s": manifests.DISCOVERY_START_DELAY_S if delay_s is None else delay_s,
        "crashed": "",
        "new_meets_old_s": new_meets_old,
        "old_meets_new_s": old_meets_new,
        "matched_pair_lost": lost(talker, listener, killed_at, settled),
        "matched_pair_published": settled - killed_at + 1,
        "processes": [p.name for p in (talker, listener, old_listener, late, new_talker) if p.popen.poll() is not None],
    }


ROBOT_SERVER_CHOICES = ("none", "listed", "linked")


def cut_off_robot(
    lab: Lab, procs: Processes, robot_server: str, cut_s: float = 30.0, dns: bool = False, after_s: float = REDISCOVERY_TIMEOUT
) -> dict:
    """A robot cut off from the edge for ``cut_s`` seconds: its onboard pair's messages, an onboard listener started
    during the cut, an edge listener hearing the robot again after it. ``robot_server``: ``none``, the modules name
    the fleet's edge server only; ``listed``, the robot's modules also name a server on the robot (the second of
    their servers); ``linked``, the robot's modules name only the server on the robot, which connects to the edge
    server and shares what it knows. ``dns``: modules name the edge server by its DNS name, which does not resolve
    during the cut (the cluster's DNS runs on the edge). ``after_s``: how long to wait for the rematches after it."""
    if robot_server not in ROBOT_SERVER_CHOICES or (dns and robot_server != "none"):
        raise ValueError(f"robot_server: expected one of {ROBOT_SERVER_CHOICES}, and none with dns")
    names = {server_name(0): lab.addresses["edge"]}
    lab.write_hosts(names)
    edge_env = module_env(discovery_servers([lab.addresses["edge"]], dns=dns))
    both = discovery_servers([lab.addresses["edge"], lab.addresses["robot"]], dns=dns)
    env = {
        "none": edge_env,
        "listed": module_env(both),
        "linked": module_env(";" + both.split(";")[1]),  # the robot's server alone, at its position
    }[robot_server]
    start_server(procs, "edge-server", "edge", 0, backup=False, address=lab.addresses["edge"])
    if robot_server != "none":
        peers = both.split(";")[0] if robot_server == "linked" else ""
        start_server(procs, "robot-server", "robot", 1, backup=False, peers=peers, address=lab.addresses["robot"])
    talker = procs.start_talker("talker", "talk", env, period="0.1")
    listener = procs.start_listener("listener", "listen", env)
    edge = procs.start_listener("listener-edge", "edge", edge_env if robot_server == "linked" else env)
    if seconds_until(lambda: len(listener.received()) >= 3 and len(edge.received()) >= 3, MEET_TIMEOUT) is None:
        raise AssertionError(f"the robot's talker, its listener and the edge listener did not meet\n{procs.tails()}")

    lab.set_connected("edge", False)
    lab.write_hosts({})  # the cluster's DNS runs on the edge: no name resolves during the cut
    cut_at, start = talker.published()[-1], time.monotonic()
    late = procs.start_listener("listener-late", "late", env, wait=False)
    started_during = seconds_until(lambda: bool(late.received()), cut_s)
    time.sleep(max(0.0, cut_s - (time.monotonic() - start)))
    reconnect_at = talker.published()[-1]
    onboard_lost = lost(talker, listener, cut_at, reconnect_at)
    heard_by_edge = len(edge.received())
    late_alive = late.popen.poll() is None

    lab.set_connected("edge", True)
    lab.write_hosts(names)
    conditions = {"edge": lambda: len(edge.received()) > heard_by_edge + 2}
    if started_during is None:
        conditions["late"] = lambda: bool(late.received())
    after = first_times(conditions, after_s)
    edge_rematch, late_after = after["edge"], after.get("late")
    return {
        "robot_server": robot_server,
        "dns": dns,
        "cut_s": cut_s,
        "onboard_published_during": reconnect_at - cut_at + 1,
        "onboard_lost_during": onboard_lost,
        "started_during_first_message_s": started_during,
        "started_during_alive": late_alive,
        "started_during_first_message_after_reconnect_s": late_after,
        "edge_rematch_after_reconnect_s": edge_rematch,
    }
