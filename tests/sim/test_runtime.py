"""The simulation runtime (sim/kuberos_sim/runtime): a rendered deployment run for real on this machine.

A probe RosDeployment is rendered with the project's own code (two discovery servers on the edge, a probe
module on each robot and one per robot on the edge, printing its node name, params file and where
kuberos_sim imports from) and run by ``Runtime`` unchanged. Measured here: ping RTTs through the fabric
against the inventory, multicast blocked between hosts while the rendered discovery servers connect
participants, a CPU quota enforced by cgroups, a host added and removed while the run goes on, and teardown
leaving nothing behind.

The pure parts (the delay rule, the fabric's queueing and reloading, reading a rendered directory) run anywhere; the rest
needs root, `ip netns`, TUN and cgroup v1 cpu/cpuacct (skipped otherwise), and the ROS 2 wheels for the
discovery test (fails otherwise, as test_discovery_netns does). Every wait is bounded; traffic stays
between the run's namespaces.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from helpers import ROOT
from sshlab import run

sys.path[:0] = [os.path.join(ROOT, "sim"), os.path.join(ROOT, "tests", "integration")]

from kuberos_sim.runtime import LAN_RTT_MS, ProcessExitedError, Runtime, environment_problem, rtt_ms  # noqa: E402
from kuberos_sim.runtime import fabric as fabric_module  # noqa: E402
from kuberos_sim.runtime.cgroups import machine_cores  # noqa: E402
from kuberos_sim.runtime.delays import one_way_delays_ms  # noqa: E402
from kuberos_sim.runtime.rendered import load_rendered  # noqa: E402
from netlab import CHATTER as TOPIC  # noqa: E402
from netlab import LISTENER, TALKER  # noqa: E402
from test_discovery_netns import require_ros  # noqa: E402

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests, service  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import Node, load_inventory  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import placement_table  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import render_dir  # noqa: E402

pytestmark = pytest.mark.sim

RTT_TOLERANCE = 0.10
STARTUP_TIMEOUT = 30.0  # rclpy on a robot's half core
DISCOVERY_TIMEOUT = 30.0
NEGATIVE_WINDOW = 8.0
PROBE = (
    "python3 -c \"import os, sys, time, kuberos_sim; print('NODE=' + os.environ['KUBEROS_NODE_NAME']); "
    "params = os.environ['KUBEROS_PARAMS_FILE']; print('PARAMS=' + params + ' ' + open(params).read().replace(chr(10), ' ')); "
    "print('PYTHON=' + sys.executable); print('SIM=' + kuberos_sim.__file__, flush=True); time.sleep(600)\""
)
MODULE = {"image": "probe", "launch": [PROBE], "resources": {"cpu": "100m", "memory": "64Mi"}}
PROBE_SPEC = {
    "metadata": {"name": "sim-probe", "targetFleet": "test-fleet"},
    "discovery": {"servers": 2},
    "rosModules": [
        {**MODULE, "name": "onboard-probe", "requirements": {"onboard": True}, "rosParameters": {"greeting": "onboard-hello"}},
        {**MODULE, "name": "edge-probe", "preference": "edge", "rosParameters": {"greeting": "edge-hello"}},
    ],
}
FAILING_SPEC = {
    "metadata": {"name": "sim-failing", "targetFleet": "test-fleet"},
    "rosModules": [
        {
            **MODULE,
            "name": "crash",
            "launch": ["python3 -c \"print('boom before exit'); raise SystemExit(3)\""],
            "preference": "edge",
        }
    ],
}


def render(spec: dict, inventory_raw: dict, directory: str) -> str:
    """Render a spec as the render module does: manifests/ and placement.json under directory."""
    deployments, placement = service.load_and_place(spec, inventory_raw)
    objects = manifests.render_deployment(deployments, placement, manifests.RenderOptions())
    render_dir.apply_plan(render_dir.plan_render_dir(directory, objects, placement.to_dict(), placement_table(placement)))
    return directory


def require_environment() -> None:
    problem = environment_problem()
    if problem:
        pytest.skip(f"the simulator cannot run here: {problem}")


def wait_until(condition, timeout: float, what: str, runtime: Runtime) -> float:
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if condition():
            return time.monotonic() - start
        time.sleep(0.2)
    tails = "\n".join(p.tail(10) for p in runtime.processes.values())
    pytest.fail(f"{what}: not within {timeout:.0f} s\n{tails}", pytrace=False)


def ping_rtt_ms(runtime: Runtime, source: str, target: str, count: int = 20) -> float:
    """The fastest round-trip time of ``count`` pings: the fabric's delay plus its least overhead. A busy machine only
    ever adds time (the mean of the same pings once read 5.68 ms for a 5 ms link under load, the median 5.57 ms in a CI
    run), and no packet can come back sooner than the delay the fabric holds it for."""
    done = run(
        "ip", "netns", "exec", runtime.hosts[source].netns,
        "ping", "-n", "-c", str(count), "-i", "0.05", "-W", "2", runtime.host_address(target),
        timeout=count * 0.05 + 10,
    )  # fmt: skip
    times = sorted(float(t) for t in re.findall(r"time=([\d.]+) ms", done.stdout))
    assert len(times) >= count // 2, done.stdout
    return times[0]


def received(process) -> list[int]:
    return [int(n) for n in re.findall(r"^received kuberos (\d+)$", process.output(), re.MULTILINE)]


def published(process) -> list[int]:
    return [int(n) for n in re.findall(r"^published kuberos (\d+) subscribers=\d+$", process.output(), re.MULTILINE)]


@pytest.fixture(scope="module")
def rendered_dirs(tmp_path_factory, local_raw) -> dict[str, str]:
    base = tmp_path_factory.mktemp("rendered")
    return {
        "probe": render(PROBE_SPEC, local_raw, str(base / "probe")),
        "failing": render(FAILING_SPEC, local_raw, str(base / "failing")),
    }


@pytest.fixture(scope="module")
def runtime(rendered_dirs, local_inventory, tmp_path_factory):
    """The probe deployment running, with both cloud VMs as extra hosts."""
    require_environment()
    with Runtime(
        rendered_dirs["probe"], local_inventory, str(tmp_path_factory.mktemp("run")), extra_hosts=("cloud-1", "cloud-2")
    ) as started:
        started.start()
        yield started
    assert not started.leftovers() and not started.close_problems, (started.leftovers(), started.close_problems)


# --- the delay rule (pure) --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "a, b, expected",
    [
        ("fetch-1", "edge-1", 5.0),  # the edge tier default of inventories/local
        ("fetch-1", "edge-3", 3.0),  # edge-3's kuberos_latency_ms
        ("fetch-1", "cloud-1", 40.0),  # the cloud tier default
        ("fetch-2", "cloud-2", 60.0),  # cloud-2's kuberos_latency_ms
        ("fetch-1", "cloud-2", 180.0),  # fetch-1's kuberos_link_latency_ms override
        ("fetch-1", "fetch-2", LAN_RTT_MS),  # two robots: the LAN
        ("edge-1", "edge-2", LAN_RTT_MS),  # one site (resource group site-a)
        ("cloud-1", "cloud-2", LAN_RTT_MS),  # one region (cloud-eu)
        ("edge-1", "cloud-1", 40.0),  # edge-cloud: the cloud node's latency
        ("edge-3", "cloud-2", 60.0),
        ("edge-2", "edge-2", 0.0),
    ],
)
def test_delay_rule(local_inventory, a, b, expected):
    assert rtt_ms(local_inventory, a, b) == expected
    assert rtt_ms(local_inventory, b, a) == expected


def test_delay_rule_is_symmetric_finite_and_halved_per_direction(local_inventory):
    nodes = list(local_inventory.nodes)
    delays = one_way_delays_ms(local_inventory, nodes)
    for a in nodes:
        assert a not in delays[a]
        for b in nodes:
            if a != b:
                assert math.isfinite(delays[a][b]) and delays[a][b] == delays[b][a] == rtt_ms(local_inventory, a, b) / 2


def test_delay_rule_names_an_unknown_node(local_inventory):
    with pytest.raises(ValueError, match="'edge-9' is not a node"):
        rtt_ms(local_inventory, "fetch-1", "edge-9")


# --- the fabric's queueing (pure: pipes stand in for TUN devices) -----------------------------------------


def ipv4(destination: str, size: int = 64) -> bytes:
    header = bytes([0x45, 0]) + size.to_bytes(2, "big") + bytes(12) + bytes(int(x) for x in destination.split("."))
    return header + bytes(size - len(header))


def test_fabric_delays_forwards_in_order_drops_multicast_unknown_and_overflow():
    read_a, write_a = os.pipe()
    fabric = fabric_module.Fabric({"hosts": [], "delay_ms": {"b": {"a": 50.0}}, "queue_packets": 3})
    fabric.by_address[bytes([10, 0, 0, 1])] = (write_a, "a")
    try:
        for n in range(4):
            fabric.receive("b", ipv4("10.0.0.1", 64 + n), now=100.0)
        fabric.receive("b", ipv4("239.255.0.1"), now=100.0)
        fabric.receive("b", ipv4("10.0.0.9"), now=100.0)
        fabric.receive("b", b"\x60" + bytes(60), now=100.0)  # IPv6
        fabric.deliver_due(100.049)
        assert fabric.stats.packets == 0
        fabric.deliver_due(100.050)
        assert len(os.read(read_a, 65536)) == 64 + 65 + 66  # a pipe merges them: the first three, the fourth dropped
        stats = fabric.stats.to_dict(fabric.delay_ms)
        assert stats["packets"] == 3 and stats["pairs"]["b->a"]["delay_ms"] == 50.0
        assert stats["drops"] == {
            "multicast": 1, "unknown_destination": 1, "not_ipv4": 1, "queue_full": 1, "write_error": 0, "host_removed": 0,
            "loss": 0, "link_queue_full": 0,
        }  # fmt: skip
    finally:
        os.close(read_a)
        os.close(write_a)


def test_a_limited_link_sends_at_its_rate_each_way_and_a_lossy_one_drops_its_share():
    """b's link sends 1 Mbit/s: four 1250-byte packets (10 ms each on the link) leave b one after the other, then wait
    the pair's 5 ms; a's link is not limited. A queue over link_queue_s is dropped at its tail. A link losing 20 %
    drops about that share (2000 packets: between 15 % and 25 %), the same with the same seed."""
    read_a, write_a = os.pipe()
    os.set_blocking(read_a, False)
    config = {"hosts": [], "delay_ms": {"b": {"a": 5.0}}, "link_bps": {"b": 1e6}, "link_queue_s": 0.035}
    fabric = fabric_module.Fabric(config)
    fabric.by_address[bytes([10, 0, 0, 1])] = (write_a, "a")
    try:
        for _ in range(5):
            fabric.receive("b", ipv4("10.0.0.1", 1250), now=100.0)
        due = sorted(entry[0] for entry in fabric.heap)
        assert [round(t - 100.0, 4) for t in due] == [0.015, 0.025, 0.035, 0.045]  # the fifth would wait 40 ms: dropped
        assert fabric.stats.drops["link_queue_full"] == 1
        fabric.deliver_due(100.0149)
        assert fabric.stats.packets == 0
        fabric.deliver_due(100.0451)
        assert fabric.stats.packets == 4
    finally:
        os.close(read_a)
        os.close(write_a)

    def lost(seed):
        lossy = fabric_module.Fabric({"hosts": [], "delay_ms": {}, "link_loss": {"b": 0.2}, "seed": seed})
        lossy.by_address[bytes([10, 0, 0, 1])] = (-1, "a")
        for n in range(2000):
            lossy.receive("b", ipv4("10.0.0.1", 64), now=100.0 + n)
            lossy.heap.clear()
        return lossy.stats.drops["loss"]

    assert 300 <= lost(7) <= 500 and lost(7) == lost(7)
    with pytest.raises(ValueError):
        fabric_module.Fabric({"hosts": [], "delay_ms": {}, "link_loss": {"b": 1.0}})


class PipeHosts:
    """Pipes standing in for the hosts' TUN devices: ``open`` is the fabric's opener (the fabric writes a host's
    packets to the write end, which it closes on detach); ``read`` takes what reached a host."""

    def __init__(self, failing: tuple[str, ...] = ()):
        self.read_ends: dict[str, int] = {}
        self.write_ends: dict[str, int] = {}
        self.failing = failing

    def open(self, namespace: str, _tun: str) -> int:
        if namespace in self.failing:
            raise FileNotFoundError(f"/var/run/netns/{namespace}")
        read, write = os.pipe()
        os.set_blocking(read, False)
        self.read_ends[namespace], self.write_ends[namespace] = read, write
        return write

    def read(self, namespace: str) -> bytes:
        try:
            return os.read(self.read_ends[namespace], 65536)
        except BlockingIOError:
            return b""

    def close(self) -> None:
        for fd in self.read_ends.values():
            os.close(fd)


def fabric_config(hosts: dict[str, str], delay_ms: dict) -> dict:
    return {"hosts": [{"node": n, "netns": f"ns-{n}", "address": a} for n, a in hosts.items()], "delay_ms": delay_ms}


def test_fabric_reload_attaches_detaches_drops_in_flight_packets_and_takes_new_delays():
    pipes = PipeHosts(failing=("ns-bad",))
    fabric = fabric_module.Fabric(fabric_config({"a": "10.0.0.1", "b": "10.0.0.2"}, {"b": {"a": 50.0}, "a": {"b": 50.0}}))
    try:
        fabric.attach(pipes.open)
        fabric.receive("b", ipv4("10.0.0.1", 64), now=100.0)  # in flight to a when a goes
        fabric.receive("a", ipv4("10.0.0.2", 65), now=100.0)  # sent by a before it went: still delivered
        fabric.reload(fabric_config({"b": "10.0.0.2", "c": "10.0.0.3"}, {"b": {"c": 5.0}, "c": {"b": 5.0}}), pipes.open)
        assert sorted(fabric.by_node()) == ["b", "c"] and len(fabric.heap) == 1
        assert fabric.stats.drops["host_removed"] == 1 and fabric.stats.pairs[("b", "a")].drops == 1
        assert fabric.stats.in_flight_bytes == 65 and fabric.stats.pairs[("b", "a")].in_flight_bytes == 0
        fabric.receive("b", ipv4("10.0.0.1"), now=101.0)  # a's address is no host's now
        assert fabric.stats.drops["unknown_destination"] == 1
        fabric.receive("b", ipv4("10.0.0.3", 66), now=101.0)  # to the new host, with the new delay
        fabric.deliver_due(101.0049)
        assert pipes.read("ns-c") == b""
        fabric.deliver_due(101.005)
        assert len(pipes.read("ns-c")) == 66 and len(pipes.read("ns-b")) == 65
        # a later host may get a's old fd number: none of a's packets reaches it
        fabric.reload(fabric_config({"b": "10.0.0.2", "c": "10.0.0.3", "d": "10.0.0.4"}, {}), pipes.open)
        fabric.deliver_due(200.0)
        assert pipes.read("ns-d") == b"" and fabric.stats.packets == 2
        stats = fabric.stats.to_dict(fabric.delay_ms)
        assert stats["pairs"]["b->c"]["delay_ms"] == 0.0 and stats["dropped"] == 2  # the last delays taken
        # a host that cannot be attached: nothing changes, the fds opened for it are closed
        with pytest.raises(FileNotFoundError):
            fabric.reload(fabric_config({"b": "10.0.0.2", "e": "10.0.0.5", "bad": "10.0.0.6"}, {"b": {"e": 9.0}}), pipes.open)
        assert sorted(fabric.by_node()) == ["b", "c", "d"] and fabric.delay_ms == {}
        with pytest.raises(OSError):
            os.fstat(pipes.write_ends["ns-e"])  # opened before "bad" failed, closed since
    finally:
        for fd in list(fabric.fds):
            os.close(fd)
        pipes.close()


def wait_for_line(path, text: str, count: int, process: subprocess.Popen, timeout: float = 10.0) -> float:
    """Seconds until ``text`` occurs ``count`` times in the file at ``path``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout and process.poll() is None:
        if path.read_text().count(text) >= count:
            return time.monotonic() - start
        time.sleep(0.005)
    pytest.fail(f"no {text!r} within {timeout:.0f} s (exit {process.poll()}):\n{path.read_text()}", pytrace=False)


def test_the_fabric_reloads_on_sighup_at_once_and_survives_a_failed_reload(tmp_path):
    """The script itself, without hosts (no root needed): its wait is 30 s long (stats_interval), yet SIGHUP and
    SIGTERM act at once; a config naming a namespace that does not exist is refused and the fabric goes on."""
    config = {"hosts": [], "delay_ms": {}, "stats_file": str(tmp_path / "stats.json"), "stats_interval": 30.0}
    path, log = tmp_path / "fabric.json", tmp_path / "fabric.log"
    path.write_text(json.dumps(config))
    with open(log, "wb") as out:
        fabric = subprocess.Popen([sys.executable, fabric_module.SCRIPT, str(path)], stdout=out, stderr=subprocess.STDOUT)
    try:
        wait_for_line(log, "fabric ready: 0 hosts", 1, fabric)
        path.write_text(json.dumps({**config, "delay_ms": {"a": {"b": 7.0}}}))
        fabric.send_signal(signal.SIGHUP)
        seconds = wait_for_line(log, "fabric reloaded: 0 hosts", 1, fabric)
        missing = {"node": "gone", "netns": "krs-test-no-such-namespace", "address": "10.0.0.9"}
        path.write_text(json.dumps({**config, "hosts": [missing]}))
        fabric.send_signal(signal.SIGHUP)
        wait_for_line(log, "fabric reload failed: ", 1, fabric)
        assert fabric.poll() is None, log.read_text()
        fabric.send_signal(signal.SIGHUP)
        wait_for_line(log, "fabric reload failed: ", 2, fabric)
        path.write_text(json.dumps(config))
        fabric.send_signal(signal.SIGHUP)
        wait_for_line(log, "fabric reloaded: 0 hosts", 2, fabric)
        start = time.monotonic()
        fabric.send_signal(signal.SIGTERM)
        assert fabric.wait(5) == 0, log.read_text()
        print(f"reload {seconds * 1000:.1f} ms after SIGHUP, stopped {(time.monotonic() - start) * 1000:.1f} ms after SIGTERM")
        assert seconds < 2.0 and "fabric stopped" in log.read_text()
    finally:
        if fabric.poll() is None:
            fabric.kill()
            fabric.wait()


# --- reading a rendered directory (pure) ------------------------------------------------------------------


def test_a_bad_rendered_directory_is_reported_by_file_field_and_reason(rendered_dirs, tmp_path):
    with pytest.raises(SpecError, match="does not exist"):
        load_rendered(str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SpecError, match="manifests: is missing"):
        load_rendered(str(tmp_path / "empty"))
    broken = tmp_path / "broken" / "manifests" / "ns"
    broken.mkdir(parents=True)
    (broken / "deployment-a.yaml").write_text(
        "kind: Deployment\nmetadata: {name: a, namespace: ns}\nspec: {template: {spec: {}}}\n"
    )
    (broken / "service-b.yaml").write_text("kind: [unclosed\n")
    with pytest.raises(SpecError) as error:
        load_rendered(str(tmp_path / "broken"))
    text = str(error.value)
    assert "manifests/ns/deployment-a.yaml: spec.template.spec.nodeSelector.device.kuberos.io/hostname: is missing" in text
    assert "manifests/ns/deployment-a.yaml: spec.template.spec.containers: is missing" in text
    assert "manifests/ns/service-b.yaml: cannot be read as YAML" in text
    rendered = load_rendered(rendered_dirs["probe"])
    assert list(rendered.deployments)[:2] == ["kuberos-discovery-0", "kuberos-discovery-1"]  # servers start first


def test_cli_reports_bad_input_without_a_traceback(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, "sim"), os.path.join(ROOT, ".collections")])}
    inventory = os.path.join(ROOT, "inventories", "local")
    done = subprocess.run(
        [sys.executable, "-m", "kuberos_sim.runtime", "--rendered", str(tmp_path), "-i", inventory],
        capture_output=True, text=True, timeout=120, env=env, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "manifests: is missing" in done.stderr and "Traceback" not in done.stderr, done.stderr


# --- the runtime, for real --------------------------------------------------------------------------------


@pytest.mark.parametrize("target", ["edge-1", "cloud-1", "cloud-2", "fetch-2"])
def test_ping_rtt_matches_the_inventory(runtime, local_inventory, target):
    expected = rtt_ms(local_inventory, "fetch-1", target)
    measured = ping_rtt_ms(runtime, "fetch-1", target)
    print(f"fetch-1 -> {target}: RTT {measured:.3f} ms emulated, {expected:.1f} ms in the inventory")
    # Never sooner than the delay; later by the fabric's overhead (a Python loop on two busy cores: 0.25-0.6 ms seen
    # on the fastest of 20 pings), at most 10 % or, for the LAN's 1 ms, 0.75 ms (a doubled LAN delay still fails).
    overhead = max(expected * RTT_TOLERANCE, 0.75)
    assert expected - 0.05 <= measured <= expected + overhead, (
        f"fetch-1 -> {target}: {measured:.3f} ms measured, {expected} ms expected"
    )


def test_modules_see_their_node_params_and_the_sim_packages(runtime):
    modules = [
        p for p in runtime.processes.values()
        if p.deployment and "probe" in p.deployment and not runtime.rendered.deployments[p.deployment].is_discovery_server
    ]  # fmt: skip
    assert len(modules) == 4
    for process in modules:
        wait_until(lambda p=process: "SIM=" in p.output(), STARTUP_TIMEOUT, f"{process.name} printed nothing", runtime)
        out = process.output()
        greeting = "onboard-hello" if "onboard" in process.name else "edge-hello"
        assert f"NODE={process.host}\n" in out, process.tail()
        assert re.search(rf"^PARAMS=/etc/kuberos/params.yaml .*greeting: {greeting}", out, re.MULTILINE), process.tail()
        assert f"PYTHON={runtime.prefix}/bin/python3" in out, process.tail()
        assert f"SIM={ROOT}/sim/kuberos_sim/__init__.py" in out, process.tail()
    assert not os.path.exists("/etc/kuberos"), "the params mount leaked out of the process's mount namespace"


def test_multicast_does_not_cross_but_the_rendered_discovery_servers_connect(runtime):
    require_ros()
    env = runtime.container_env("sim-probe-onboard-probe-fetch-1")
    simple = {k: v for k, v in env.items() if k != "ROS_DISCOVERY_SERVER"}
    drops_before = runtime.fabric_stats().get("drops", {}).get("multicast", 0)
    talker = runtime.start_on("fetch-1", "talker-simple", [sys.executable, TALKER, TOPIC], simple)
    listener = runtime.start_on("cloud-1", "listener-simple", [sys.executable, LISTENER, TOPIC], simple)
    wait_until(lambda: len(published(talker)) >= 2, STARTUP_TIMEOUT, "the talker did not publish", runtime)
    wait_until(lambda: "ready" in listener.output().split(), STARTUP_TIMEOUT, "the listener did not subscribe", runtime)
    deadline = time.monotonic() + NEGATIVE_WINDOW
    while time.monotonic() < deadline:
        assert not received(listener), "found each other without a discovery server"
        time.sleep(0.2)
    assert talker.running and listener.running
    time.sleep(1.2)  # the fabric writes its statistics every second
    multicast = runtime.fabric_stats()["drops"]["multicast"] - drops_before
    assert multicast > 0, "no multicast reached the fabric: the negative control proves nothing"

    talker = runtime.start_on("fetch-1", "talker", [sys.executable, TALKER, TOPIC], env)
    listener = runtime.start_on(
        "cloud-1", "listener", [sys.executable, LISTENER, TOPIC], runtime.container_env("sim-probe-edge-probe-fetch-1")
    )
    seconds = wait_until(lambda: len(received(listener)) >= 3, DISCOVERY_TIMEOUT, "the listener got no messages", runtime)
    print(f"{multicast} multicast packets dropped in {NEGATIVE_WINDOW:.0f} s without discovery servers; "
          f"through them the listener on cloud-1 had 3 messages from fetch-1 after {seconds:.1f} s")  # fmt: skip


def test_a_robots_modules_started_while_the_fleets_servers_are_gone_meet_through_the_robots_own_server(
    rendered_dirs, local_inventory, tmp_path
):
    """The fleet's discovery servers stopped (the robot cut off from the edge, as far as discovery goes): a talker and
    a listener started then on fetch-1 with an onboard module's environment meet through fetch-1's own server; the
    same pair with the fleet's servers only (the negative control, on fetch-2) does not. With the fleet's servers
    back, an edge module's listener on cloud-1 hears fetch-1's talker."""
    require_environment()
    require_ros()
    with Runtime(rendered_dirs["probe"], local_inventory, str(tmp_path), extra_hosts=("cloud-1",)) as runtime:
        runtime.start(modules=False)
        onboard = runtime.container_env("sim-probe-onboard-probe-fetch-1")
        edge = runtime.container_env("sim-probe-edge-probe-fetch-1")
        fleet_only = dict(onboard, ROS_DISCOVERY_SERVER=edge["ROS_DISCOVERY_SERVER"])
        assert onboard["ROS_DISCOVERY_SERVER"].startswith(edge["ROS_DISCOVERY_SERVER"] + ";")
        own = onboard["ROS_DISCOVERY_SERVER"].rsplit(";", 1)[1]
        assert own.startswith(runtime.host_address("fetch-1") + ":"), own
        fleet_servers = sorted(n for n, d in runtime.rendered.deployments.items() if d.component == "discovery-server")
        assert len(fleet_servers) == 2
        kept = {n: runtime.rendered.deployments[n] for n in fleet_servers}
        for name in fleet_servers:
            runtime.stop_deployment(name)
        control_talker = runtime.start_on("fetch-2", "control-talker", [sys.executable, TALKER, TOPIC], fleet_only)
        control_listener = runtime.start_on("fetch-2", "control-listener", [sys.executable, LISTENER, TOPIC], fleet_only)
        talker = runtime.start_on("fetch-1", "talker", [sys.executable, TALKER, TOPIC], onboard)
        listener = runtime.start_on("fetch-1", "listener", [sys.executable, LISTENER, TOPIC], onboard)
        met = wait_until(lambda: len(received(listener)) >= 3, DISCOVERY_TIMEOUT, "fetch-1's pair did not meet", runtime)
        wait_until(lambda: "ready" in control_listener.output().split(), STARTUP_TIMEOUT, "no control listener", runtime)
        deadline = time.monotonic() + NEGATIVE_WINDOW
        while time.monotonic() < deadline:
            assert not received(control_listener), "the pair without the robot's server met with the fleet's servers gone"
            time.sleep(0.2)
        assert control_talker.running and len(published(control_talker)) >= 2 and talker.running
        for name, dep in kept.items():
            runtime.rendered.deployments[name] = dep
            runtime.start_deployment(name)
        remote = runtime.start_on("cloud-1", "edge-listener", [sys.executable, LISTENER, TOPIC], edge)
        back = wait_until(lambda: len(received(remote)) >= 3, DISCOVERY_TIMEOUT, "cloud-1 never heard fetch-1", runtime)
    print(f"fleet's servers stopped: fetch-1's pair met through its own server in {met:.1f} s, the pair without it "
          f"not in {NEGATIVE_WINDOW:.0f} s; servers back, cloud-1 heard fetch-1 after {back:.1f} s")  # fmt: skip


def test_64kb_datagrams_cross_unfragmented(runtime):
    """Fast DDS's largest datagrams: sent from fetch-1 to edge-1, counted on arrival; throughput reported."""
    receiver = runtime.start_on(
        "edge-1", "udp-sink",
        [sys.executable, "-c", "import socket, time\n"
         "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)\n"
         "s.bind(('0.0.0.0', 7400)); print('bound', flush=True); s.settimeout(3); n = 0; first = None\n"
         "try:\n while True:\n  d = s.recv(70000); first = first or time.monotonic(); n += len(d)\n"
         "except socket.timeout: pass\n"
         "print('got', n, time.monotonic() - 3 - (first or time.monotonic()), flush=True)"],
    )  # fmt: skip
    wait_until(lambda: "bound" in receiver.output(), STARTUP_TIMEOUT, "the sink did not bind", runtime)
    count = 2000
    sender = runtime.start_on(
        "fetch-1", "udp-source",
        [sys.executable, "-c", f"import socket, time\ns = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
         f"for _ in range({count}):\n s.sendto(bytes(64000), ('{runtime.host_address('edge-1')}', 7400)); time.sleep(0.0002)\n"],
        cgroup="hardware",
    )  # fmt: skip
    wait_until(lambda: "got" in receiver.output(), 60, "the sink did not finish", runtime)
    assert sender.returncode == 0, sender.tail()
    got, seconds = receiver.output().split("got")[1].split()
    got_bytes, seconds = int(got), max(float(seconds), 1e-3)
    print(f"{got_bytes // 64000}/{count} datagrams of 64000 bytes, {got_bytes / seconds / 1e6:.0f} MB/s through the fabric")
    assert got_bytes % 64000 == 0 and got_bytes >= 64000 * count * 0.9, receiver.tail()


def test_a_robots_link_bandwidth_and_loss_from_the_inventory_limit_what_crosses_it(rendered_dirs, local_raw, tmp_path):
    """fetch-1's link at 4 Mbit/s losing 10 % (kuberos_link_bandwidth, kuberos_link_loss): a burst of 1000-byte
    datagrams to edge-1 arrives at about 4 Mbit/s less the loss (between 2.8 and 4.2), and of 300 datagrams sent
    10 ms apart (no queue) between 80 % and 97 % arrive."""
    require_environment()
    raw = copy.deepcopy(local_raw)
    raw["hosts"]["fetch-1"].update({"kuberos_link_bandwidth": "4 Mbit/s", "kuberos_link_loss": "10%"})
    sink = (
        "import socket, sys, time\n"
        "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)\n"
        "s.bind(('0.0.0.0', int(sys.argv[1]))); print('bound', flush=True); s.settimeout(20); n = 0; first = last = None\n"
        "try:\n while True:\n  d = s.recv(70000); last = time.monotonic(); first = first or last; n += 1; s.settimeout(2)\n"
        "except socket.timeout: pass\n"
        "print('got', n, (last or 0) - (first or 0), flush=True)"
    )
    with Runtime(rendered_dirs["probe"], load_inventory(raw), str(tmp_path)) as runtime:
        runtime.start(modules=False)
        edge = runtime.host_address("edge-1")
        burst = runtime.start_on("edge-1", "sink-burst", [sys.executable, "-c", sink, "7401"])
        spaced = runtime.start_on("edge-1", "sink-spaced", [sys.executable, "-c", sink, "7402"])
        wait_until(lambda: "bound" in burst.output() and "bound" in spaced.output(), STARTUP_TIMEOUT, "no sinks", runtime)
        runtime.start_on(
            "fetch-1", "source",
            [sys.executable, "-c", "import socket, time\ns = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
             f"for _ in range(3000):\n s.sendto(bytes(1000), ('{edge}', 7401)); time.sleep(0.0005)\n"
             f"for _ in range(300):\n s.sendto(bytes(100), ('{edge}', 7402)); time.sleep(0.01)\n"],
            cgroup="hardware",
        )  # fmt: skip
        wait_until(lambda: "got" in burst.output() and "got" in spaced.output(), 60, "the sinks did not finish", runtime)
        stats = runtime.fabric_stats()
    got, seconds = burst.output().split("got")[1].split()
    rate = int(got) * 1028 * 8 / max(float(seconds), 1e-3) / 1e6  # IPv4 + UDP headers: 28 bytes
    arrived = int(spaced.output().split("got")[1].split()[0])
    print(f"fetch-1 at 4 Mbit/s losing 10 %: a burst arrived at {rate:.2f} Mbit/s ({got}/3000 datagrams), "
          f"{arrived}/300 spaced datagrams arrived; fabric drops {stats['drops']}")  # fmt: skip
    assert 2.8 <= rate <= 4.2, rate
    assert 240 <= arrived <= 291, arrived
    assert stats["drops"]["loss"] > 0 and stats["drops"]["link_queue_full"] > 0, stats["drops"]


def test_cpu_quota_is_enforced_and_hardware_is_accounted_apart(rendered_dirs, local_inventory, tmp_path):
    """cpu_scale 1/16: a 4-CPU robot gets a quarter core; a busy loop there uses that much, one beside it in
    the hardware cgroup (no quota) as much as a busy loop outside the runtime gets in the same seconds (the
    reference: this machine may be busy with other work), and both groups are counted apart."""
    require_environment()
    busy = [sys.executable, "-c", "while True: pass"]
    reference = subprocess.Popen(busy)
    try:
        with Runtime(rendered_dirs["probe"], local_inventory, str(tmp_path), cpu_scale=0.0625) as runtime:
            runtime.start(modules=False)
            assert runtime.hosts["fetch-1"].cpu_cores == 0.25
            hardware_group = runtime.hosts["fetch-1"].cgroups["hardware"]
            assert read_int(os.path.join(hardware_group.cpu_dir, "cpu.cfs_quota_us")) == -1
            runtime.start_on("fetch-1", "busy-node", busy)
            runtime.start_on("fetch-1", "busy-hardware", busy, cgroup="hardware")
            time.sleep(1.0)
            before, reference_before, start = runtime.cpu_seconds(), process_cpu_seconds(reference.pid), time.monotonic()
            time.sleep(4.0)
            after, reference_after = runtime.cpu_seconds(), process_cpu_seconds(reference.pid)
            elapsed = time.monotonic() - start
    finally:
        reference.kill()
        reference.wait()
    node = (after[("fetch-1", "node")] - before[("fetch-1", "node")]) / elapsed
    hardware = (after[("fetch-1", "hardware")] - before[("fetch-1", "hardware")]) / elapsed
    outside = (reference_after - reference_before) / elapsed
    print(
        f"quota 0.25 core: the node cgroup used {node:.3f} cores, the hardware cgroup {hardware:.3f}, "
        f"a busy loop outside the runtime {outside:.3f}"
    )
    assert node <= 0.25 + 0.04, f"node cgroup used {node:.3f} cores with a 0.25 quota"
    assert node >= 0.25 - 0.04 or outside < 0.25, f"node cgroup used {node:.3f} cores of its 0.25 on a machine that had them"
    assert hardware >= 0.6 * outside, (
        f"the unlimited hardware cgroup used {hardware:.3f} cores, a busy loop outside the runtime {outside:.3f}"
    )
    assert runtime.cpu_seconds() and runtime.cpu_seconds_by_tier()["onboard"] >= after[("fetch-1", "node")]  # kept after close


def read_int(path: str) -> int:
    with open(path, encoding="utf-8") as handle:
        return int(handle.read().strip())


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU time of one process (/proc/<pid>/stat, fields 14 and 15, in clock ticks)."""
    with open(f"/proc/{pid}/stat", encoding="utf-8") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_busy_hosts_share_a_core_in_proportion_to_their_size(rendered_dirs, local_inventory, tmp_path):
    """cpu_scale 1/4: a robot computer gets 1 core, an edge server 2 (this machine's cores). Two busy loops on one
    core, one on each host, are below both quotas, so the kernel divides that core by the groups' weights: 1:2,
    as the hosts' sizes (with the kernel's equal default weights it was 1:1, and an edge server of 18 processes
    got no more CPU than one robot's physics). The hardware group keeps the default weight."""
    require_environment()
    if machine_cores() < 2:
        pytest.skip("needs 2 cores: the edge server's quota must exceed the robot computer's")
    busy = ["taskset", "-c", "0", sys.executable, "-c", "while True: pass"]
    with Runtime(rendered_dirs["probe"], local_inventory, str(tmp_path), cpu_scale=0.25) as runtime:
        runtime.start(modules=False)
        robot, edge = runtime.hosts["fetch-1"], runtime.hosts["edge-1"]
        assert (robot.cpu_cores, edge.cpu_cores) == (1.0, 2.0)
        shares = {
            name: int(open(os.path.join(group.cpu_dir, "cpu.shares"), encoding="utf-8").read())
            for name, group in (
                ("robot", robot.cgroups["node"]),
                ("edge", edge.cgroups["node"]),
                ("hardware", robot.cgroups["hardware"]),
            )
        }
        assert shares == {"robot": 2048, "edge": 4096, "hardware": 1024}
        runtime.start_on("fetch-1", "busy-robot", busy)
        runtime.start_on("edge-1", "busy-edge", busy)
        time.sleep(1.0)
        before, start = runtime.cpu_seconds(), time.monotonic()
        time.sleep(4.0)
        after, elapsed = runtime.cpu_seconds(), time.monotonic() - start
    used = {node: (after[(node, "node")] - before[(node, "node")]) / elapsed for node in ("fetch-1", "edge-1")}
    print(f"one core shared: robot computer {used['fetch-1']:.3f}, edge server {used['edge-1']:.3f} cores")
    assert used["edge-1"] > 1.5 * used["fetch-1"], used


def assert_rtt(runtime: Runtime, source: str, target: str) -> float:
    """Ping from ``source`` to ``target``: the inventory's RTT, within test_ping_rtt_matches_the_inventory's bounds."""
    expected = rtt_ms(runtime.inventory, source, target)
    measured = ping_rtt_ms(runtime, source, target, count=10)
    assert expected - 0.05 <= measured <= expected + max(expected * RTT_TOLERANCE, 0.75), (
        f"{source} -> {target}: {measured:.3f} ms measured, {expected} ms expected"
    )
    return measured


def test_a_host_added_and_removed_while_the_run_goes_on(rendered_dirs, local_inventory, tmp_path):
    """A cloud VM provisioned during the run (a node the inventory did not have, as the burst adds it): made a host
    live, no running host's address moving, reached with its latency, running a process; removed: the process
    stopped, its namespace and cgroups gone, its CPU still counted, the fabric forwarding between the others. The
    freed address goes to the next host added, which close() removes like the others."""
    require_environment()
    vm = Node("burst-1", "cloud", 8000, 16 << 30, resource_group="cloud-eu", latency_ms=30.0)
    with Runtime(rendered_dirs["probe"], local_inventory, str(tmp_path)) as runtime:
        runtime.start(modules=False)
        addresses = {node: host.address for node, host in runtime.hosts.items()}
        host = runtime.add_host("burst-1", runtime.inventory.with_nodes([vm]))
        assert {node: runtime.hosts[node].address for node in addresses} == addresses
        assert host.address not in addresses.values() and host.tier == "cloud" and host.cpu_cores == 1.0
        quota = open(os.path.join(host.cgroups["node"].cpu_dir, "cpu.cfs_quota_us"), encoding="utf-8").read()
        shares = open(os.path.join(host.cgroups["node"].cpu_dir, "cpu.shares"), encoding="utf-8").read()
        assert (int(quota), int(shares)) == (100_000, 2048)
        there = assert_rtt(runtime, "fetch-1", "burst-1")
        back = assert_rtt(runtime, "burst-1", "fetch-2")
        edge = assert_rtt(runtime, "edge-1", "burst-1")  # edge-cloud: the VM's latency
        busy = runtime.start_on("burst-1", "busy", [sys.executable, "-c", "while True: pass"])
        wait_until(lambda: runtime.cpu_seconds()[("burst-1", "node")] > 0.5, 20, "the VM's process used no CPU", runtime)
        stopped = runtime.remove_host("burst-1")
        assert stopped == [busy] and not busy.running and busy in runtime.stopped and "burst-1" not in runtime.hosts
        assert not os.path.exists(f"/var/run/netns/{host.netns}") and not os.path.exists(f"/etc/netns/{host.netns}")
        assert not any(os.path.exists(d) for group in host.cgroups.values() for d in group.dirs)
        used = runtime.removed[-1].cpu_seconds["node"]
        assert used > 0.5 and runtime.cpu_seconds()[("burst-1", "node")] == used
        assert runtime.cpu_seconds_by_tier()["cloud"] == used  # the run's only cloud host
        lan = assert_rtt(runtime, "fetch-2", "fetch-1")
        again = runtime.add_host("cloud-1")  # in the fixture's inventory, not a host yet
        assert again.address == host.address
        cloud = assert_rtt(runtime, "fetch-1", "cloud-1")
        # the fabric writes its figures once a second: those of the pings just sent may come a write later
        wait_until(
            lambda: "fetch-1->cloud-1" in runtime.fabric_stats().get("pairs", {}), 10, "no figures of fetch-1->cloud-1", runtime
        )
        pairs = runtime.fabric_stats()["pairs"]
        assert pairs["fetch-1->burst-1"]["packets"] >= 5 and pairs["fetch-1->cloud-1"]["delay_ms"] == 20.0
        reloads = list(runtime.fabric_reload_seconds)
    print(f"RTT through hosts added live: fetch-1 -> burst-1 {there:.3f} ms, burst-1 -> fetch-2 {back:.3f} ms, "
          f"edge-1 -> burst-1 {edge:.3f} ms (30 ms in the inventory), fetch-1 -> cloud-1 {cloud:.3f} ms (40), "
          f"fetch-2 -> fetch-1 {lan:.3f} ms after the removal (1); fabric reloads "
          f"{', '.join(f'{r * 1000:.1f}' for r in reloads)} ms; burst-1 used {used:.2f} CPU seconds")  # fmt: skip
    assert len(reloads) == 3 and max(reloads) < 1.0, reloads  # its wait is up to a second (stats_interval) otherwise
    assert runtime.leftovers() == [] and not runtime.close_problems, (runtime.leftovers(), runtime.close_problems)
    assert runtime.cpu_seconds()[("burst-1", "node")] == used and ("cloud-1", "node") in runtime.cpu_seconds()


def test_an_early_exit_is_reported_with_its_log_and_everything_is_removed(rendered_dirs, local_inventory, tmp_path):
    require_environment()
    runtime = Runtime(rendered_dirs["failing"], local_inventory, str(tmp_path))
    with pytest.raises(ProcessExitedError) as error:
        runtime.start()
    assert "exited 3" in str(error.value) and "boom before exit" in str(error.value), error.value
    assert runtime.leftovers() == []


def test_teardown_leaves_no_namespaces_cgroups_etc_netns_or_processes(rendered_dirs, local_inventory, tmp_path):
    require_environment()
    with pytest.raises(KeyError), Runtime(rendered_dirs["probe"], local_inventory, str(tmp_path)) as runtime:
        runtime.start()
        extra = runtime.start_on("fetch-2", "sleeper", ["sh", "-c", "sleep 600 & sleep 600"], cgroup="hardware")
        hosts = list(runtime.hosts.values())
        assert all(os.path.exists(f"/etc/netns/{h.netns}/hosts") for h in hosts)
        assert os.path.isdir(f"/sys/fs/cgroup/cpu/{runtime.cgroup_parent}/fetch-2.hardware")
        raise KeyError("an exception inside the run")
    assert runtime.leftovers() == [] and not runtime.close_problems, (runtime.leftovers(), runtime.close_problems)
    listed = run("ip", "netns", "list").stdout
    assert all(h.netns not in listed for h in hosts), listed
    for root in ("/sys/fs/cgroup/cpu", "/sys/fs/cgroup/cpuacct"):
        assert not os.path.exists(os.path.join(root, runtime.cgroup_parent))
    assert not any(os.path.exists(f"/etc/netns/{h.netns}") for h in hosts)
    assert not extra.running
    assert run("pgrep", "-f", f"krs-{runtime.suffix}", check=False).returncode == 1
