"""Cyclone DDS without multicast, configured with unicast peer lists, proven with real processes in network namespaces.

For Cyclone DDS a module instance gets a Service (`<instance>.<namespace>.svc.cluster.local`) and the
configuration `kuberos.cyclonedds.config_xml(peers)` renders from the names of the instances it talks with,
named by CYCLONEDDS_URI. Here that configuration is written unchanged to a file per instance, and the
participants are real Cyclone DDS processes: tests/integration/ros/cyclone_chatter.py, written with Cyclone
DDS's own Python binding (PyPI cyclonedds, whose wheel bundles libddsc), not rclpy: PyPI has no
rmw_cyclonedds_cpp wheel. They run in network namespaces on a bridge that floods no multicast
(tests/netlab.py), each with a private /dev/shm; /etc/netns/<ns>/hosts answers the Services' names as
cluster DNS would.

Names resolving to the pods' own addresses (a headless Service):

- The negative control: with the bridge flooding no multicast, participants on Cyclone's defaults
  (multicast discovery) never meet; they meet once it floods multicast again, while participants with the
  rendered configuration and no peers still never meet (the configuration really turns multicast off).
- With each other's names as peers, a talker and a listener meet and every reliable message arrives.
- A module that moves: the talker stops (or is killed) and starts again in a third namespace, its name
  now resolving there. The listener keeps running with its configuration, whose entry for the talker
  Cyclone resolved once, at start, to the old address. It still hears the new talker, because the new
  talker's list names the listener: its SPDP reaches the listener, which learns the new address from it.
  Without that entry (a peer list that is not symmetric) they never meet, which shows it.
- Cyclone DDS 11 aborts a process whose configured peer name does not resolve.

Names resolving to a ClusterIP Service's virtual IP, as the renderer has it (`KubeProxy` below: kube-proxy's
iptables mode in every namespace, DNAT of the Service's SPDP ports to the pod that runs the instance, REJECT
while it has none, conntrack entries deleted when the endpoint changes):

- A talker and a listener meet through each other's Service and every reliable message arrives.
- A talker that moves (endpoint updated, listener not restarted) is heard again, because its SPDP to the
  listener's Service reaches the listener. Without the listener in its list it is never heard: Cyclone sends
  SPDP to a configured peer only as the participant starts (3 or 6 packets to each of the 32 ports, all
  within 0.3 s here), never again. A Service's address is never a discovered participant's, so it stays
  an "aging" initial locator, due again 30 s later but pruned first, 30 s after the start
  (Discovery/InitialLocatorPruneDelay). The listener sends nothing to the talker's Service after the move
  (its DNAT rules count 0 packets).
- A peer whose pod does not exist yet: its name resolves (to the Service), so the participant starts and
  keeps running (its SPDP to the Service is rejected, silently); when the peer starts, 2 s later or after
  the first participant pruned its locators, they meet at once, through the later one's SPDP to the first
  one's Service. If the later one's list does not name the first, they never meet.

So the Service makes every name resolve and reaches whichever pod runs an instance when a participant starts;
a move is still noticed only through symmetric peer lists.

Needs root and `ip netns` (skipped otherwise), iptables and conntrack for the Service tests (skipped
otherwise), and cyclonedds from requirements.txt in the venv (fails otherwise). Traffic stays between the
namespaces this module creates; every wait is bounded.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import pytest
from netlab import Lab, Process, Processes, open_lab
from sshlab import LabError, run

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import cyclonedds
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import ros_environment

pytestmark = pytest.mark.ros

CHATTER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "ros", "cyclone_chatter.py")
TOPIC = "kuberos_chatter"
DOMAIN_ID = 7
# The names of the instances' Services: <instance>.<namespace>.svc.<cluster domain>.
TALKER = "demo-fetch-controller-fetch-1.kuberos-demo.svc.cluster.local"
LISTENER = "demo-fetch-motion-planner-fetch-1.kuberos-demo.svc.cluster.local"
COUNT = 50  # reliable messages a talker writes
STARTUP_TIMEOUT = 20.0  # a process printing that it is up
DISCOVERY_TIMEOUT = 30.0  # a listener receiving every message
NEGATIVE_WINDOW = 8.0  # how long participants get to (wrongly) meet; unicast peers meet in well under a second


@functools.cache
def cyclonedds_problem() -> str | None:
    check = "import cyclonedds.domain, cyclonedds.idl, cyclonedds.pub, cyclonedds.sub"
    done = subprocess.run([sys.executable, "-c", check], env=ros_environment(), capture_output=True, text=True, timeout=60)
    return None if done.returncode == 0 else done.stderr[-2000:]


def require_cyclonedds() -> None:
    problem = cyclonedds_problem()
    if problem:
        pytest.fail(
            f"the Cyclone DDS Python binding is not usable from {sys.prefix}; install it with "
            f"`{sys.prefix}/bin/pip install -r requirements.txt`.\n{problem}",
            pytrace=False,
        )


@pytest.fixture(scope="module")
def lab(request) -> Lab:
    lab = open_lab(request, "talk")
    for role in ("listen", "moved", "other"):
        lab.add(role)
    return lab


@pytest.fixture
def procs(lab, tmp_path):
    processes = Processes(lab, str(tmp_path))
    yield processes
    processes.close()


def resolve(lab: Lab, talker_role: str) -> None:
    """The Services' names, as cluster DNS would answer them: the talker's in talker_role, the listener's in listen."""
    lab.write_hosts({TALKER: lab.addresses[talker_role], LISTENER: lab.addresses["listen"]})


def instance_env(procs: Processes, instance: str, peers: list[str]) -> dict[str, str]:
    """A module container's environment: the rendered configuration in a file of its own, and the domain."""
    path = os.path.join(procs.directory, f"{instance}.xml")
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(cyclonedds.config_xml(peers, domain_id=DOMAIN_ID))
    return {"CYCLONEDDS_URI": f"file://{path}", "ROS_DOMAIN_ID": str(DOMAIN_ID)}


def start(procs: Processes, name: str, role: str, env: dict[str, str], *args: str) -> Process:
    process = procs.start(name, role, [sys.executable, CHATTER, *args], env)
    procs.wait_until(lambda: "ready" in process.output().split("\n"), STARTUP_TIMEOUT, f"{name} did not start", poll=0.02)
    return process


def start_talker(procs: Processes, name: str, role: str, env: dict[str, str], first: int = 1) -> Process:
    return start(procs, name, role, env, "talk", TOPIC, str(COUNT), str(first))


def start_listener(procs: Processes, name: str, role: str, env: dict[str, str]) -> Process:
    return start(procs, name, role, env, "listen", TOPIC)


def matched_after(talker: Process) -> str:
    lines = [line for line in talker.output().splitlines() if line.startswith("matched after ")]
    return lines[0].removeprefix("matched after ") if lines else "never"


def never_meet(procs: Processes, pairs: list[tuple[Process, Process]], window: float, why: str) -> None:
    """For window seconds, no listener of pairs receives and no talker matches; all of them keep running."""
    deadline = time.monotonic() + window
    while time.monotonic() < deadline:
        for talker, listener in pairs:
            assert not listener.received(), f"{listener.name} received {why}\n{procs.tails()}"
            assert matched_after(talker) == "never", f"{talker.name} matched a reader {why}\n{procs.tails()}"
        time.sleep(0.2)
    exited = [p.name for pair in pairs for p in pair if p.popen.poll() is not None]
    assert not exited, f"{exited} exited\n{procs.tails()}"


# --- the rendered configuration ---------------------------------------------------------------------------


def test_config_xml_lists_each_peer_once_sorted_and_escaped():
    xml = cyclonedds.config_xml(["b.ns.svc.cluster.local", 'a"<&>.example', "b.ns.svc.cluster.local"], domain_id=3)
    root = ET.fromstring(xml.split("\n", 1)[1])  # ElementTree refuses the declaration's encoding in a str
    namespace = {"c": "https://cdds.io/config"}
    assert root.find("c:Domain", namespace).get("Id") == "3"
    assert root.findtext("c:Domain/c:General/c:AllowMulticast", namespaces=namespace) == "false"
    assert root.findtext("c:Domain/c:Discovery/c:ParticipantIndex", namespaces=namespace) == "auto"
    assert root.findtext("c:Domain/c:Discovery/c:MaxAutoParticipantIndex", namespaces=namespace) == "31"
    peers = root.findall("c:Domain/c:Discovery/c:Peers/c:Peer", namespace)
    assert [p.get("Address") for p in peers] == ['a"<&>.example', "b.ns.svc.cluster.local"]
    assert xml == cyclonedds.config_xml(["b.ns.svc.cluster.local", 'a"<&>.example'], domain_id=3)
    for wrong in ({"max_participants": 0}, {"max_participants": 121}, {"domain_id": -1}, {"domain_id": 233}):
        with pytest.raises(ValueError):
            cyclonedds.config_xml([], **wrong)


# --- real participants ------------------------------------------------------------------------------------


def test_negative_control_without_peers_or_multicast_participants_never_meet(procs, lab):
    """Multicast is really blocked by the bridge, and really turned off by the rendered configuration."""
    require_cyclonedds()
    defaults = {"ROS_DOMAIN_ID": str(DOMAIN_ID)}  # no CYCLONEDDS_URI: Cyclone's defaults, multicast discovery
    multicast = (
        start_talker(procs, "talker-multicast", "talk", defaults),
        start_listener(procs, "listener-multicast", "listen", defaults),
    )
    no_peers = instance_env(procs, "no-peers", [])
    unicast = (
        start_talker(procs, "talker-no-peers", "moved", no_peers),
        start_listener(procs, "listener-no-peers", "other", no_peers),
    )
    never_meet(procs, [multicast, unicast], NEGATIVE_WINDOW, "while the bridge floods no multicast")

    # The control's control: the multicast pair meets as soon as the bridge floods multicast, the pair configured
    # without multicast and without peers still does not.
    lab.set_multicast_flood(True)
    try:
        seconds = procs.wait_until(lambda: multicast[1].received(), DISCOVERY_TIMEOUT, "multicast discovery failed")
        never_meet(procs, [unicast], NEGATIVE_WINDOW, "with multicast disabled in its configuration")
    finally:
        lab.set_multicast_flood(False)
    print(
        f"no discovery in {NEGATIVE_WINDOW:.0f} s without multicast; with multicast, Cyclone's defaults meet after "
        f"{seconds:.1f} s and the rendered configuration without peers still not in {NEGATIVE_WINDOW:.0f} s"
    )


def test_participants_meet_through_their_peer_lists_and_every_reliable_message_arrives(procs, lab):
    require_cyclonedds()
    resolve(lab, "talk")
    listener = start_listener(procs, "listener", "listen", instance_env(procs, "listener", [TALKER]))
    started = time.monotonic()
    talker = start_talker(procs, "talker", "talk", instance_env(procs, "talker", [LISTENER]))
    procs.wait_until(lambda: listener.received(), DISCOVERY_TIMEOUT, "the listener received nothing", poll=0.02)
    first = time.monotonic() - started
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, f"not all {COUNT} messages arrived", poll=0.02)
    every = time.monotonic() - started
    assert listener.received() == list(range(1, COUNT + 1)), procs.tails()
    procs.wait_until(lambda: f"acknowledged {COUNT}" in talker.output(), DISCOVERY_TIMEOUT, "the talker got no acks")
    print(
        f"talker matched the listener {matched_after(talker)} after creating its participant; the listener had the first "
        f"message {first:.2f} s and all {COUNT} {every:.2f} s after the talker's process was started"
    )


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGKILL], ids=["stopped", "killed"])
def test_the_listener_hears_a_talker_that_moved_under_the_same_name(procs, lab, stop):
    require_cyclonedds()
    resolve(lab, "talk")
    listener = start_listener(procs, "listener", "listen", instance_env(procs, "listener", [TALKER]))
    talker_env = instance_env(procs, "talker", [LISTENER])
    old = start_talker(procs, "talker", "talk", talker_env)
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, "the talker was not heard before it moved")

    old.kill(stop)
    resolve(lab, "moved")  # the Service's name follows the new pod, before it starts
    started = time.monotonic()
    new = start_talker(procs, "talker-moved", "moved", talker_env, first=1001)
    procs.wait_until(
        lambda: 1001 in listener.received(), DISCOVERY_TIMEOUT, "the listener did not hear the moved talker", poll=0.02
    )
    seconds = time.monotonic() - started
    procs.wait_until(lambda: len(listener.received()) >= 2 * COUNT, DISCOVERY_TIMEOUT, "not every message of the moved talker")
    assert listener.received() == [*range(1, COUNT + 1), *range(1001, 1001 + COUNT)], procs.tails()
    assert listener.popen.poll() is None, procs.tails()
    print(
        f"talker {signal.Signals(stop).name}, restarted at {lab.addresses['moved']}: it matched the listener "
        f"{matched_after(new)} after creating its participant; the listener had its first message {seconds:.2f} s after "
        "its process was started"
    )


def test_the_listener_does_not_resolve_the_moved_talkers_name_again(procs, lab):
    """What makes the move work: the moved talker's peer list. Without the listener in it, they never meet."""
    require_cyclonedds()
    resolve(lab, "talk")
    listener = start_listener(procs, "listener", "listen", instance_env(procs, "listener", [TALKER]))
    old = start_talker(procs, "talker", "talk", instance_env(procs, "talker", [LISTENER]))
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, "the talker was not heard before it moved")
    old.kill()
    resolve(lab, "moved")
    new = start_talker(procs, "talker-moved", "moved", instance_env(procs, "talker-no-peers", []), first=1001)
    deadline = time.monotonic() + NEGATIVE_WINDOW
    while time.monotonic() < deadline:
        assert max(listener.received()) == COUNT and matched_after(new) == "never", procs.tails()
        time.sleep(0.2)
    assert listener.popen.poll() is None and new.popen.poll() is None, procs.tails()


def test_a_peer_name_that_does_not_resolve_aborts_the_process(procs, lab):
    """Cyclone DDS 11 resolves peer names once, at start, and aborts (SIGABRT) if one does not resolve."""
    require_cyclonedds()
    resolve(lab, "talk")
    env = instance_env(procs, "unresolvable", [TALKER, "nowhere.kuberos-demo.svc.cluster.local"])
    process = procs.start("unresolvable", "other", [sys.executable, CHATTER, "listen", TOPIC], env)
    procs.wait_until(lambda: process.popen.poll() is not None, STARTUP_TIMEOUT, "a participant with an unknown peer kept running")
    assert process.popen.returncode == -signal.SIGABRT, procs.tails()
    assert "add_peer_address: nowhere.kuberos-demo.svc.cluster.local: unknown address" in process.output(), procs.tails()
    assert "ready" not in process.output().split("\n"), procs.tails()


# --- behind ClusterIP Services, as the renderer has it ----------------------------------------------------

SERVICE_RANGE = "10.213.8"  # the Services' virtual IPs: no interface holds them, as none holds a cluster's
VIPS = {TALKER: f"{SERVICE_RANGE}.10", LISTENER: f"{SERVICE_RANGE}.11"}
SPDP_PORTS = cyclonedds.discovery_ports(DOMAIN_ID)  # what the renderer's Service forwards
PRUNE_TIMEOUT = 45.0  # Cyclone prunes a participant's configured peer locators 30 s after it started
AFTER_PRUNE = 3.0  # how much longer a pair gets to (wrongly) meet once those locators are gone


class KubeProxy:
    """kube-proxy's iptables mode in every namespace of a Lab (each is a node and its pod at once).

    - nat KUBE-SERVICES, jumped to from OUTPUT (what a pod sends) and PREROUTING (what a node forwards): for
      each port of a Service with an endpoint `-d <VIP> -p udp --dport P -j DNAT --to-destination <pod>:P`.
      (kube-proxy goes through a KUBE-SVC- and a KUBE-SEP- chain per Service; with one endpoint, to this.)
    - filter KUBE-SERVICES, jumped to from OUTPUT and FORWARD for new flows: each port of a Service without
      endpoints REJECTs (icmp-port-unreachable).
    - sync() rewrites both chains at once (iptables-restore --noflush, as kube-proxy does) and deletes the UDP
      conntrack entries of each Service whose endpoint changed (kube-proxy deletes those of a stale endpoint,
      and all of a Service's when it gets its first): else a flow begun before would go on to the old pod.
    - No SNAT: kube-proxy masquerades only traffic from outside the pod network and a pod reaching itself.
    - A route to the Service range through eth0 (in a pod, its default route): without it sendto() fails
      (ENETUNREACH, Cyclone logs "ddsi_udp_conn_write ... failed") before the nat table sees the packet.
    """

    def __init__(self, lab: Lab):
        self.lab, self.endpoints = lab, {}

    def install(self) -> None:
        for namespace in self.lab.namespaces.values():
            run("ip", "-n", namespace, "route", "add", f"{SERVICE_RANGE}.0/24", "dev", "eth0")
            self._restore(
                namespace,
                nat=[f"-A {chain} -j KUBE-SERVICES" for chain in ("OUTPUT", "PREROUTING")],
                filter=[f"-A {chain} -m conntrack --ctstate NEW -j KUBE-SERVICES" for chain in ("OUTPUT", "FORWARD")],
            )

    def sync(self, endpoints: dict[str, str | None]) -> None:
        """Each Service's endpoint (a pod's address, or None while no pod runs the instance), in every namespace."""
        nat, reject = [], []
        for name, pod in sorted(endpoints.items()):
            for port in SPDP_PORTS:
                match = f"-A KUBE-SERVICES -d {VIPS[name]}/32 -p udp -m udp --dport {port}"
                if pod:
                    nat.append(f"{match} -j DNAT --to-destination {pod}:{port}")
                else:
                    reject.append(f"{match} -j REJECT --reject-with icmp-port-unreachable")
        changed = [name for name in endpoints if endpoints[name] != self.endpoints.get(name, "")]
        for namespace in self.lab.namespaces.values():
            self._restore(namespace, nat=["-F KUBE-SERVICES", *nat], filter=["-F KUBE-SERVICES", *reject])
            for name in changed:
                self.forget(namespace, VIPS[name])
        self.endpoints = dict(endpoints)

    def reset(self, endpoints: dict[str, str | None]) -> None:
        """sync() for a test of its own: every Service's conntrack entries go, whoever's they were."""
        self.endpoints = {}
        self.sync(endpoints)

    def packets(self, role: str, name: str, target: str) -> int:
        """Packets to name's Service that the role's namespace DNATed (a flow's first only) or REJECTed (every one) since
        the last sync."""
        table = "nat" if target == "DNAT" else "filter"
        saved = run("ip", "netns", "exec", self.lab.namespaces[role], "iptables-save", "-c", "-t", table).stdout
        pattern = rf"^\[(\d+):\d+\] -A KUBE-SERVICES -d {re.escape(VIPS[name])}/32 .* -j {target}\b"
        return sum(int(count) for count in re.findall(pattern, saved, re.MULTILINE))

    @staticmethod
    def forget(namespace: str, vip: str) -> None:
        done = run("ip", "netns", "exec", namespace, "conntrack", "-D", "-p", "udp", "--orig-dst", vip, check=False)
        if "flow entries have been deleted" not in done.stderr:  # exit 1 when there were none
            raise LabError(f"conntrack -D in {namespace}: {done.stderr.strip()}")

    @staticmethod
    def _restore(namespace: str, **tables: list[str]) -> None:
        """Lines for each table's KUBE-SERVICES chain (made if missing), in one transaction."""
        lines = [line for table, rules in tables.items() for line in (f"*{table}", ":KUBE-SERVICES - [0:0]", *rules, "COMMIT")]
        run("ip", "netns", "exec", namespace, "iptables-restore", "--noflush", input="\n".join([*lines, ""]))


@pytest.fixture(scope="module")
def proxy(request) -> KubeProxy:
    """A lab of its own (talk, listen, moved) whose names resolve to the Services' VIPs, with kube-proxy."""
    missing = [program for program in ("iptables-restore", "iptables-save", "conntrack") if not shutil.which(program)]
    if missing:
        pytest.skip(f"kube-proxy's iptables mode needs {', '.join(missing)} (Debian: iptables, conntrack)")
    lab = open_lab(request, "talk")
    for role in ("listen", "moved"):
        lab.add(role)
    proxy = KubeProxy(lab)
    try:
        proxy.install()
        proxy.forget(lab.namespaces["talk"], VIPS[TALKER])  # conntrack works here
    except RuntimeError as error:
        pytest.skip(f"iptables or conntrack is not usable in a network namespace here: {error}")
    lab.write_hosts(VIPS)  # the names never change: a Service's address stays while its pods come and go
    return proxy


@pytest.fixture
def service_procs(proxy, tmp_path):
    processes = Processes(proxy.lab, str(tmp_path))
    yield processes
    processes.close()


def traced(env: dict[str, str], path: str) -> dict[str, str]:
    """env with Cyclone's trace of its configuration and discovery in path (a second source: settings unchanged)."""
    tracing = f"<Tracing><Category>config,discovery</Category><OutputFile>{path}</OutputFile></Tracing>"
    return {**env, "CYCLONEDDS_URI": f"{env['CYCLONEDDS_URI']},{tracing}"}


def trace_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as handle:
            return handle.read()
    except FileNotFoundError:
        return ""


def locators_pruned(path: str, name: str) -> float | None:
    """Seconds from Cyclone adding the locators of name's Service (at start) to pruning them, None until it has."""
    text, vip = trace_text(path), re.escape(VIPS[name])
    added = re.search(rf"^(\d+\.\d+) .*add_peer_address: add udp/{vip}:{SPDP_PORTS[0]} \.\.\. :{SPDP_PORTS[-1]} ", text, re.M)
    pruned = re.findall(rf"^(\d+\.\d+) .*spdp: prune loc udp/{vip}:(\d+)", text, re.M)
    if not added or len(pruned) < len(SPDP_PORTS):
        return None
    return max(float(t) for t, _port in pruned) - float(added.group(1))


def never_heard(procs: Processes, listener: Process, talker: Process, heard: int, until, timeout: float, event: str) -> float:
    """Until until() held (event, within timeout) and AFTER_PRUNE longer, listener received no more than the heard it had
    and talker matched no reader; both keep running. Seconds it took."""
    start, done = time.monotonic(), None
    while done is None or time.monotonic() < done + AFTER_PRUNE:
        assert len(listener.received()) == heard, f"{listener.name} heard {talker.name} ({event})\n{procs.tails()}"
        assert matched_after(talker) == "never", f"{talker.name} matched a reader ({event})\n{procs.tails()}"
        assert listener.popen.poll() is None and talker.popen.poll() is None, procs.tails()
        if done is None and until():
            done = time.monotonic()
        if done is None and time.monotonic() - start > timeout:
            pytest.fail(f"{event}: not within {timeout:.0f} s\n{procs.tails()}", pytrace=False)
        time.sleep(0.2)
    return time.monotonic() - start


def test_service_participants_meet_through_each_others_service_and_every_reliable_message_arrives(service_procs, proxy):
    require_cyclonedds()
    procs, lab = service_procs, proxy.lab
    proxy.reset({TALKER: lab.addresses["talk"], LISTENER: lab.addresses["listen"]})
    listener = start_listener(procs, "listener", "listen", instance_env(procs, "listener", [TALKER]))
    started = time.monotonic()
    talker = start_talker(procs, "talker", "talk", instance_env(procs, "talker", [LISTENER]))
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, f"not all {COUNT} messages arrived", poll=0.02)
    every = time.monotonic() - started
    assert listener.received() == list(range(1, COUNT + 1)), procs.tails()
    procs.wait_until(lambda: f"acknowledged {COUNT}" in talker.output(), DISCOVERY_TIMEOUT, "the talker got no acks")
    # Each reached the other's pod through the other's Service: the names resolve to nothing else.
    assert proxy.packets("talk", LISTENER, "DNAT") > 0 and proxy.packets("listen", TALKER, "DNAT") > 0, procs.tails()
    print(
        f"through Services: the talker matched the listener {matched_after(talker)} after creating its participant; "
        f"all {COUNT} messages arrived {every:.2f} s after the talker's process was started"
    )


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGKILL], ids=["stopped", "killed"])
def test_service_a_moved_talker_is_heard_by_the_listener_it_names(service_procs, proxy, stop):
    require_cyclonedds()
    procs, lab = service_procs, proxy.lab
    proxy.reset({TALKER: lab.addresses["talk"], LISTENER: lab.addresses["listen"]})
    listener = start_listener(procs, "listener", "listen", instance_env(procs, "listener", [TALKER]))
    talker_env = instance_env(procs, "talker", [LISTENER])
    old = start_talker(procs, "talker", "talk", talker_env)
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, "the talker was not heard before it moved")

    old.kill(stop)
    proxy.sync({TALKER: lab.addresses["moved"], LISTENER: lab.addresses["listen"]})  # the new pod is the endpoint
    started = time.monotonic()
    new = start_talker(procs, "talker-moved", "moved", talker_env, first=1001)
    procs.wait_until(
        lambda: 1001 in listener.received(), DISCOVERY_TIMEOUT, "the listener did not hear the moved talker", poll=0.02
    )
    seconds = time.monotonic() - started
    procs.wait_until(lambda: len(listener.received()) >= 2 * COUNT, DISCOVERY_TIMEOUT, "not every message of the moved talker")
    assert listener.received() == [*range(1, COUNT + 1), *range(1001, 1001 + COUNT)], procs.tails()
    assert listener.popen.poll() is None, procs.tails()
    assert proxy.packets("moved", LISTENER, "DNAT") > 0, procs.tails()  # it found the listener through its Service
    assert proxy.packets("listen", TALKER, "DNAT") == 0, procs.tails()  # and not the other way round
    print(
        f"talker {signal.Signals(stop).name}, restarted behind its Service at {lab.addresses['moved']}: it matched the "
        f"listener {matched_after(new)} after creating its participant; the listener had its first message {seconds:.2f} s "
        "after its process was started"
    )


def test_service_a_moved_talker_whose_list_does_not_name_the_listener_is_never_heard(service_procs, proxy):
    """The listener's SPDP to the talker's Service as it starts is all it ever sends there (see the module's docstring).

    Were the rendered Peer elements given PruneDelay="inf" (Cyclone 11 takes it), the listener would go on sending
    SPDP to the Service every 30 s and hear the moved talker then (about 30 s after it started): this would fail.
    """
    require_cyclonedds()
    procs, lab = service_procs, proxy.lab
    proxy.reset({TALKER: lab.addresses["talk"], LISTENER: lab.addresses["listen"]})
    trace = os.path.join(procs.directory, "listener.trace")
    listener = start_listener(procs, "listener", "listen", traced(instance_env(procs, "listener", [TALKER]), trace))
    old = start_talker(procs, "talker", "talk", instance_env(procs, "talker", [LISTENER]))
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, "the talker was not heard before it moved")
    assert proxy.packets("listen", TALKER, "DNAT") > 0, procs.tails()  # the listener did probe the talker's Service

    old.kill()
    proxy.sync({TALKER: lab.addresses["moved"], LISTENER: lab.addresses["listen"]})
    new = start_talker(procs, "talker-moved", "moved", instance_env(procs, "talker-no-peers", []), first=1001)
    waited = never_heard(
        procs,
        listener,
        new,
        COUNT,
        lambda: locators_pruned(trace, TALKER) is not None,
        PRUNE_TIMEOUT,
        "the listener pruning the talker's Service",
    )
    assert proxy.packets("listen", TALKER, "DNAT") == 0, procs.tails()  # nothing sent to the Service since the move
    print(
        f"moved talker without the listener in its list: not heard in {waited:.1f} s; the listener sent nothing to the "
        f"talker's Service after the move and pruned its locators {locators_pruned(trace, TALKER):.1f} s after adding them"
    )


@pytest.mark.parametrize("late", [False, True], ids=["2s-later", "after-the-prune"])
def test_service_a_peer_whose_pod_does_not_exist_yet_is_met_when_it_starts(service_procs, proxy, late):
    """Unlike a name that does not resolve, a Service without endpoints lets the participant start (REJECTed SPDP)."""
    require_cyclonedds()
    procs, lab = service_procs, proxy.lab
    proxy.reset({TALKER: None, LISTENER: lab.addresses["listen"]})
    trace = os.path.join(procs.directory, "listener.trace")
    listener = start_listener(procs, "listener", "listen", traced(instance_env(procs, "listener", [TALKER]), trace))
    first = time.monotonic()
    procs.wait_until(lambda: proxy.packets("listen", TALKER, "REJECT") > 0, STARTUP_TIMEOUT, "no SPDP to the empty Service")
    time.sleep(1.0)
    rejected = proxy.packets("listen", TALKER, "REJECT")  # all the SPDP the listener sends to the Service: see below
    if late:
        procs.wait_until(lambda: locators_pruned(trace, TALKER) is not None, PRUNE_TIMEOUT, "the locators were not pruned")
        assert proxy.packets("listen", TALKER, "REJECT") == rejected, procs.tails()  # none after its first second
    else:
        time.sleep(1.0)
    assert listener.popen.poll() is None and listener.output() == "ready\n", procs.tails()  # running, nothing logged

    proxy.sync({TALKER: lab.addresses["talk"], LISTENER: lab.addresses["listen"]})  # the talker's pod is up
    started = time.monotonic()
    talker = start_talker(procs, "talker", "talk", instance_env(procs, "talker", [LISTENER]))
    procs.wait_until(lambda: len(listener.received()) >= COUNT, DISCOVERY_TIMEOUT, "the late talker was not heard", poll=0.02)
    seconds = time.monotonic() - started
    assert listener.received() == list(range(1, COUNT + 1)), procs.tails()
    assert proxy.packets("talk", LISTENER, "DNAT") > 0 and proxy.packets("listen", TALKER, "DNAT") == 0, procs.tails()
    print(
        f"talker started {started - first:.1f} s after the listener (its Service without endpoints until then, "
        f"{rejected} SPDP packets to its {len(SPDP_PORTS)} ports rejected"
        f"{', none after the first second; the listener had pruned its locators' if late else ''}): "
        f"it matched {matched_after(talker)} after creating "
        f"its participant; all {COUNT} messages {seconds:.2f} s after its process was started"
    )


def test_service_a_later_peer_whose_list_does_not_name_the_first_is_never_met(service_procs, proxy):
    """The control of the one above: what makes them meet is the later one's SPDP to the first one's Service."""
    require_cyclonedds()
    procs, lab = service_procs, proxy.lab
    proxy.reset({TALKER: None, LISTENER: lab.addresses["listen"]})
    trace = os.path.join(procs.directory, "listener.trace")
    listener = start_listener(procs, "listener", "listen", traced(instance_env(procs, "listener", [TALKER]), trace))
    procs.wait_until(lambda: proxy.packets("listen", TALKER, "REJECT") > 0, STARTUP_TIMEOUT, "no SPDP to the empty Service")
    time.sleep(2.0)
    proxy.sync({TALKER: lab.addresses["talk"], LISTENER: lab.addresses["listen"]})
    talker = start_talker(procs, "talker", "talk", instance_env(procs, "talker-no-peers", []))
    waited = never_heard(
        procs,
        listener,
        talker,
        0,
        lambda: locators_pruned(trace, TALKER) is not None,
        PRUNE_TIMEOUT,
        "the listener pruning the talker's Service",
    )
    assert proxy.packets("listen", TALKER, "DNAT") == 0, procs.tails()
    print(f"a talker that started 2 s after the listener and does not name it: not met in {waited:.1f} s")
