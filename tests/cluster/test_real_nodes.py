"""Real pods on real kubelets: the local cluster's real-node tier (docs/real-nodes.md).

One cluster for this module, started with playbooks/local_cluster.yml on inventories/real-pods (robot-1,
edge-1, edge-2 and cloud-1 as real nodes: a kubelet, containerd and kube-proxy each, in network namespaces
linked by the delay fabric with the inventory's round-trip times: robot-edge 5 ms, robot-cloud 40 ms), on
ports and addresses of its own. The tests run in order:

- the nodes register with the inventory's labels and taints and are Ready; starting again changes nothing;
- a listener on cloud-1 hears a talker on robot-1 through a Fast DDS discovery server pod on edge-1 reached by
  its Service name (CoreDNS, kube-proxy); the same listener program pointed at a Service without the server
  hears nothing (the negative control);
- ROS 2 round trips between a pod on robot-1 and pods on edge-1 and cloud-1 show the inventory's delays;
- playbooks/deploy.yml places and applies the pick-and-place example: every instance runs as a pod on the node
  its placement names, and the robot's simulated hardware on robot-1 completes a pick cycle with them;
- the kubelet of a node stopped: the controller moves its modules and they run again on another node;
- teardown (local_cluster_state=absent, twice: the second changes nothing) leaves the host as it was
  (namespaces, links, mounts, cgroups, routes, iptables, sysctls, CNI state, processes).
"""

from __future__ import annotations

import functools
import json
import os
import re
import shlex
import statistics
import subprocess
import sys
import threading
import time

import pytest
import yaml
from helpers import ROOT
from real_tier import (
    PROMETHEUS,
    ROS_IMAGE,
    RealCluster,
    apply_objects,
    bridge_round_trips,
    container_of,
    controller_pods,
    cut_off_robot,
    events_of,
    heard,
    lease_holder,
    logs,
    placed_instances,
    pod_ready,
    program_pod,
    programs_configmap,
    prometheus_api,
    prometheus_objects,
    ros_in_container,
    running_instances,
    udp_flows,
    wait_for,
)  # fmt: skip

sys.path.insert(0, os.path.join(ROOT, ".collections"))
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import (
    RealNodes,
    snapshot_changes,
    snapshot_host,
)

pytestmark = [pytest.mark.cluster, pytest.mark.real_nodes]

REAL_PORTS = {
    "apiserver": 28443,
    "etcd_client": 28379,
    "etcd_peer": 28380,
    "controller_manager": 28257,
    "scheduler": 28259,
    "kwok": 28247,
}
BASE, TAG = 241, "kt"  # addresses 10.241-243.x, names kt...: apart from a developer's real nodes (10.231, kr)
NODES = ["cloud-1", "edge-1", "edge-2", "robot-1"]
SPEC = os.path.join(ROOT, "examples", "pick-and-place.yml")
GRACE = 2
UNREACHABLE_S = 10  # the API server's default toleration of an unreachable node, shortened (Kubernetes: 300 s)
PAIR_S = 20.0  # two talker-listener pairs started on the cut-off robot run this long


def require_real_nodes() -> None:
    problems = []  # the programs built from the Go module proxy are the role's to build
    if os.geteuid() != 0:
        problems.append("real nodes need root")
    for program in ("containerd", "runc", "socat", "umoci", "debootstrap"):
        if not any(os.access(os.path.join(d, program), os.X_OK) for d in os.environ.get("PATH", "").split(":")):
            problems.append(f"{program} is not installed (scripts/setup.sh installs it)")
    if RealNodes.cni_bin_dir() is None:
        problems.append("the CNI plugins are not installed (containernetworking-plugins)")
    if problems:
        message = "; ".join(problems)
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    require_real_nodes()
    before = snapshot_host()
    cluster = RealCluster(
        tmp_path_factory.mktemp("real-cluster"), REAL_PORTS, BASE, TAG, local_cluster_unreachable_toleration_s=UNREACHABLE_S
    )
    cluster.before = before
    try:
        started = time.monotonic()
        result = cluster.start()
        assert result.returncode == 0, result.stdout[-8000:] + result.stderr[-3000:]
        cluster.start_seconds = time.monotonic() - started
        cluster.connect()
        yield cluster
    finally:
        cluster.stop(state="absent")


@pytest.fixture(scope="module")
def lab(real):
    """A namespace with the test's ROS programs (a ConfigMap) and a discovery server pod on edge-1 + its Service."""
    namespace = "real-node-test"
    real.core.create_namespace({"metadata": {"name": namespace}})
    programs_configmap(real.core, namespace)
    server = program_pod("discovery", "edge-1", namespace, [], {})
    server["spec"]["containers"][0].update(
        command=["fast-discovery-server", "-i", "0", "-l", "0.0.0.0", "-p", "11811"], args=[], volumeMounts=[]
    )
    server["spec"]["volumes"] = []
    real.core.create_namespaced_pod(namespace, server)
    for name, selector in (("discovery", {"test": "discovery"}), ("no-discovery", {"test": "nothing-here"})):
        real.core.create_namespaced_service(
            namespace,
            {
                "metadata": {"name": name},
                "spec": {"selector": selector, "ports": [{"name": "dds", "port": 11811, "protocol": "UDP", "targetPort": 11811}]},
            },
        )
    yield namespace
    try:
        real.core.delete_namespace(namespace)
    except Exception:
        pass


def ros_env(service, namespace):
    return {"ROS_DISCOVERY_SERVER": f"{service}.{namespace}.svc.cluster.local:11811", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


def phase(real, namespace, pod):
    try:
        found = real.core.read_namespaced_pod(pod, namespace)
    except Exception:
        return None
    return found.status.phase, found.spec.node_name, found.status.pod_ip


# -- the tests, in order ---------------------------------------------------------------------------------------


def test_real_nodes_register_with_the_inventorys_labels_and_taints(real):
    nodes = {n.metadata.name: n for n in real.core.list_node().items}
    assert sorted(nodes) == NODES, "every host of inventories/real-pods is a real node, none is kwok"
    for name, node in nodes.items():
        ready = {c.type: c.status for c in node.status.conditions}["Ready"]
        assert ready == "True", name
        assert node.metadata.annotations.get("kwok.x-k8s.io/node") is None
        assert node.status.node_info.kubelet_version == "v1.34.4"
        internal = [a.address for a in node.status.addresses if a.type == "InternalIP"]
        assert internal and internal[0].startswith(f"10.{BASE + 1}.0."), internal
        assert node.metadata.labels[labels.ROLE] in ("robot", "edge", "cloud"), node.metadata.labels
    robot = nodes["robot-1"]
    assert robot.metadata.labels.get(labels.FLEET) == "test-fleet"
    assert robot.metadata.labels.get(labels.DEVICE_PREFIX + "gripper") == "true"
    assert [(t.key, t.value, t.effect) for t in robot.spec.taints or []] == [(labels.ROBOT_TAINT, "robot-1", "NoSchedule")]
    print(f"real cluster started in {real.start_seconds:.1f} s")


def test_starting_the_running_real_nodes_again_changes_nothing(real):
    again = real.start()
    assert again.returncode == 0, again.stdout[-6000:]
    assert again.changed == 0, again.stdout[-6000:]


def test_discovery_through_a_service_across_two_real_nodes_with_a_negative_control(real, lab):
    wait_for(lambda: (phase(real, lab, "discovery") or ("",))[0] == "Running", 120, "the discovery server pod Running")
    talker, listener = ["/programs/talker.py", "/kuberos_chatter"], ["/programs/listener.py", "/kuberos_chatter"]
    pods = {
        "talker": program_pod("talker", "robot-1", lab, talker, ros_env("discovery", lab), robot=True),
        "listener": program_pod("listener", "cloud-1", lab, listener, ros_env("discovery", lab)),
        # the same program on the same node, its discovery Service without endpoints: nothing may arrive
        "lonely": program_pod("lonely", "cloud-1", lab, listener, ros_env("no-discovery", lab)),
    }
    for pod in pods.values():
        real.core.create_namespaced_pod(lab, pod)
    for name in pods:
        wait_for(lambda name=name: (phase(real, lab, name) or ("",))[0] == "Running", 120, f"{name} Running")
    placed = {name: phase(real, lab, name)[1] for name in ("discovery", *pods)}
    assert placed == {"discovery": "edge-1", "talker": "robot-1", "listener": "cloud-1", "lonely": "cloud-1"}
    wait_for(lambda: "received kuberos" in logs(real.core, lab, "listener"), 60, "the listener to hear the talker")
    assert "ready" in logs(real.core, lab, "lonely"), "the negative control runs"
    time.sleep(5)  # the talker keeps publishing; the control had as long as the listener and more
    assert "received" not in logs(real.core, lab, "lonely"), "a listener without a discovery server heard the talker"
    for name in pods:
        real.core.delete_namespaced_pod(name, lab, grace_period_seconds=0)


def test_ros_round_trips_between_real_nodes_show_the_inventorys_delays(real, lab):
    env = ros_env("discovery", lab)
    real.core.create_namespaced_pod(lab, program_pod("ping", "robot-1", lab, ["/programs/ros_ping.py", "ping"], env, robot=True))
    real.core.create_namespaced_pod(lab, program_pod("echo-edge", "edge-2", lab, ["/programs/ros_ping.py", "echo"], env))
    wait_for(lambda: "rtt_ms" in logs(real.core, lab, "ping"), 120, "round trips robot-1 <-> edge-2")

    def samples(count):
        return wait_for(
            lambda: (
                (v := [float(line.split()[1]) for line in logs(real.core, lab, "ping").splitlines() if line.startswith("rtt_ms")])
                and len(v) >= count
                and v
            ),
            60,
            f"{count} round trips",
        )

    edge = statistics.median(samples(20)[-15:])
    real.core.delete_namespaced_pod("echo-edge", lab, grace_period_seconds=0)
    wait_for(lambda: phase(real, lab, "echo-edge") is None, 60, "the edge echo gone")
    real.core.create_namespaced_pod(lab, program_pod("echo-cloud", "cloud-1", lab, ["/programs/ros_ping.py", "echo"], env))
    time.sleep(3)
    seen = len(samples(1))
    cloud = statistics.median(samples(seen + 25)[-15:])
    print(f"ROS round trip robot-1 <-> edge-2 {edge:.1f} ms (inventory 5 ms), <-> cloud-1 {cloud:.1f} ms (inventory 40 ms)")
    assert 5.0 <= edge < 5.0 + 25.0, edge
    assert 40.0 <= cloud < 40.0 + 25.0, cloud
    for name in ("ping", "echo-cloud"):
        real.core.delete_namespaced_pod(name, lab, grace_period_seconds=0)


@pytest.fixture(scope="module")
def deployed(real, tmp_path_factory):
    render = tmp_path_factory.mktemp("render-real")
    started = time.monotonic()
    result = real.deploy(SPEC, render)
    assert result.returncode == 0, result.stdout[-8000:] + result.stderr[-3000:]
    with open(os.path.join(render, "placement.json"), encoding="utf-8") as handle:
        placement = json.load(handle)
    real.deploy_seconds = time.monotonic() - started
    return placement


def fleet_namespace(placement):
    return placement["deployments"][0]["namespace"]


def test_deployed_instances_run_as_pods_on_the_nodes_the_placement_names(real, deployed):
    wanted = placed_instances(deployed)
    assert wanted and set(wanted.values()) <= set(NODES), deployed
    namespace = fleet_namespace(deployed)
    started = time.monotonic()
    wait_for(
        lambda: running_instances(real.core, namespace) == wanted or None,
        300,
        f"every instance Running and Ready where placed: {wanted}",
        2,
    )
    ready = time.monotonic() - started
    print(f"deploy {real.deploy_seconds:.1f} s, then all {len(wanted)} pods Running and Ready in {ready:.1f} s")


def test_the_robots_hardware_completes_a_pick_cycle_with_the_real_pods(real, deployed):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, "sim"), os.path.join(ROOT, ".collections")])}
    command = [sys.executable, "-m", "kuberos_sim.real_pods", "--kubeconfig", real.kubeconfig, "--robots", "robot-1",
               "--cycles", "1", "--time-limit", "420"]  # fmt: skip
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    print(done.stdout[-3000:])
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-3000:]
    summary = json.loads(done.stdout[done.stdout.rindex("\n{") :])
    assert summary["cycles"]["robot-1"]["succeeded"] >= 1


def test_the_discovery_servers_run_the_published_ros_layout_through_its_entrypoint(real, deployed):
    """ros:jazzy-ros-base is the published layout here (nothing of ROS on PATH, /ros_entrypoint.sh sources it):
    the servers start only because the rendered pods keep the image's entrypoint (args, not command)."""
    namespace = fleet_namespace(deployed)
    pods = real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/component=discovery-server").items
    assert len(pods) == len(deployed["discovery"][0]["servers"]) == 2
    for pod in pods:
        (container,) = pod.spec.containers
        assert container.image == "ros:jazzy-ros-base" and not container.command, container
        assert "exec fast-discovery-server" in container.args[2], container.args
        (status,) = pod.status.container_statuses
        assert status.ready and status.restart_count == 0, status
        assert "/ros-base:" in status.image or status.image.endswith("ros:jazzy-ros-base"), status.image
        running = lambda p=pod: "### Server is running ###" in logs(real.core, namespace, p.metadata.name)  # noqa: E731
        wait_for(running, 30, f"{pod.metadata.name} serving (after its start delay)")
        assert "Participant Type:   SERVER" in logs(real.core, namespace, pod.metadata.name)


def talker_and_listener_homes(real, namespace):
    """(the real nodes, an edge module's pod, its container, robot-1's onboard container): where the restart tests
    run their talker and their listeners."""
    nodes = RealNodes.from_state(real.plane(), {})
    edge = next(
        p for p in real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/component=ros-module").items
        if p.spec.node_name != "robot-1" and pod_ready(p)
    )  # fmt: skip
    edge_container = edge.status.container_statuses[0].container_id.split("://", 1)[1]
    return nodes, edge, edge_container, container_of(real.core, namespace, "robot-1")


def replacements(real, namespace, instance, old):
    """The Ready pods of ``instance`` other than ``old`` (that are not being deleted)."""
    pods = real.core.list_namespaced_pod(namespace, label_selector=f"kuberos.io/instance={instance}").items
    return [p for p in pods if p.metadata.name != old.metadata.name and pod_ready(p) and not p.metadata.deletion_timestamp]


@pytest.mark.parametrize("how", [pytest.param("container", marks=pytest.mark.full), pytest.param("pod", marks=pytest.mark.full)])
def test_a_fleet_discovery_server_killed_and_restarted_and_who_still_meets_the_participants_that_ran_before(real, deployed, how):
    """A talker runs in an edge module's container; the fleet's first discovery server is killed (SIGKILL, as a crash):
    its container (the kubelet starts it again in the same pod, at the same address) or its pod (no grace: its
    Deployment replaces it at a new address). A listener started at once with the fleet's servers hears the talker
    through the other server. A listener started later that names only the killed server hears it too: the
    replacement waited out its lease before serving, and it announces its Service's address, so the clients that ran
    before reach it also at its new pod address (docs/connectivity.md)."""
    namespace = fleet_namespace(deployed)
    nodes, edge, edge_container, robot_container = talker_and_listener_homes(real, namespace)
    server = deployed["discovery"][0]["servers"][0]
    topic = f"/kuberos_killed_{how}"
    talker = ros_in_container(nodes.socket(edge.spec.node_name), edge_container, "talker", topic, 200, False)
    try:
        time.sleep(5)
        (old,) = real.core.list_namespaced_pod(namespace, label_selector=f"kuberos.io/instance={server['name']}").items
        killed = time.monotonic()
        if how == "container":
            (status,) = old.status.container_statuses
            task = status.container_id.split("://", 1)[1]
            kill = ["ctr", "-a", nodes.socket(old.spec.node_name), "-n", "k8s.io", "tasks", "kill", "-s", "SIGKILL", task]
            subprocess.run(kill, check=True, capture_output=True, timeout=30)

            def again():
                pod = real.core.read_namespaced_pod(old.metadata.name, namespace)
                return [pod] if pod.status.container_statuses[0].restart_count > status.restart_count and pod_ready(pod) else []

            (new,) = wait_for(again, 90, f"{server['name']}'s container started again", 0.5)
        else:
            real.core.delete_namespaced_pod(old.metadata.name, namespace, grace_period_seconds=0)
            replaced = functools.partial(replacements, real, namespace, server["name"], old)
            (new,) = wait_for(replaced, 90, f"{server['name']} replaced", 0.5)
        back_s = time.monotonic() - killed
        socket = nodes.socket("robot-1")
        through_fleet = heard(ros_in_container(socket, robot_container, "listener", topic, 30, True), 30)
        later_s = time.monotonic() - killed
        through_it = heard(ros_in_container(socket, robot_container, "listener", topic, 40, server["id"]), 40)
    finally:
        talker.kill()
    print(f"{server['name']}'s {how} killed ({old.status.pod_ip} -> {new.status.pod_ip}, Ready again after {back_s:.1f} s): "
          f"a listener with the fleet's servers heard the talker {through_fleet['first_s']} s after starting; one started "
          f"{later_s:.1f} s after the kill with that server only, {through_it['first_s']} s after starting")  # fmt: skip
    assert (old.status.pod_ip == new.status.pod_ip) == (how == "container")
    assert through_fleet["first_s"] is not None and through_fleet["first_s"] < 10, through_fleet
    assert through_it["first_s"] is not None and through_it["first_s"] < 10, (
        f"a discovery server whose {how} was restarted never learned of a participant that ran before: {through_it}"
    )


@pytest.mark.parametrize(
    "how", [pytest.param("killed", marks=pytest.mark.full), pytest.param("stopped", marks=pytest.mark.full), "stopped-together"]
)
def test_the_fleets_discovery_servers_restarted_in_turn_a_module_started_after_meets_one_that_ran_before(real, deployed, how):
    """A talker starts in an edge module's container; then the fleet's two discovery server pods are deleted in turn,
    each replaced by its Deployment (a new pod address behind the same Service address) before the next goes:
    ``killed`` (no grace: as a crash or a lost node) or ``stopped`` (the default grace: the server hears SIGTERM and
    says goodbye); or both stopped at once (``stopped-together``: nobody left to copy from). A listener started
    afterwards in robot-1's onboard container, with the fleet's servers only, hears the talker that ran before the
    restarts: every node of the fleet rediscovers, because each server announces its Service's address and waits out
    its lease before it serves (docs/connectivity.md). The connection tracking of the servers' port on the talker's
    node is printed before and after."""
    namespace = fleet_namespace(deployed)
    nodes, edge, edge_container, robot_container = talker_and_listener_homes(real, namespace)
    port = real.core.read_namespaced_service(deployed["discovery"][0]["servers"][0]["name"], namespace).spec.ports[0].port
    talker_netns = nodes.nets[edge.spec.node_name].netns
    talker = ros_in_container(nodes.socket(edge.spec.node_name), edge_container, "talker", "/kuberos_restart", 200, False)
    flows = {}
    try:
        time.sleep(5)
        flows["before"] = udp_flows(talker_netns, port)
        restarted = []
        servers = deployed["discovery"][0]["servers"]
        for group in [servers] if how == "stopped-together" else [[server] for server in servers]:
            started, olds = time.monotonic(), {}
            for server in group:
                (old,) = real.core.list_namespaced_pod(namespace, label_selector=f"kuberos.io/instance={server['name']}").items
                grace = 0 if how == "killed" else None
                real.core.delete_namespaced_pod(old.metadata.name, namespace, grace_period_seconds=grace)
                olds[server["name"]] = old
            for name, old in olds.items():
                (new,) = wait_for(functools.partial(replacements, real, namespace, name, old), 90, f"{name} replaced", 0.5)
                restarted.append((name, round(time.monotonic() - started, 1), old.status.pod_ip, new.status.pod_ip))
        flows["after the restarts"] = udp_flows(talker_netns, port)
        listener = ros_in_container(nodes.socket("robot-1"), robot_container, "listener", "/kuberos_restart", 90, True)
        got = heard(listener, 90)
        flows["at the end"] = udp_flows(talker_netns, port)
    finally:
        talker.kill()
    seen = "\n".join(f"  {when}:\n" + "\n".join(f"    {line}" for line in lines) for when, lines in flows.items())
    print(f"discovery servers {how} {restarted}; a listener started after on robot-1 heard the edge talker "
          f"that ran before after {got['first_s']} s ({got['messages']} messages); UDP flows to port {port} in "
          f"{talker_netns}:\n{seen}")  # fmt: skip
    assert all(old_ip != new_ip for _name, _s, old_ip, new_ip in restarted), restarted
    assert got["servers"] and len(got["servers"].split(";")) == 2, got
    assert got["first_s"] is not None, f"a module started after the servers' restarts never heard one from before: {got}\n{seen}"


# -- the lab registry: pulls by digest with pull secrets ---------------------------------------------------------


def registry_state(real):
    """(address, {built image: pull reference by digest}, password) of the tier's registry."""
    directory = os.path.join(real.state_dir, "nodes", "registry")
    with open(os.path.join(directory, "images.json"), encoding="utf-8") as handle:
        served = json.load(handle)
    with open(os.path.join(directory, "password"), encoding="utf-8") as handle:
        password = handle.read().strip()
    return f"10.{BASE}.0.1:5443", served, password


def pull_secret(real, namespace, name, address, password):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import docker_config_json

    secret = {
        "metadata": {"name": name},
        "type": "kubernetes.io/dockerconfigjson",
        "stringData": {".dockerconfigjson": docker_config_json(address, "kuberos", password)},
    }
    real.core.create_namespaced_secret(namespace, secret)


def registry_spec(name, image, secret):
    hello = "import rclpy, time; print('hello from the registry', flush=True); time.sleep(3600)"
    return {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosDeployment",
        "metadata": {"name": name, "targetFleet": "test-fleet"},
        "imageRegistries": [{"name": "default", "pullSecret": secret, "pullPolicy": "Always"}],
        "rosModules": [
            {
                "name": "hello",
                "image": image,
                "launch": [shlex.join(["python3", "-c", hello])],
                "preference": ["cloud", "edge"],
                "resources": {"cpu": "100m", "memory": "128Mi"},
            }
        ],
    }


def test_pods_pull_by_digest_from_the_registry_with_a_pull_secret_on_every_node(real, lab):
    """The published-layout image by digest, imagePullPolicy Always (the kubelet asks the registry each time), the
    credentials from a kubernetes.io/dockerconfigjson Secret; each node's containerd trusts the registry's CA."""
    address, served, password = registry_state(real)
    (image,) = [ref for built, ref in served.items() if "/ros-base:" in built]
    assert image.startswith(f"{address}/kuberos/ros-base@sha256:")
    pull_secret(real, lab, "lab-registry", address, password)
    names = []
    for node in NODES:
        name = f"pull-{node}"
        pod = program_pod(name, node, lab, [], {}, robot=node.startswith("robot"))
        container = pod["spec"]["containers"][0]
        container.update(image=image, imagePullPolicy="Always", command=None, volumeMounts=[],
                         args=["python3", "-c", "import rclpy; print('pulled and sourced', rclpy.__name__)"])  # fmt: skip
        pod["spec"].update(volumes=[], restartPolicy="Never", imagePullSecrets=[{"name": "lab-registry"}])
        real.core.create_namespaced_pod(lab, pod)
        names.append(name)
    for name in names:
        wait_for(lambda name=name: (phase(real, lab, name) or ("",))[0] == "Succeeded", 180, f"{name} Succeeded")
        assert "pulled and sourced rclpy" in logs(real.core, lab, name)
    pulled = {}
    for event in real.core.list_namespaced_event(lab, field_selector="reason=Pulled").items:
        if event.involved_object.name in names and "Successfully pulled" in event.message:
            pulled[event.involved_object.name] = event.message.split(" in ", 1)[1]
    print("pulled:", pulled)
    assert sorted(pulled) == sorted(names)
    for name in names:
        real.core.delete_namespaced_pod(name, lab, grace_period_seconds=0)


@pytest.mark.parametrize(
    "case, expected",
    [
        ("wrong password", "the registry refused the credentials"),
        ("unknown image", "the registry has no such image"),
    ],
)
def test_a_deploy_whose_image_cannot_be_pulled_fails_in_one_sentence_naming_the_image_and_registry(
    real, deployed, tmp_path, case, expected
):
    address, served, password = registry_state(real)
    (image,) = [ref for built, ref in served.items() if "/ros-base:" in built]
    namespace = fleet_namespace(deployed)
    name = "registry-" + case.replace(" ", "-")
    if case == "wrong password":
        pull_secret(real, namespace, name, address, password + "-wrong")
    else:
        pull_secret(real, namespace, name, address, password)
        image = image.rpartition("@")[0] + "@sha256:" + "0" * 64
    spec = tmp_path / f"{name}.yml"
    spec.write_text(yaml.safe_dump(registry_spec(name, image, name)), encoding="utf-8")
    started = time.monotonic()
    try:
        result = real.deploy(str(spec), tmp_path / "render")
        elapsed = time.monotonic() - started
        assert result.returncode != 0
        text = result.stdout + result.stderr
        assert f"robot-1/hello cannot start: image {image} from registry {address}: {expected}" in text, text[-5000:]
        assert elapsed < 150, f"the deploy waited {elapsed:.0f} s for a pull that cannot succeed"
    finally:
        undo = real.play("undeploy.yml", "-e", f"rosdeployment_file={spec}")
        assert undo.returncode == 0, undo.stdout[-3000:]
        real.core.delete_namespaced_secret(name, namespace)


def test_a_deploy_pulls_its_modules_by_digest_with_the_pull_secret_named_in_image_registries(real, deployed, tmp_path):
    address, served, password = registry_state(real)
    (image,) = [ref for built, ref in served.items() if "/ros-base:" in built]
    namespace = fleet_namespace(deployed)
    pull_secret(real, namespace, "registry-good", address, password)
    spec = tmp_path / "registry-good.yml"
    spec.write_text(yaml.safe_dump(registry_spec("registry-good", image, "registry-good")), encoding="utf-8")
    try:
        result = real.deploy(str(spec), tmp_path / "render")
        assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
        pods = real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/deployment=registry-good").items
        assert len(pods) == 1 and pods[0].spec.image_pull_secrets[0].name == "registry-good"
        assert pods[0].spec.containers[0].image == image and not pods[0].spec.containers[0].command
        pod = pods[0].metadata.name
        wait_for(lambda: "hello from the registry" in logs(real.core, namespace, pod), 60, "the module's output")
    finally:
        undo = real.play("undeploy.yml", "-e", f"rosdeployment_file={spec}")
        assert undo.returncode == 0, undo.stdout[-3000:]
        real.core.delete_namespaced_secret("registry-good", namespace)


# -- rollouts with real containers ----------------------------------------------------------------------------------

VERSIONED = "import rclpy, sys, time; print('talker version', sys.argv[1], flush=True); rclpy.init(); time.sleep(3600)"


def test_a_rollout_upgrades_a_real_container_and_a_broken_image_stops_at_the_canary(real, deployed, tmp_path):
    """A catalog module in three versions, each an image in the lab registry pulled by digest: 0.1.0 the published
    ROS layout, 0.2.0 the collection's image, 0.2.1 an image whose entrypoint exits at start (derived in the
    registry from 0.2.0: the same layers, another configuration). Deploy 0.1.0; roll out to 0.2.0 (it runs for
    real, the downtime polled includes the container's start); roll out to 0.2.1: the canary's pod exits, the gate
    stops the rollout and rolls the canary back to 0.2.0, which still runs."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import RegistryClient, lab_repository

    address, served, password = registry_state(real)
    # the catalog's form: the image by name and tag, its digest apart (rendered as name:tag@digest)
    tagged = {}  # "ros" -> (registry/kuberos/ros:<key>, digest)
    for built, ref in served.items():
        repository, tag = lab_repository(built)
        tagged[repository.split("/")[-1]] = (f"{address}/{repository}:{tag}", ref.split("@")[1])
    ca = os.path.join(real.state_dir, "nodes", "registry", "ca.crt")
    client = RegistryClient(address, "kuberos", password, ca)
    repository = lab_repository(next(built for built in served if "/ros:" in built))[0]
    broken_digest = client.derive_image(repository, tagged["ros"][1], "0.2.1-broken", Entrypoint=["/bin/sh", "-c", "exit 3"])
    versions = [
        ("0.1.0", *tagged["ros-base"]),
        ("0.2.0", *tagged["ros"]),
        ("0.2.1", f"{address}/{repository}:0.2.1-broken", broken_digest),
    ]
    catalog = {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosModuleCatalog",
        "modules": [
            {
                "name": "real-talker",
                "versions": [
                    {"version": version, "image": image, "digest": digest, "rosDistro": "jazzy",
                     "launch": [shlex.join(["python3", "-c", VERSIONED, version])], "preference": ["cloud", "edge"],
                     "resources": {"cpu": "100m", "memory": "128Mi"}}
                    for version, image, digest in versions
                ],
            }
        ],
    }  # fmt: skip
    (tmp_path / "catalog").mkdir()
    (tmp_path / "catalog" / "talker.yml").write_text(yaml.safe_dump(catalog), encoding="utf-8")
    namespace = fleet_namespace(deployed)
    pull_secret(real, namespace, "rollout-registry", address, password)

    def spec(version_range):
        path = tmp_path / f"talker-{version_range.strip('^')}.yml"
        document = {
            "apiVersion": "kuberos.io/v1alpha1",
            "kind": "RosDeployment",
            "metadata": {"name": "real-rollout", "targetFleet": "test-fleet"},
            "imageRegistries": [{"name": "default", "pullSecret": "rollout-registry"}],
            "rosModules": [{"name": "talker", "module": f"real-talker@{version_range}"}],
        }
        path.write_text(yaml.safe_dump(document), encoding="utf-8")
        return str(path)

    catalog_var = ("-e", f"kuberos_catalog={tmp_path / 'catalog'}")

    def running():
        pods = real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/deployment=real-rollout").items
        return [p for p in pods if p.metadata.deletion_timestamp is None]

    def images():
        return sorted(p.spec.containers[0].image.rsplit("@", 1)[1] for p in running())

    try:
        result = real.deploy(spec("^0.1"), tmp_path / "render", *catalog_var)
        assert result.returncode == 0, result.stdout[-6000:]
        assert images() == [tagged["ros-base"][1]]
        wait_for(lambda: "talker version 0.1.0" in logs(real.core, namespace, running()[0].metadata.name), 60, "0.1.0 talking")

        down, stop = [], threading.Event()

        def watch():
            since = None
            while not stop.is_set():
                ready = any(all(s.ready for s in p.status.container_statuses or [False]) for p in running())
                now = time.monotonic()
                if not ready and since is None:
                    since = now
                elif ready and since is not None:
                    down.append(now - since)
                    since = None
                time.sleep(0.2)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        started = time.monotonic()
        upgraded = real.play("rollout.yml", "-e", f"rosdeployment_file={spec('0.2.0')}", "-e", "rosdeployment_rollout_soak=3",
                             *catalog_var)  # fmt: skip
        stop.set()
        watcher.join()
        assert upgraded.returncode == 0, upgraded.stdout[-6000:]
        assert images() == [tagged["ros"][1]], "0.2.0 runs, pulled by digest"
        wait_for(lambda: "talker version 0.2.0" in logs(real.core, namespace, running()[0].metadata.name), 60, "0.2.0 talking")
        took, longest = time.monotonic() - started, max(down, default=0.0)
        print(f"rollout 0.1.0 -> 0.2.0 on real nodes: {took:.1f} s, longest downtime {longest:.1f} s")

        broken = real.play("rollout.yml", "-e", f"rosdeployment_file={spec('0.2.1')}", "-e", "rosdeployment_rollout_soak=3",
                           "-e", "rosdeployment_rollout_gate_timeout=90", *catalog_var)  # fmt: skip
        assert broken.returncode != 0, broken.stdout[-3000:]
        assert "stopped at the canary" in broken.stdout and "rolled back robots robot-1" in broken.stdout, broken.stdout[-4000:]
        wait_for(lambda: images() == [tagged["ros"][1]], 120, "the canary back on 0.2.0")
        talking = lambda: "talker version 0.2.0" in logs(real.core, namespace, running()[0].metadata.name)  # noqa: E731
        wait_for(talking, 60, "0.2.0 talking again")
        print("broken 0.2.1 stopped at the canary and rolled back to 0.2.0")
    finally:
        undo = real.play("undeploy.yml", "-e", f"rosdeployment_file={spec('^0.1')}", *catalog_var)
        assert undo.returncode == 0, undo.stdout[-3000:]
        real.core.delete_namespaced_secret("rollout-registry", namespace)


# A worker that stops at once on SIGTERM (a python without a handler, as PID 1 of its container, ignores it: its pod
# would take the whole 30 s grace period to stop, in every downtime alike)
WORKER = (
    "import signal, sys, time; signal.signal(signal.SIGTERM, lambda *_: sys.exit(0)); "
    "print('worker version', sys.argv[1], flush=True); time.sleep(3600)"
)
PRESTAGE_BYTES = 40 * 10**6  # each new version's own layer: random, so the robot must download it
PRESTAGE_LINK_BPS = 40e6  # robot-1's control link (to the registry) while the versions roll out: about 8 s per layer


def test_a_rollout_pre_pulls_a_robots_new_image_so_the_robots_downtime_leaves_out_the_pull(real, deployed, tmp_path):
    """An onboard module that stops before its new version starts (upgrade: recreate) on robot-1, whose link to the
    registry is limited to 40 Mbit/s; each new version brings a layer of 40 MB of its own. Rolled out without
    pre-pulling, the module is down while its image crosses the link; with pre-pulling (the default), the image is
    on the robot before the wave and the module is down only for the restart. The downtimes side by side."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import RegistryClient, lab_repository

    address, served, password = registry_state(real)
    ca = os.path.join(real.state_dir, "nodes", "registry", "ca.crt")
    client = RegistryClient(address, "kuberos", password, ca)
    built = next(b for b in served if "/ros:" in b)
    repository, tag = lab_repository(built)
    base = served[built].split("@")[1]
    versions = [("1.0.0", f"{address}/{repository}:{tag}", base)]
    for version in ("1.1.0", "1.2.0"):
        digest = client.derive_image(repository, base, f"prestage-{version}", extra_bytes=PRESTAGE_BYTES)
        versions.append((version, f"{address}/{repository}:prestage-{version}", digest))
    catalog = {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosModuleCatalog",
        "modules": [
            {
                "name": "robot-worker",
                "versions": [
                    {"version": version, "image": image, "digest": digest, "rosDistro": "jazzy",
                     "launch": [shlex.join(["python3", "-c", WORKER, version])], "upgrade": "recreate",
                     "requirements": {"onboard": True}, "resources": {"cpu": "100m", "memory": "128Mi"}}
                    for version, image, digest in versions
                ],
            }
        ],
    }  # fmt: skip
    (tmp_path / "catalog").mkdir()
    (tmp_path / "catalog" / "worker.yml").write_text(yaml.safe_dump(catalog), encoding="utf-8")
    namespace = fleet_namespace(deployed)
    pull_secret(real, namespace, "prestage-registry", address, password)
    nodes = RealNodes.from_state(real.plane(), {})

    def spec(version):
        path = tmp_path / f"worker-{version}.yml"
        document = {
            "apiVersion": "kuberos.io/v1alpha1",
            "kind": "RosDeployment",
            "metadata": {"name": "prestage", "targetFleet": "test-fleet", "robotSelector": {"robot": ["robot-1"]}},
            "imageRegistries": [{"name": "default", "pullSecret": "prestage-registry"}],
            "rosModules": [{"name": "worker", "module": f"robot-worker@{version}"}],
        }
        path.write_text(yaml.safe_dump(document), encoding="utf-8")
        return str(path)

    catalog_var = ("-e", f"kuberos_catalog={tmp_path / 'catalog'}")

    def roll(version, prestage):
        done = real.play(
            "rollout.yml", "-e", f"rosdeployment_file={spec(version)}", "-e", "rosdeployment_rollout_soak=2",
            "-e", f"rosdeployment_rollout_prestage={str(prestage).lower()}", "-e", "rosdeployment_rollout_gate_timeout=180",
            *catalog_var,
        )  # fmt: skip
        assert done.returncode == 0, done.stdout[-6000:]
        found = re.search(r"longest time a module had no Ready pod: ([\d.]+) s", done.stdout)
        assert found, done.stdout[-3000:]
        return float(found.group(1)), done.stdout

    try:
        result = real.deploy(spec("1.0.0"), tmp_path / "render", *catalog_var)
        assert result.returncode == 0, result.stdout[-6000:]
        assert nodes.shape("robot-1", PRESTAGE_LINK_BPS)
        without, _out = roll("1.1.0", prestage=False)
        with_prestage, out = roll("1.2.0", prestage=True)
        staged = re.search(r"pre-pulled 1 image\(s\) onto 1/1 robot\(s\) in ([\d.]+) s", out)
        assert staged, out[-3000:]
        pull_s = float(staged.group(1))
        print(f"robot-1 at {PRESTAGE_LINK_BPS / 1e6:g} Mbit/s, a new {PRESTAGE_BYTES / 1e6:g} MB layer per version: "
              f"downtime {without:.1f} s without pre-pulling, {with_prestage:.1f} s with "
              f"(the pre-pull took {pull_s:.1f} s)")  # fmt: skip
        assert pull_s >= PRESTAGE_BYTES * 8 / PRESTAGE_LINK_BPS * 0.8, "the layer crossed the limited link"
        assert without >= with_prestage + 0.5 * pull_s, (without, with_prestage, pull_s)
    finally:
        nodes.shape("robot-1", None)
        undo = real.play("undeploy.yml", "-e", f"rosdeployment_file={spec('1.0.0')}", *catalog_var)
        assert undo.returncode == 0, undo.stdout[-3000:]
        real.core.delete_namespaced_secret("prestage-registry", namespace)
        gone = lambda: not real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/deployment=prestage").items  # noqa: E731
        wait_for(gone, 90, "the prestage deployment's pods gone")


# -- resource defaults: rclpy modules without `resources` under a 1 kHz load -----------------------------------------

LOAD = (  # a publisher at RATE Hz of 64-byte strings, or a subscriber that says how many it got every 5 s
    "import sys, rclpy; from std_msgs.msg import String; role, rate = sys.argv[1], float(sys.argv[2]); rclpy.init(); "
    "node = rclpy.create_node('load_' + role); got = [0]\n"
    "if role == 'pub':\n    pub = node.create_publisher(String, 'load', 10); msg = String(data='x' * 64); "
    "node.create_timer(1.0 / rate, lambda: pub.publish(msg))\n"
    "else:\n    node.create_subscription(String, 'load', lambda m: got.__setitem__(0, got[0] + 1), 10); "
    "node.create_timer(5.0, lambda: print('received', got[0], flush=True))\n"
    "rclpy.spin(node)"
)


def memory_peak(real, pod) -> int:
    """The pod's memory cgroup high-water mark (cgroup v1 cgroupfs: <kubelet root>/kubepods/<qos>/pod<uid>)."""
    node = pod.spec.node_name
    net = RealNodes.from_state(real.plane(), {}).nets[node]
    pattern = f"/sys/fs/cgroup/memory/{net.cgroup}/kubepods*/**/pod{pod.metadata.uid}/memory.max_usage_in_bytes"
    import glob

    (path,) = glob.glob(pattern, recursive=True) or [None]
    assert path, pattern
    with open(path, encoding="utf-8") as handle:
        return int(handle.read())


# -- declared topics, checked live -----------------------------------------------------------------------------------

# A talker and a listener of std_msgs/String on <robot>/chatter, with the reliability (and rate) given as arguments.
_NODE = (
    "import os, sys, rclpy; from rclpy.qos import QoSProfile, ReliabilityPolicy; from std_msgs.msg import String; "
    "rclpy.init(); node = rclpy.create_node(sys.argv[1], namespace='/' + os.environ['KUBEROS_ROBOT_NAME'].replace('-', '_')); "
    "qos = QoSProfile(depth=10, reliability=getattr(ReliabilityPolicy, sys.argv[2])); "
)
TALKER = _NODE + (
    "pub = node.create_publisher(String, 'chatter', qos); "
    "node.create_timer(1.0 / float(sys.argv[3]), lambda: pub.publish(String(data='chat'))); "
    "print('talking at', sys.argv[3], 'Hz', flush=True); rclpy.spin(node)"
)
LISTENER = _NODE + (
    "heard = []; "
    "node.create_subscription(String, 'chatter', lambda m: heard or (heard.append(1), print('heard', m.data, flush=True)), qos); "
    "print('listening', flush=True); rclpy.spin(node)"
)


def _topic(direction, reliability, rate_min=None):
    topic = {"name": "chatter", "type": "std_msgs/msg/String", "qos": {"reliability": reliability}}
    return {direction: [{**topic, "rate": {"min": rate_min}} if rate_min else topic]}


def test_declared_topics_are_checked_live_after_deploy_and_in_a_rollouts_gate(real, deployed, tmp_path):
    """Modules that declare their topics, as real rclpy pods. A talker at 10 Hz and a listener, both best effort, as
    declared: the deploy's live check passes. A rollout to a talker at 1 Hz under its declared 5 Hz: the canary's
    gate fails on the rate and the canary is rolled back. A talker that declares reliable but publishes best effort
    (the declarations match, so deploy accepts them): the live check names both nodes and why, and the deploy fails."""
    image = ROS_IMAGE
    catalog = {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosModuleCatalog",
        "modules": [{"name": "graph-talker", "versions": [
            {"version": version, "image": image, "launch": [shlex.join(["python3", "-c", TALKER, "talker", "BEST_EFFORT", hz])],
             "preference": ["edge"], "resources": {"cpu": "100m", "memory": "128Mi"},
             "topics": _topic("publishes", "best_effort", 5)}
            for version, hz in (("0.1.0", "10"), ("0.2.0", "1"))
        ]}],
    }  # fmt: skip
    (tmp_path / "catalog").mkdir()
    (tmp_path / "catalog" / "talker.yml").write_text(yaml.safe_dump(catalog), encoding="utf-8")
    namespace = fleet_namespace(deployed)
    listener = {"name": "listener", "image": image, "preference": ["cloud", "edge"],
                "resources": {"cpu": "100m", "memory": "128Mi"},
                "launch": [shlex.join(["python3", "-c", LISTENER, "listener", "BEST_EFFORT"])],
                "topics": _topic("subscribes", "best_effort")}  # fmt: skip

    def spec(name, modules, file=""):
        path = tmp_path / f"{file or name}.yml"
        document = {"apiVersion": "kuberos.io/v1alpha1", "kind": "RosDeployment",
                    "metadata": {"name": name, "targetFleet": "test-fleet"}, "rosModules": modules}  # fmt: skip
        path.write_text(yaml.safe_dump(document, width=1000), encoding="utf-8")
        return str(path)

    check = ("-e", "rosdeployment_graph_check=true", "-e", f"kuberos_catalog={tmp_path / 'catalog'}")
    talker = {"name": "talker", "module": "graph-talker@^0.1"}
    good = spec("graph-check", [talker, listener])
    slow = spec("graph-check", [{**talker, "module": "graph-talker@0.2.0"}, listener], file="graph-check-0.2")

    def launched():
        pods = real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/deployment=graph-check").items
        return sorted(shlex.join(p.spec.containers[0].args[-3:]) for p in pods if p.metadata.deletion_timestamp is None)

    try:
        started = time.monotonic()
        done = real.deploy(good, tmp_path / "render", *check)
        assert done.returncode == 0, done.stdout[-6000:]
        assert re.search(r"graph-check: 1 topic\(s\) on 1 robot\(s\) as declared, in [0-9.]+ s", done.stdout), done.stdout[-3000:]
        print(f"deploy with the live graph check: {time.monotonic() - started:.1f} s")
        assert not real.core.list_namespaced_pod(namespace, label_selector="kuberos.io/graph-check").items, "check pods go"

        # The controller keeps the dashboard's ROS graph current: its next check rewrites the graph ConfigMap.
        def graph():
            found = real.core.read_namespaced_config_map("kuberos-graph-graph-check", namespace)
            return json.loads(found.data["graph.json"])["robots"]["robot-1"]

        first = graph()
        assert first["ok"] and [t["name"] for t in first["topics"]] == ["/robot_1/chatter"], first
        assert first["topics"][0]["publishers"] == ["/robot_1/talker"] and first["topics"][0]["rate"] > 5, first
        state = str(tmp_path / "controller-graph")
        extra = {"controller_kubeconfig": real.kubeconfig, "controller_state_dir": state, "controller_graph_every": 2,
                 "controller_replicas": 1, "controller_graph_image": image}  # fmt: skip
        assert real.play("controller.yml", "-e", json.dumps(extra)).returncode == 0
        try:
            wait_for(lambda: graph()["at"] != first["at"], 120, "the controller's graph check")
            assert graph()["ok"], graph()
        finally:
            extra["controller_state"] = "stopped"
            real.play("controller.yml", "-e", json.dumps(extra))
        # What the listener printed, read back as a developer does, without kubectl.
        heard = real.play("logs.yml", "-e", "deployment=graph-check", "-e", "module=listener", "-e", "robot=robot-1")
        assert heard.returncode == 0, heard.stdout[-3000:]
        assert "robot-1/listener: pod graph-check-listener-robot-1-" in heard.stdout, heard.stdout[-3000:]
        assert "listening" in heard.stdout and "heard chat" in heard.stdout, heard.stdout[-3000:]
        before = launched()
        rolled = real.play("rollout.yml", "-e", f"rosdeployment_file={slow}", "-e", "rosdeployment_rollout_soak=2", *check)
        assert rolled.returncode != 0, rolled.stdout[-3000:]
        out = rolled.stdout
        assert "stopped at the canary" in out and "the ROS graph does not connect as declared" in out, out[-4000:]
        assert re.search(r"/robot_1/chatter: [0-9.]+ Hz over 3 s, outside at least 5 Hz \(declared by talker\)", out), out[-4000:]
        assert "rolled back robots robot-1" in out, out[-4000:]
        wait_for(lambda: launched() == before, 120, "the talker back at 10 Hz")

        liar = dict(talker, module="graph-talker@^0.1", topics=_topic("publishes", "reliable"))
        honest_listener = dict(listener, topics=_topic("subscribes", "reliable"),
                               launch=[shlex.join(["python3", "-c", LISTENER, "listener", "RELIABLE"])])  # fmt: skip
        lying = spec("graph-lie", [liar, honest_listener])
        failed = real.deploy(lying, tmp_path / "render-lie", *check)
        assert failed.returncode != 0, failed.stdout[-3000:]
        caught = (
            "the ROS graph does not connect as declared: graph-lie: /robot_1/chatter: /robot_1/listener and "
            "/robot_1/talker never match: a reliable subscription gets nothing from a best_effort publisher"
        )
        assert caught in failed.stdout, failed.stdout[-4000:]
    finally:
        for path in (good, str(tmp_path / "graph-lie.yml")):
            if os.path.exists(path):
                undo = real.undeploy(path, *check)
                assert undo.returncode == 0, undo.stdout[-3000:]


def test_rclpy_modules_without_resources_run_a_1khz_load_under_the_defaults_without_oom(real, deployed, tmp_path):
    """Two modules with the default requests and memory limit (spec.DEFAULT_CPU, DEFAULT_MEMORY): a publisher at
    1 kHz and a subscriber, 20 s; neither restarts nor is OOM-killed, and their memory peaks are printed."""
    spec = {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosDeployment",
        "metadata": {"name": "load", "targetFleet": "test-fleet"},
        "rosModules": [
            {"name": name, "image": ROS_IMAGE, "launch": [shlex.join(["python3", "-c", LOAD, role, "1000"])],
             "preference": ["cloud", "edge"]}
            for name, role in (("load-pub", "pub"), ("load-sub", "sub"))
        ],
    }  # fmt: skip
    path = tmp_path / "load.yml"
    path.write_text(yaml.safe_dump(spec), encoding="utf-8")
    namespace = fleet_namespace(deployed)
    try:
        result = real.deploy(str(path), tmp_path / "render")
        assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
        pods = {p.metadata.labels["kuberos.io/module"]: p for p in real.core.list_namespaced_pod(
            namespace, label_selector="kuberos.io/deployment=load").items}  # fmt: skip
        limits = {m: p.spec.containers[0].resources.limits["memory"] for m, p in pods.items()}
        assert limits == {"load-pub": "128Mi", "load-sub": "128Mi"}, limits
        time.sleep(20)  # four of the subscriber's 5 s reports; the memory peak is reached within seconds
        counts = [int(line.split()[1]) for line in logs(real.core, namespace, pods["load-sub"].metadata.name).splitlines()
                  if line.startswith("received")]  # fmt: skip
        assert len(counts) >= 2 and counts[-1] > counts[-2], counts
        rate = (counts[-1] - counts[-2]) / 5.0
        for module, pod in pods.items():
            live = real.core.read_namespaced_pod(pod.metadata.name, namespace)
            (status,) = live.status.container_statuses
            assert status.restart_count == 0 and status.state.running, (module, status)
            assert not (status.last_state.terminated and status.last_state.terminated.reason == "OOMKilled"), module
            print(f"{module} on {live.spec.node_name}: memory peak {memory_peak(real, live) / 2**20:.1f} MiB (limit 128Mi)")
        print(f"load-sub received {rate:.0f} messages/s of the 1 kHz publisher")
    finally:
        undo = real.play("undeploy.yml", "-e", f"rosdeployment_file={path}")
        assert undo.returncode == 0, undo.stdout[-3000:]


# -- the controller as pods ----------------------------------------------------------------------------------------

IN_NODE = """
import http.client, json, socket, ssl, sys
address, name, ca, token = sys.argv[1:5]
context = ssl.create_default_context(cafile=ca)


class ToService(http.client.HTTPSConnection):
    # TCP to the Service's address, TLS checked against the Service's DNS name (as a client resolving it would)
    def connect(self):
        self.sock = context.wrap_socket(socket.create_connection((address, 8611), timeout=10), server_hostname=name)


answers = {}
for path, bearer in (("/metrics", token), ("/metrics", ""), ("/healthz", "")):
    connection = ToService(name, 8611, context=context, timeout=10)
    connection.request("GET", path, headers={"Authorization": "Bearer " + bearer} if bearer else {})
    response = connection.getresponse()
    answers[f"{path} {bool(bearer)}"] = [response.status, response.read().decode()[:20000]]
    connection.close()
print(json.dumps(answers))
"""


# Polls the dashboard's last lines of an instance that prints "tick <epoch>" every 0.25 s, from a node (the same
# kernel's clock as the pods'): for each line that appears after the first answer, when it appeared minus when printed.
IN_NODE_LOGS = """
import http.client, json, socket, ssl, sys, time
address, name, ca, token, instance = sys.argv[1:6]
context = ssl.create_default_context(cafile=ca)


def ask(bearer):
    connection = http.client.HTTPSConnection(name, 8611, context=context, timeout=10)
    connection.sock = context.wrap_socket(socket.create_connection((address, 8611), timeout=10), server_hostname=name)
    connection.request("GET", "/api/logs?lines=20&instance=" + instance, headers={"Authorization": "Bearer " + bearer})
    response = connection.getresponse()
    body = response.read()
    connection.close()
    return response.status, body


refused = ask("")[0]
first, delays, answers = None, [], 0
end = time.monotonic() + 20
while time.monotonic() < end:
    status, body = ask(token)
    now = time.time()
    if status == 200:
        answers += 1
        ticks = [line for line in json.loads(body).get("lines", []) if line.startswith("tick ")]
        if first is None:
            first = set(ticks)
        for line in ticks:
            if line not in first:
                first.add(line)
                delays.append(round(now - float(line.split()[1]), 3))
    time.sleep(0.1)
print(json.dumps({"refused": refused, "answers": answers, "delays": delays}))
"""
TICKER = "import time\nwhile True:\n    print('tick', repr(time.time()), flush=True)\n    time.sleep(0.25)"


def test_the_controller_runs_as_pods_on_the_edge_servers_behind_tls_and_tokens_and_a_killed_leader_hands_over(
    real, deployed, tmp_path
):
    """controller.yml in-cluster: two replicas from the collection's image on edge-1 and edge-2 (reaching the API
    server through the `kubernetes` Service), one holding the Lease; the dashboard's /metrics through the Service
    over TLS answers a token the API server vouches for and refuses none; the leader's pod killed, the other takes
    the Lease within the lease duration and a bit."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

    name = "kuberos-controller.kuberos-system.svc"
    ca_cert, ca_key = pki.new_ca("dashboard test CA", days=1)
    cert, key = pki.issue(ca_cert, ca_key, name, usage=pki.SERVER, days=1, alt_names=[name, f"{name}.cluster.local"])
    for path, obj in (("ca.crt", ca_cert), ("tls.crt", cert), ("tls.key", key)):
        pki.write_pem(str(tmp_path / path), obj)
    try:
        real.core.create_namespace({"metadata": {"name": "kuberos-system"}})
    except Exception:
        pass
    real.core.create_namespaced_secret(
        "kuberos-system",
        {
            "metadata": {"name": "kuberos-dashboard-tls"},
            "type": "kubernetes.io/tls",
            "stringData": {f: (tmp_path / f).read_text() for f in ("tls.crt", "tls.key", "ca.crt")},
        },
    )
    extra = {
        "controller_mode": "in_cluster", "controller_kubeconfig": real.kubeconfig, "controller_fleets": ["test-fleet"],
        "controller_dashboard_tls_secret": "kuberos-dashboard-tls", "controller_grace": GRACE,
    }  # fmt: skip
    result = real.play("controller.yml", "-e", json.dumps(extra))
    assert result.returncode == 0, result.stdout[-6000:]
    try:
        pods = wait_for(
            lambda: (lambda found: found if len(found) == 2 else None)(controller_pods(real.core)), 180, "two pods Ready"
        )
        assert sorted(pods.values()) == ["edge-1", "edge-2"], pods
        leader = wait_for(
            lambda: lease_holder(real.core) if lease_holder(real.core) in pods else None, 60, "a replica holding the Lease"
        )

        from kubernetes import client

        token = real.core.create_namespaced_service_account_token(
            "kuberos-dashboard-viewer", "kuberos-system", client.AuthenticationV1TokenRequest(spec={"expirationSeconds": 600})
        ).status.token
        address = real.core.read_namespaced_service("kuberos-controller", "kuberos-system").spec.cluster_ip
        netns = RealNodes.from_state(real.plane(), {}).nets["edge-1"].netns
        command = ["ip", "netns", "exec", netns, sys.executable, "-c", IN_NODE, address, name, str(tmp_path / "ca.crt"), token]
        deadline = time.monotonic() + 30  # edge-1's kube-proxy learns the Ready pods' endpoints a moment after they are
        while True:
            done = subprocess.run(command, capture_output=True, text=True, timeout=60)
            if done.returncode == 0 or "Connection refused" not in done.stderr or time.monotonic() > deadline:
                break
            time.sleep(1)
        assert done.returncode == 0, done.stderr[-3000:]
        answers = json.loads(done.stdout)
        assert answers["/metrics True"][0] == 200 and "kuberos_" in answers["/metrics True"][1], answers["/metrics True"][1][:500]
        assert answers["/metrics False"][0] == 401, "no token, no metrics"
        assert answers["/healthz False"][0] == 200

        # The dashboard's last lines of a module, live, behind the same tokens: the time from a line printed in a pod
        # to the dashboard's answer (polled every 0.1 s; the page asks every 2 s while its log panel is open).
        ticker = tmp_path / "ticker.yml"
        module = {"name": "ticker", "image": ROS_IMAGE, "launch": [shlex.join(["python3", "-c", TICKER])],
                  "preference": ["edge"], "resources": {"cpu": "50m", "memory": "64Mi"}}  # fmt: skip
        metadata = {"name": "ticker", "targetFleet": "test-fleet"}
        document = {"apiVersion": "kuberos.io/v1alpha1", "kind": "RosDeployment", "metadata": metadata, "rosModules": [module]}
        ticker.write_text(yaml.safe_dump(document), encoding="utf-8")
        assert real.deploy(str(ticker), tmp_path / "render-ticker").returncode == 0
        try:
            command = ["ip", "netns", "exec", netns, sys.executable, "-c", IN_NODE_LOGS, address, name, str(tmp_path / "ca.crt"),
                       token, "ticker-ticker-robot-1"]  # fmt: skip
            polled = json.loads(subprocess.run(command, capture_output=True, text=True, timeout=120, check=True).stdout)
            assert polled["refused"] == 401, "no token, no logs"
            assert len(polled["delays"]) >= 20, polled
            delays = sorted(polled["delays"])
            p95 = delays[int(0.95 * (len(delays) - 1))]
            print(f"dashboard logs: {len(delays)} lines, printed -> answered median {statistics.median(delays):.2f} s, "
                  f"p95 {p95:.2f} s, max {delays[-1]:.2f} s over {polled['answers']} answers")  # fmt: skip
        finally:
            real.undeploy(str(ticker))

        # A Prometheus in the cluster (Debian's, no Operator) scrapes both replicas, found by DNS through the headless
        # Service, over TLS with its own ServiceAccount's token: the scrape job the ServiceMonitor stands for.
        prometheus = prometheus_objects("kuberos-system", "kuberos-dashboard-tls")
        apply_objects(real.core.api_client, prometheus)
        try:
            ready = lambda: (lambda p: p.status.pod_ip if pod_ready(p) else None)(  # noqa: E731
                real.core.read_namespaced_pod(PROMETHEUS, "kuberos-system")
            )
            address = wait_for(ready, 180, "Prometheus Ready")
            up = 'up{job="kuberos-controller"}'
            scraped = lambda: (lambda d: d["result"] if d and len(d["result"]) == 2 else None)(  # noqa: E731
                prometheus_api(address, "query", query=up)
            )
            targets = wait_for(scraped, 90, "both replicas scraped", 2)
            addresses = {real.core.read_namespaced_pod(p, "kuberos-system").status.pod_ip for p in pods}
            assert {s["metric"]["instance"].rsplit(":", 1)[0] for s in targets} == addresses, targets
            assert all(s["value"][1] == "1" for s in targets), targets
            nodes = prometheus_api(address, "query", query="max by (node) (kuberos_node_ready)")["result"]
            assert {s["metric"]["node"] for s in nodes} == set(NODES), nodes
            groups = {g["name"] for g in prometheus_api(address, "rules")["groups"]}
            assert {"kuberos.recording", "kuberos.alerts"} <= groups, groups
            print(f"Prometheus in the cluster: both replicas up over TLS, {len(nodes)} nodes' kuberos_node_ready, rules {groups}")
        finally:
            apply_objects(real.core.api_client, prometheus, delete=True)

        killed = time.monotonic()
        # Deleted as a drain or an eviction deletes it (SIGTERM, the Lease given up). A forced deletion (grace 0) only
        # removes the object, without waiting for the process to end. The other replica takes the free Lease, or the
        # Deployment's replacement does when it starts before the other's next try (bench/RESULTS.md).
        real.core.delete_namespaced_pod(leader, "kuberos-system")
        taken = lambda: (lambda h: h if h and h != leader else None)(lease_holder(real.core))  # noqa: E731
        holder = wait_for(taken, 30, f"another replica to take the Lease from {leader}", interval=0.1)
        takeover = time.monotonic() - killed
        print(f"in-cluster controller: leader {leader} deleted, {holder} took the Lease in {takeover:.1f} s")
        assert takeover < 10
        wait_for(lambda: len(controller_pods(real.core)) == 2, 180, "the Deployment's replacement replica Ready")
    finally:
        extra["controller_state"] = "stopped"
        real.play("controller.yml", "-e", json.dumps(extra))
        real.core.delete_namespaced_secret("kuberos-dashboard-tls", "kuberos-system")


PARTNER_PORTS = {
    "apiserver": 29443,
    "etcd_client": 29379,
    "etcd_peer": 29380,
    "controller_manager": 29257,
    "scheduler": 29259,
    "kwok": 29247,
}
PARTNER_BASE, PARTNER_TAG = 245, "kq"  # the partner's real nodes: addresses 10.245-247.x, names kq...


@pytest.mark.full  # make test: the bridge between real processes (tests/integration/test_bridge.py), a partner cluster on kwok
def test_the_bridge_runs_as_pods_between_this_cluster_and_a_partner_cluster_of_real_nodes(real, deployed, tmp_path_factory):
    """A second cluster of real nodes (partner-1, its own control plane, addresses and ports) registered as the
    third-party cluster ``partner-real``; a module placed there answers robot-1's pings across the bridge: the
    bridge server as a pod at this cluster's edge, the client, a discovery server and the module as pods in the
    partner cluster, the client reaching the server's NodePort on an edge node's address. Round trips are measured
    to an echo on edge-1 (direct) and then through the bridge; undeploy leaves nothing in the partner cluster."""
    folder = tmp_path_factory.mktemp("pr")  # short: containerd's socket path under it must stay within 104 characters
    seen = bridge_round_trips(real, deployed, folder, PARTNER_PORTS, PARTNER_BASE, PARTNER_TAG)
    direct, through = statistics.median(seen["direct_ms"]), statistics.median(seen["through_ms"])
    print(
        f"robot-1 <-> echo: direct (edge-1) p50 {direct:.1f} ms; through the bridge pods (server on "
        f"{seen['server_nodes']}, client and echo on partner-1) p50 {through:.1f} ms: {through - direct:.1f} ms added; "
        f"through the bridge {min(seen['through_ms']):.1f} to {max(seen['through_ms']):.1f} ms"
    )
    assert not seen["token_printed"], "the partner's token is never printed"
    assert len(seen["server_nodes"]) == 1 and seen["server_nodes"][0] in {"edge-1", "edge-2"}, seen
    remote = seen["partner_pods"]
    assert {"kuberos-bridge-client", "kuberos-discovery-0", "bridge-echo-echo-robot-1"} <= set(remote), remote
    assert set(remote.values()) == {"partner-1"}, remote
    assert len(seen["through_ms"]) >= 20 and seen["partner_left"] == [], seen


TRIAL = (  # a run's program: says its mode, leaves a termination message, then exits 0, exits 3 or hangs
    "import sys, time; mode = sys.argv[1].split(':=')[1]; print('trial', mode, flush=True); "
    "open('/dev/termination-log', 'w').write('result ' + mode); "
    "time.sleep(120) if mode == 'hang' else sys.exit(3 if mode == 'fail' else 0)"
)
BATCH = {
    "kind": "RosBatchJob",
    "metadata": {"name": "real-batch", "targetFleet": "test-fleet"},
    "job": {"module": "trial", "runningTimeout": "20 s", "grid": [{"map": "p", "key": "mode", "values": ["ok", "fail", "hang"]}]},
    "parameterMaps": [{"name": "p", "type": "key-value", "data": {"mode": "ok"}}],
    "rosModules": [
        {
            "name": "trial",
            "image": ROS_IMAGE,
            "launch": shlex.join(["python3", "-c", TRIAL]),
            "launchArguments": {"mode": "{p.mode}"},
            "preference": ["edge", "cloud"],
        }
    ],
}


def test_a_batch_job_runs_its_programs_on_real_nodes_and_collects_what_they_said(real, tmp_path):
    """Three runs of a real program, as Jobs on the real kubelets: one exits 0, one exits 3, one hangs past its
    running timeout (activeDeadlineSeconds); each run's log and termination message come back in the results."""
    spec = tmp_path / "real-batch.yml"
    spec.write_text(yaml.safe_dump(BATCH), encoding="utf-8")
    out = tmp_path / "batch"
    result = real.play("batch.yml", "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={out}")
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
    runs = {r["parameters"]["p.mode"]: r for r in json.loads((out / "results.json").read_text())}
    print({mode: (r["state"], r["why"], r["node"]) for mode, r in runs.items()})
    assert runs["ok"]["state"] == "succeeded" and runs["ok"]["message"] == "result ok"
    assert runs["fail"]["state"] == "failed" and runs["fail"]["why"] == "trial exited 3 (Error)"
    assert runs["fail"]["message"] == "result fail"
    assert runs["hang"]["state"] == "failed" and runs["hang"]["why"] == "running timeout"
    for number, mode in enumerate(("ok", "fail", "hang")):
        assert (out / "runs" / f"{number}-0" / "trial.log").read_text().startswith(f"trial {mode}")
        assert runs[mode]["node"] in ("edge-1", "edge-2", "cloud-1")
    real.play(
        "batch.yml",
        "-e",
        f"rosdeployment_file={spec}",
        "-e",
        f"kuberos_render_dir={out}",
        "-e",
        "rosdeployment_batch_state=absent",
    )


def test_a_robot_cut_off_longer_than_the_eviction_delay_keeps_its_pods_and_nothing_moves(real, deployed, lab, tmp_path_factory):
    """robot-1 loses its network (every packet of its control link and its link to the other nodes dropped) for
    longer than the API server's default toleration of an unreachable node (shortened to UNREACHABLE_S here): a pod
    without the platform's tolerations (the negative control) is evicted, the onboard modules are not, the controller
    moves nothing and says "robot offline"; once reconnected, the same pods run on with the same restart counts and
    every module runs where it was placed (docs/connectivity.md)."""
    namespace = fleet_namespace(deployed)
    state = str(tmp_path_factory.mktemp("controller-offline"))
    extra = {"controller_kubeconfig": real.kubeconfig, "controller_state_dir": state, "controller_grace": GRACE}
    assert real.play("controller.yml", "-e", json.dumps(extra)).returncode == 0
    status = f"kuberos-status-{deployed['deployments'][0]['name']}"
    # a rollout while robot-1 is away: the controller's environment changes (an onboard module of robot-1's)
    text = open(SPEC, encoding="utf-8").read().replace(
        "    devices: [gripper]\n  resources: {cpu: 500m, memory: 512Mi}\n",
        "    devices: [gripper]\n  resources: {cpu: 500m, memory: 512Mi}\n  env: {ROLLOUT_TRY: '2'}\n", 1,
    )  # fmt: skip
    changed = tmp_path_factory.mktemp("offline-rollout") / "pick-and-place.yml"
    changed.write_text(text, encoding="utf-8")
    assert "ROLLOUT_TRY" in text

    def rollout():
        return real.play("rollout.yml", "-e", f"rosdeployment_file={changed}", "-e", "rosdeployment_rollout_soak=2")

    try:
        seen = cut_off_robot(
            real, namespace, placed_instances(deployed), "robot-1", lab, status, GRACE + 8, UNREACHABLE_S, PAIR_S,
            during=rollout,
        )  # fmt: skip
    finally:
        extra["controller_state"] = "stopped"
        real.play("controller.yml", "-e", json.dumps(extra))
    before = seen["before"]
    assert before and seen["cut"] and seen["reconnected"], seen
    assert not any(deleting for _uid, _restarts, deleting in before.values()), before
    assert seen["during"] == before, "an onboard pod was evicted, deleted or restarted while its robot was offline"
    assert seen["after"] == before, "the same pods, the same restart counts after the robot is back"
    placed = placed_instances(deployed)
    assert {i: seen["running_after"][i] for i in placed} == placed, "every module runs where it was placed"
    assert all(r["note"].startswith("robot offline since") for r in seen["offline_rows"]), seen["offline_rows"]
    said = seen["robot_offline_events"]
    assert said and all("robot robot-1 is offline" in message for message in said), said
    assert seen["moves_after"] == [], "nothing moved"
    assert seen["control_gone"]
    away = seen["during_result"]
    assert away.returncode == 0, away.stdout[-4000:]
    assert "pending, offline (the next rollout run finishes them): robot-1" in away.stdout, away.stdout[-3000:]
    finished = real.play("rollout.yml", "-e", f"rosdeployment_file={changed}", "-e", "rosdeployment_rollout_soak=2")
    assert finished.returncode == 0 and "robot-1: " in finished.stdout, finished.stdout[-3000:]
    controller = next(
        d for d in real.apps.list_namespaced_deployment(namespace, label_selector="kuberos.io/module=controller").items
    )  # fmt: skip
    assert any(e.name == "ROLLOUT_TRY" for e in controller.spec.template.spec.containers[0].env or []), "robot-1 finished"
    own, fleet_only = seen["pair_with_own_server"], seen["pair_fleet_only"]
    # the kubelet expanded the rendered list: three cluster IPs, the robot's own server last; the control lacks it
    assert own["servers"] and len(own["servers"].split(";")) == 3, own
    assert fleet_only["servers"] == own["servers"].rsplit(";", 1)[0], (own, fleet_only)
    assert own["first_s"] is not None, f"a pair started on the cut-off robot did not meet through its own server: {own}"
    assert fleet_only["first_s"] is None, f"the pair without the robot's server met with the edge unreachable: {fleet_only}"
    print(
        f"robot-1 cut off {seen['partition_s']:.0f} s: tainted unreachable after {seen['tainted_after_s']:.0f} s, the "
        f"negative control evicted after {seen['control_evicted_after_s']:.0f} s, {len(before)} onboard pods untouched; "
        f"reconnected: Ready after {seen['ready_after_reconnect_s']:.1f} s, every module Running and Ready where placed "
        f"after {seen['rematch_after_reconnect_s']:.1f} s; a pair started during the cut met through the robot's own "
        f"server after {own['first_s']:.1f} s, the pair without it not in {PAIR_S:.0f} s"
    )


def test_a_stopped_kubelet_makes_the_controller_move_its_modules_and_they_run_again(real, deployed, tmp_path_factory):
    namespace = fleet_namespace(deployed)
    state = str(tmp_path_factory.mktemp("controller-real"))
    extra = {"controller_kubeconfig": real.kubeconfig, "controller_state_dir": state, "controller_grace": GRACE}
    assert real.play("controller.yml", "-e", json.dumps(extra)).returncode == 0
    try:
        before = running_instances(real.core, namespace)
        victim = "edge-2"
        moved = sorted(name for name, node in before.items() if node == victim)
        assert moved, f"nothing runs on {victim}: {before}"
        nodes = RealNodes.from_state(real.plane(), {})
        # The controller's probe counts a node down only once its kubelet has answered it (a kubelet silent from
        # the start is left to Kubernetes): let it probe a few rounds first.
        time.sleep(3)
        assert nodes.stop_kubelet(victim)
        started = time.monotonic()

        def moved_and_running():
            now = running_instances(real.core, namespace)
            return all(now.get(name) not in (None, victim) for name in moved) and now

        after = wait_for(moved_and_running, 240, f"{moved} Running off {victim}", 0.5)
        took = time.monotonic() - started
        print(f"{victim} kubelet stopped: {moved} Running on {[after[m] for m in moved]} after {took:.1f} s")
        why = [message for _name, message in events_of(real.core, namespace, "ModuleMoved").values() if victim in message]
        assert any("has not answered the controller's probes" in message for message in why), why
        assert took < 30, "the controller's own probe, not Kubernetes' 40 s node grace period, saw the node down"
        assert {name: node for name, node in after.items() if name not in moved} == {
            name: node for name, node in before.items() if name not in moved
        }, "only the stopped node's modules moved"
    finally:
        extra["controller_state"] = "stopped"
        real.play("controller.yml", "-e", json.dumps(extra))


def test_teardown_leaves_the_host_as_it_was(real):
    result = real.stop(state="absent")
    assert result.returncode == 0, result.stdout[-6000:]
    again = real.stop(state="absent")
    assert again.returncode == 0 and again.changed == 0, again.stdout[-6000:]
    after = snapshot_host()
    differences = snapshot_changes(real.before, after)
    assert not differences, json.dumps(differences, indent=1)[:6000]
    assert not os.path.exists(real.state_dir)
