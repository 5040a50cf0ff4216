"""KubeROS-Bridge between two independent ROS 2 graphs, with real processes in network namespaces.

Two namespaces stand for the two clusters: "a" (the main cluster) and "b" (the third-party cluster), on one
Linux bridge that floods no multicast (test_discovery_netns.Lab). Each runs its own Fast DDS discovery server
(`fast-discovery-server`, from the ros-fastrtps wheel), and every ROS 2 process of a graph names only its
own server in ROS_DISCOVERY_SERVER, with a private /dev/shm: no DDS path joins the graphs. The negative
control shows it (a listener in b hears nothing from a talker in a until the bridge runs). The bridge server
runs in a, the client in b, connected over TCP between the namespaces' addresses with mutual TLS
(certificates from the collection's own generate_certificates).

Needs root and `ip netns` (skipped otherwise) and requirements-ros.txt installed in the venv (fails
otherwise). Traffic stays between the namespaces this module creates; every wait is bounded.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from helpers import ROOT
from test_discovery_netns import Lab, Process, Processes, open_lab, require_ros

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import generate_certificates

pytestmark = pytest.mark.ros

HERE = os.path.dirname(os.path.abspath(__file__))
PROBE = os.path.join(HERE, "ros", "bridge_probe.py")
BRIDGE = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge"
SERVER_NAME = "kuberos-bridge.test"
BRIDGE_PORT, METRICS_PORT, DISCOVERY_PORT = 50051, 9102, 11811
STARTUP_TIMEOUT = 30.0  # a process printing that it is up (two cores, several Python processes starting at once)
FLOW_TIMEOUT = 45.0  # messages arriving through discovery and the bridge
NEGATIVE_WINDOW = 8.0
IMAGE_BYTES = 1_200_000
TOPICS = """\
topics:
- {name: /chatter, type: std_msgs/msg/String, direction: to_client}
- {name: /camera/image, type: sensor_msgs/msg/Image, direction: to_client, depth: 5}
- {name: /planning/request, type: std_msgs/msg/String, direction: to_client}
- {name: /planning/response, type: std_msgs/msg/String, direction: to_server}
"""


@pytest.fixture(scope="module")
def lab(request) -> Lab:
    lab = open_lab(request, "a")
    lab.add("b")
    return lab


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    base = tmp_path_factory.mktemp("bridge")
    good = generate_certificates(str(base / "certs"), SERVER_NAME)
    other = generate_certificates(str(base / "other-ca"), SERVER_NAME)
    topics = base / "topics.yml"
    topics.write_text(TOPICS, encoding="utf-8")
    return {**good, "other_client_cert": other["client_cert"], "other_client_key": other["client_key"], "topics": str(topics)}


@pytest.fixture
def procs(lab, tmp_path):
    processes = Processes(lab, str(tmp_path))
    processes.base_env["PYTHONPATH"] = os.path.join(ROOT, ".collections")
    yield processes
    processes.close()


def graph_env(lab: Lab, role: str) -> dict[str, str]:
    """A graph's ROS environment: its own discovery server only; the same domain id in both graphs.

    Every process has a private /dev/shm (as pods have), so processes of one namespace must use UDP: Fast DDS
    would pick shared memory for a peer on its own address, and the data would never arrive.
    """
    return {
        "ROS_DISCOVERY_SERVER": f"{lab.addresses[role]}:{DISCOVERY_PORT}",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_DOMAIN_ID": "0",
        "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
    }


def lines(process: Process, pattern: str) -> list[re.Match]:
    return list(re.finditer(pattern, process.output(), re.MULTILINE))


def numbers(process: Process, word: str) -> list[int]:
    return [int(m.group(1)) for m in lines(process, rf"^{word} (\d+)\b")]


def start_discovery(procs: Processes, role: str) -> Process:
    server = procs.start(
        f"discovery-{role}", role, ["fast-discovery-server", "-i", "0", "-l", "0.0.0.0", "-p", str(DISCOVERY_PORT)]
    )
    procs.wait_until(lambda: "Server ID:" in server.output(), STARTUP_TIMEOUT, f"discovery server in {role} did not start")
    return server


def start_probe(procs: Processes, name: str, role: str, *args: str) -> Process:
    probe = procs.start(name, role, [sys.executable, PROBE, *args], graph_env(procs.lab, role))
    procs.wait_until(lambda: "ready" in probe.output().split(), STARTUP_TIMEOUT, f"{name} did not start")
    return probe


def start_bridge_server(procs: Processes, files: dict, name: str = "bridge-server", *extra: str) -> Process:
    lab = procs.lab
    command = [
        sys.executable, "-m", BRIDGE, "server", "--listen", f"{lab.addresses['a']}:{BRIDGE_PORT}",
        "--cert", files["server_cert"], "--key", files["server_key"], "--ca", files["ca_cert"],
        "--topics", files["topics"], "--metrics-port", str(METRICS_PORT), *extra,
    ]  # fmt: skip
    server = procs.start(name, "a", command, graph_env(lab, "a"))
    procs.wait_until(lambda: "server listening on" in server.output(), STARTUP_TIMEOUT, f"{name} did not listen")
    return server


def start_bridge_client(procs: Processes, files: dict, *extra: str, cert="client_cert", key="client_key") -> Process:
    lab = procs.lab
    command = [
        sys.executable, "-m", BRIDGE, "client", "--connect", f"{lab.addresses['a']}:{BRIDGE_PORT}",
        "--server-name", SERVER_NAME, "--cert", files[cert], "--key", files[key], "--ca", files["ca_cert"],
        "--topics", files["topics"], "--metrics-port", str(METRICS_PORT), "--backoff-max", "1", *extra,
    ]  # fmt: skip
    client = procs.start("bridge-client", "b", command, graph_env(lab, "b"))
    procs.wait_until(lambda: "client connecting to" in client.output(), STARTUP_TIMEOUT, "the bridge client did not start")
    return client


FETCH = "import sys, urllib.request; sys.stdout.write(urllib.request.urlopen(sys.argv[1], timeout=5).read().decode())"


def metrics(lab: Lab, role: str) -> dict[tuple[str, frozenset], float]:
    """The bridge's /metrics in a namespace, as {(name, labels): value}."""
    done = subprocess.run(
        ["ip", "netns", "exec", lab.namespaces[role], sys.executable, "-c", FETCH,
         f"http://{lab.addresses[role]}:{METRICS_PORT}/metrics"],
        capture_output=True, text=True, timeout=20,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    values = {}
    for line in done.stdout.splitlines():
        match = re.match(r"^(\w+)(?:\{(.*)\})? (\S+)$", line)
        if match:
            labels = frozenset(re.findall(r'(\w+)="([^"]*)"', match.group(2) or ""))
            values[(match.group(1), labels)] = float(match.group(3))
    return values


def metric(values: dict, name: str, **labels: str) -> float:
    wanted = set(labels.items())
    return sum(v for (n, ls), v in values.items() if n == name and wanted <= ls)


def stop_cleanly(process: Process) -> None:
    """SIGTERM: the bridge stops by itself, exit status 0, with its closing log line."""
    os.killpg(process.popen.pid, signal.SIGTERM)
    try:
        process.popen.wait(15)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{process.name} did not stop within 15 s of SIGTERM\n{process.tail()}", pytrace=False)
    assert process.popen.returncode == 0, process.tail()
    assert "stopped: " in process.output(), process.tail()


# --- tests ------------------------------------------------------------------------------------------------


def test_negative_control_the_graphs_meet_only_through_the_bridge(procs, files):
    """Without the bridge a listener in b gets nothing from a talker in a (that a listener in a hears)."""
    require_ros()
    start_discovery(procs, "a")
    start_discovery(procs, "b")
    talker = start_probe(procs, "talker-a", "a", "talk", "/chatter", "string")
    local = start_probe(procs, "listener-a", "a", "listen", "/chatter", "string")
    remote = start_probe(procs, "listener-b", "b", "listen", "/chatter", "string")
    procs.wait_until(lambda: numbers(local, "received"), FLOW_TIMEOUT, "the talker's own graph does not hear it")
    deadline = time.monotonic() + NEGATIVE_WINDOW
    while time.monotonic() < deadline:
        assert not numbers(remote, "received"), f"graph b heard graph a without the bridge\n{procs.tails()}"
        time.sleep(0.2)
    assert numbers(talker, "published")
    # The control's control: the same listener hears the talker as soon as the bridge runs.
    start_bridge_server(procs, files)
    start_bridge_client(procs, files)
    seconds = procs.wait_until(lambda: numbers(remote, "received"), FLOW_TIMEOUT, "graph b got nothing through the bridge")
    print(f"nothing in {NEGATIVE_WINDOW:.0f} s without the bridge; with it, the first message after {seconds:.1f} s")


def test_string_image_and_request_reply_cross_the_bridge_and_sigterm_stops_it(procs, lab, files):
    require_ros()
    start_discovery(procs, "a")
    start_discovery(procs, "b")
    server = start_bridge_server(procs, files)
    client = start_bridge_client(procs, files)
    procs.wait_until(lambda: "connected to server" in client.output(), FLOW_TIMEOUT, "the bridge did not connect")
    start_probe(procs, "talker-a", "a", "talk", "/chatter", "string")
    start_probe(procs, "image-talker-a", "a", "talk", "/camera/image", "image", "--period", "0.5", "--size", str(IMAGE_BYTES))
    listener = start_probe(procs, "listener-b", "b", "listen", "/chatter", "string")
    images = start_probe(procs, "image-listener-b", "b", "listen", "/camera/image", "image")
    start_probe(procs, "responder-b", "b", "respond", "/planning/request", "/planning/response")
    requester = start_probe(procs, "requester-a", "a", "request", "/planning/request", "/planning/response", "--period", "0.3")

    procs.wait_until(lambda: len(numbers(listener, "received")) >= 5, FLOW_TIMEOUT, "std_msgs/String did not cross")
    procs.wait_until(lambda: len(numbers(images, "received")) >= 3, FLOW_TIMEOUT, "sensor_msgs/Image did not cross")
    procs.wait_until(lambda: len(numbers(requester, "reply")) >= 25, FLOW_TIMEOUT, "no replies came back")
    sizes = {int(m.group(1)) for m in lines(images, r"^received \d+ bytes=(\d+)$")}
    assert sizes == {IMAGE_BYTES}, sizes
    received = numbers(listener, "received")
    assert received == sorted(received) and len(set(received)) == len(received), "out of order or duplicated"
    rtts = [float(m.group(1)) for m in lines(requester, r"^reply \d+ rtt_ms=([\d.]+)$")]

    a, b = metrics(lab, "a"), metrics(lab, "b")
    assert metric(a, "kuberos_bridge_connected") == 1 and metric(b, "kuberos_bridge_connected") == 1
    assert metric(a, "kuberos_bridge_messages_sent_total", topic="/camera/image", direction="to_client") >= 3
    assert metric(a, "kuberos_bridge_bytes_sent_total", topic="/camera/image") >= 3 * IMAGE_BYTES
    assert metric(b, "kuberos_bridge_messages_received_total", topic="/chatter", direction="to_client") >= 5
    assert metric(b, "kuberos_bridge_messages_sent_total", topic="/planning/response", direction="to_server") >= 5
    assert metric(a, "kuberos_bridge_messages_received_total", topic="/planning/response") >= 5
    assert metric(a, "kuberos_bridge_topic_active", topic="/camera/image") == 1
    for values in (a, b):
        assert metric(values, "kuberos_bridge_rejected_messages_total") == 0
        assert metric(values, "kuberos_bridge_malformed_frames_total") == 0
    steady = sorted(rtts[-3:])  # the first ones wait while the bridge's new publishers are matched (up to 3 s a side)
    print(
        f"request/reply through the bridge: {len(rtts)} replies, the first after {rtts[0]:.0f} ms, "
        f"the last 3 round trips median {steady[1]:.1f} ms"
    )
    stop_cleanly(client)
    stop_cleanly(server)


def test_a_client_with_a_certificate_from_another_ca_is_refused(procs, lab, files):
    require_ros()
    start_discovery(procs, "a")
    start_discovery(procs, "b")
    server = start_bridge_server(procs, files)
    client = start_bridge_client(procs, files, cert="other_client_cert", key="other_client_key")
    start_probe(procs, "talker-a", "a", "talk", "/chatter", "string", "--period", "0.1")
    listener = start_probe(procs, "listener-b", "b", "listen", "/chatter", "string")
    procs.wait_until(lambda: "TLS/authentication failure" in client.output(), FLOW_TIMEOUT, "the client reported no TLS failure")
    procs.wait_until(lambda: "CERTIFICATE_VERIFY_FAILED" in server.output(), FLOW_TIMEOUT, "the server logged no refusal")
    time.sleep(3)
    assert not numbers(listener, "received"), "a message passed with a foreign certificate"
    a, b = metrics(lab, "a"), metrics(lab, "b")
    assert metric(a, "kuberos_bridge_connections_total") == 0 and metric(b, "kuberos_bridge_connections_total") == 0
    assert metric(b, "kuberos_bridge_connect_failures_total", reason="tls") >= 1
    assert metric(b, "kuberos_bridge_messages_received_total") == 0 and metric(a, "kuberos_bridge_messages_sent_total") == 0
    assert "connected to" not in client.output() and "connected to" not in server.output()
    assert client.popen.poll() is None and server.popen.poll() is None, procs.tails()


def test_killing_and_restarting_the_server_resumes_the_flow_and_reports_the_drops(procs, lab, files):
    require_ros()
    start_discovery(procs, "a")
    start_discovery(procs, "b")
    server = start_bridge_server(procs, files)
    client = start_bridge_client(procs, files, "--buffer", "20")
    procs.wait_until(lambda: "connected to server" in client.output(), FLOW_TIMEOUT, "the bridge did not connect")
    start_probe(procs, "talker-a", "a", "talk", "/chatter", "string", "--period", "0.1")
    talker_b = start_probe(procs, "talker-b", "b", "talk", "/planning/response", "string", "--period", "0.05")
    listener_b = start_probe(procs, "listener-b", "b", "listen", "/chatter", "string")
    listener_a = start_probe(procs, "listener-a", "a", "listen", "/planning/response", "string")
    procs.wait_until(lambda: len(numbers(listener_b, "received")) >= 3, FLOW_TIMEOUT, "a -> b did not flow")
    procs.wait_until(lambda: len(numbers(listener_a, "received")) >= 3, FLOW_TIMEOUT, "b -> a did not flow")

    server.kill(signal.SIGKILL)
    killed_at = max(numbers(talker_b, "published"))
    procs.wait_until(lambda: "ended" in client.output(), FLOW_TIMEOUT, "the client did not notice")
    time.sleep(4)  # 20 messages/s on /planning/response: the client's buffer of 20 overflows
    restarted_at = max(numbers(talker_b, "published"))
    before_b = len(numbers(listener_b, "received"))
    start_bridge_server(procs, files, "bridge-server-2")
    procs.wait_until(lambda: client.output().count("connected to server") >= 2, FLOW_TIMEOUT, "the client did not reconnect")
    procs.wait_until(lambda: len(numbers(listener_b, "received")) > before_b + 3, FLOW_TIMEOUT, "a -> b did not resume")
    procs.wait_until(
        lambda: any(n > restarted_at for n in numbers(listener_a, "received")), FLOW_TIMEOUT, "b -> a did not resume"
    )
    # The client's buffer of 20 crossed to the restarted server, which published it. Whether listener-a gets those
    # depends on how soon it matches the server's new publisher (discovery timing, up to the 3 s the bridge waits).
    procs.wait_until(
        lambda: metric(metrics(lab, "a"), "kuberos_bridge_messages_received_total", topic="/planning/response") >= 20,
        FLOW_TIMEOUT, "the restarted server did not publish the client's buffered messages",
    )  # fmt: skip
    buffered = [n for n in numbers(listener_a, "received") if killed_at < n <= restarted_at]
    b = metrics(lab, "b")
    dropped = metric(b, "kuberos_bridge_dropped_messages_total", topic="/planning/response", reason="buffer_full")
    assert dropped >= restarted_at - killed_at - 20 - 5, (dropped, killed_at, restarted_at)  # 5: messages in flight
    assert metric(b, "kuberos_bridge_reconnects_total") >= 1 and metric(b, "kuberos_bridge_disconnects_total") >= 1
    assert metric(b, "kuberos_bridge_connect_failures_total") >= 1
    report = re.search(r"/planning/response (\d+) dropped while disconnected; (\d+) buffered messages to send", client.output())
    assert report, client.tail(30)
    assert int(report.group(1)) == dropped and int(report.group(2)) <= 20
    assert "send buffer full (20 messages" in client.output()
    print(
        f"outage: talker-b published {killed_at + 1}..{restarted_at}; the client dropped {dropped:.0f} (buffer of 20), "
        f"{len(buffered)} of the outage's messages arrived after the restart"
    )
