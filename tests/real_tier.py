"""The local cluster's real-node tier driven as a user drives it (docs/real-nodes.md), for the tests and the benchmarks.

``RealCluster`` starts and stops a cluster of real nodes with playbooks/local_cluster.yml on ports, addresses and a
state directory of its own; ``program_pod`` runs one of the test's ROS programs (tests/integration/ros, given to the
pod as a ConfigMap) on a node; ``bridge_echo_spec`` is a module in a partner cluster that answers pings across the
KubeROS-Bridge; ``round_trips`` reads what a ping pod measured.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import time
from pathlib import Path

import yaml
from helpers import ROOT, Cluster, playbook

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security

INVENTORY = "inventories/real-pods"
ROS_IMAGE = "ghcr.io/kuberos/pnp-planner:0.1"  # any name of the collection's ROS image
PROGRAMS = os.path.join(ROOT, "tests", "integration", "ros")
PROGRAM_FILES = ("talker.py", "listener.py", "node_runner.py", "ros_ping.py")
FLEET = "test-fleet"


class RealCluster(Cluster):
    """A cluster of real nodes (``inventory``: hosts marked ``kuberos_local_node: real``) on addresses 10.<base>..+2."""

    def __init__(self, state_dir, ports: dict, base: int, tag: str, inventory: str = INVENTORY, **variables):
        super().__init__(state_dir, ports)
        self.ports, self.base, self.tag, self.inventory = ports, base, tag, str(inventory)
        extra = {"local_cluster_real_nodes_base": base, "local_cluster_real_nodes_tag": tag, **variables}
        self.vars += ["-e", json.dumps({**extra, "kuberos_kubeconfig": self.kubeconfig})]

    def start(self):
        return playbook("local_cluster.yml", *self.vars, inventory=self.inventory, timeout=2400)

    def stop(self, state="stopped"):
        return playbook("local_cluster.yml", *self.vars, "-e", f"local_cluster_state={state}", inventory=self.inventory)

    def deploy(self, spec, render_dir, *extra):
        render = ["-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={render_dir}"]
        return self.play("deploy.yml", *render, *extra)

    def undeploy(self, spec, *extra):
        return self.play("undeploy.yml", "-e", f"rosdeployment_file={spec}", *extra)

    def play(self, name, *extra, timeout=900):
        return playbook(name, *self.vars, *extra, inventory=self.inventory, timeout=timeout)

    def connect(self):
        """Kubernetes clients as attributes (``core``, ``apps``), once the cluster runs."""
        self.core, self.apps, _ = self.clients()
        return self

    def plane(self):
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_control_plane import (
            LocalControlPlane,
            Ports,
        )

        return LocalControlPlane(self.state_dir, {}, Ports(**self.ports))

    def nets(self) -> dict:
        """Node name -> its NodeNet (network namespace, addresses), as the running tier's state says."""
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import RealNodes

        return RealNodes.from_state(self.plane(), {}).nets


def write_inventory(folder, hosts: dict, group: str = "cloud") -> str:
    """A real-node inventory of its own (a partner's cluster): ``hosts`` (name -> host vars) in ``group``."""
    host_vars = {"kuberos_cpu": 2, "kuberos_memory": "8Gi", "kuberos_local_node": "real", "ansible_connection": "local"}
    host_vars["ansible_python_interpreter"] = "{{ ansible_playbook_python }}"
    inventory = {"all": {"vars": host_vars, "children": {group: {"hosts": hosts}}}}
    path = os.path.join(str(folder), "hosts.yml")
    with open(path, "w", encoding="utf-8") as handle:
        yaml.safe_dump(inventory, handle)
    return path


def wait_for(check, timeout, what, interval=1.0):
    deadline = time.monotonic() + timeout
    value = None
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {value!r})")


def logs(core, namespace, pod):
    """The pod's log so far ("" before it has any: the client gives None for an empty body)."""
    try:
        return core.read_namespaced_pod_log(pod, namespace) or ""
    except Exception:
        return ""


def programs_configmap(core, namespace):
    """The test's ROS programs as the ConfigMap ``programs`` that ``program_pod`` mounts."""
    data = {}
    for name in PROGRAM_FILES:
        with open(os.path.join(PROGRAMS, name), encoding="utf-8") as handle:
            data[name] = handle.read()
    core.create_namespaced_config_map(namespace, {"metadata": {"name": "programs"}, "data": data})


def program_pod(name, node, namespace, args, env, robot=None):
    tolerations = [{"key": "kuberos.io/robot", "operator": "Exists", "effect": "NoSchedule"}] if robot else []
    env = {"ROS_HOME": pod_security.ROS_HOME, **env}  # not root, as every pod of a fleet's namespace (restricted)
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {"name": name, "namespace": namespace, "labels": {"test": name}},
        "spec": {
            "nodeSelector": {"kubernetes.io/hostname": node},
            "tolerations": tolerations,
            "terminationGracePeriodSeconds": 1,
            "containers": [
                {
                    "name": "main",
                    "image": ROS_IMAGE,
                    "imagePullPolicy": "IfNotPresent",
                    "args": ["python3", *args],
                    "env": [{"name": k, "value": v} for k, v in env.items()],
                    "volumeMounts": [{"name": "programs", "mountPath": "/programs"}],
                    "securityContext": pod_security.container_security_context(),
                }
            ],
            "volumes": [{"name": "programs", "configMap": {"name": "programs"}}],
            "securityContext": pod_security.pod_security_context(),
        },
    }


# A module that answers pings: what it hears on /<robot>/kuberos_ping it says again on /<robot>/kuberos_pong.
ECHO = (
    "import os, rclpy; from std_msgs.msg import String; rclpy.init(); node = rclpy.create_node('kuberos_echo'); "
    "robot = os.environ['KUBEROS_ROBOT_NAME'].replace('-', '_'); "
    "pong = node.create_publisher(String, f'/{robot}/kuberos_pong', 10); "
    "node.create_subscription(String, f'/{robot}/kuberos_ping', pong.publish, 10); print('echo ready', flush=True); "
    "rclpy.spin(node)"
)


def bridge_echo_spec(cluster: str, fleet: str = FLEET) -> dict:
    """A RosDeployment whose one module runs in the third-party cluster ``cluster`` and answers pings of each robot
    across the bridge (ping to the module, pong back)."""
    topic = {"type": "std_msgs/msg/String"}
    return {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosDeployment",
        "metadata": {"name": "bridge-echo", "targetFleet": fleet},
        "rosModules": [
            {
                "name": "echo",
                "image": ROS_IMAGE,
                "launch": shlex.join(["python3", "-c", ECHO]),
                "cluster": cluster,
                "resources": {"cpu": "100m", "memory": "256Mi"},
                "bridge": {
                    "topics": [
                        {"name": "/{robot}/kuberos_ping", **topic, "direction": "to_module"},
                        {"name": "/{robot}/kuberos_pong", **topic, "direction": "from_module"},
                    ]
                },
            }
        ],
    }


def round_trips(core, namespace, pod) -> list[float]:
    """The round trips (ms) a ``ros_ping.py ping`` pod printed so far."""
    return [float(line.split()[1]) for line in logs(core, namespace, pod).splitlines() if line.startswith("rtt_ms ")]


def wait_for_round_trips(core, namespace, pod, count, timeout=90) -> list[float]:
    return wait_for(
        lambda: (lambda found: found if len(found) >= count else None)(round_trips(core, namespace, pod)),
        timeout,
        f"{count} round trips of {pod}",
    )


# -- the controller as pods -----------------------------------------------------------------------------------------
CONTROLLER_NAMESPACE = "kuberos-system"


def lease_holder(core):
    from kubernetes import client

    coordination = client.CoordinationV1Api(core.api_client)
    try:
        return coordination.read_namespaced_lease("kuberos-controller", CONTROLLER_NAMESPACE).spec.holder_identity
    except Exception:
        return None


def pod_ready(pod) -> bool:
    """Running, not being deleted, every container ready."""
    statuses = pod.status.container_statuses or []
    return pod.status.phase == "Running" and pod.metadata.deletion_timestamp is None and all(s.ready for s in statuses)


def controller_pods(core) -> dict:
    """Pod name -> node of the controller's replicas that are Running and Ready."""
    pods = core.list_namespaced_pod(CONTROLLER_NAMESPACE, label_selector="app.kubernetes.io/name=kuberos-controller").items
    return {p.metadata.name: p.spec.node_name for p in pods if pod_ready(p)}


def first_pass_as_leader(core, pod: str, after: float) -> float | None:
    """The epoch at which ``pod`` logged its first completed pass as leader, if that came after ``after``."""
    for line in logs(core, CONTROLLER_NAMESPACE, pod).splitlines():
        if "first pass as leader completed at " in line:
            at = float(line.split("first pass as leader completed at ")[1].split()[0])
            if at > after:
                return at
    return None


# -- the bridge between this cluster and a partner cluster of real nodes ---------------------------------------------
PARTNER = "partner-real"
TOPICS = ["/robot_1/kuberos_ping", "/robot_1/kuberos_pong"]  # robot-1's, as ROS names them


def fleet_ros_env(real, namespace, deployment) -> dict:
    """The ROS environment a rendered container of ``deployment`` has (discovery servers, RMW, domain)."""
    (container,) = real.apps.read_namespaced_deployment(deployment, namespace).spec.template.spec.containers
    return {e.name: e.value for e in container.env if e.value is not None and e.name.startswith(("ROS_", "RMW_"))}


def _ping_samples(real, namespace, name, env, samples, warmup=50) -> list[float]:
    """``samples`` round trips of a new ping pod on robot-1 after ``warmup`` ones (10 s at 5 Hz): the first pings wait
    for matching, and through the bridge for each side's new publisher (up to 3 s each, docs/bridge.md)."""
    ping = program_pod(name, "robot-1", namespace, ["/programs/ros_ping.py", "ping", *TOPICS], env, robot=True)
    real.core.create_namespaced_pod(namespace, ping)
    try:
        return wait_for_round_trips(real.core, namespace, name, warmup + samples, 120 + samples)[warmup:]
    finally:
        real.core.delete_namespaced_pod(name, namespace, grace_period_seconds=0)


def bridge_round_trips(real, placement, folder, ports, base, tag, samples=20) -> dict:
    """Round trips from robot-1 to an echo: direct (a pod on edge-1) and then through the bridge (``bridge_echo_spec``
    deployed with its module in a second cluster of real nodes, ``partner-1``, started here on ``ports``, ``base``
    and ``tag``). Everything is removed again, the partner cluster too. Returns the samples (ms) of both paths and
    what was seen: the server's node, the partner's pods, whether deploy printed the partner's token."""
    from helpers import partner_site

    folder = Path(folder)
    (folder / "inventory").mkdir(parents=True)
    write_inventory(folder / "inventory", {"partner-1": {}})
    partner = RealCluster(folder / "state", ports, base, tag, str(folder / "inventory"), local_cluster_registry_port=0)
    namespace = placement["deployments"][0]["namespace"]
    spec = folder / "bridge-echo.yml"
    spec.write_text(yaml.safe_dump(bridge_echo_spec(PARTNER)))
    server = f"kuberos-bridge-{PARTNER}"
    seen: dict = {}
    extra: tuple = ()
    try:
        started = partner.start()
        assert started.returncode == 0, started.stdout[-8000:] + started.stderr[-3000:]
        partner.connect()
        endpoint = real.nets()["edge-1"].node_ip  # any node's kube-proxy serves the NodePort
        api_server = f"https://127.0.0.1:{ports['apiserver']}"
        ca_cert = os.path.join(partner.state_dir, "pki", "ca.crt")
        site = partner_site(partner.core, folder, PARTNER, api_server, ca_cert, endpoint, latency_ms=10)
        extra = ("-i", site["inventory"], "--vault-password-file", site["password"])

        perception = next(i["name"] for i in placement["instances"] if i["module"] == "perception")
        env = fleet_ros_env(real, namespace, perception)
        programs_configmap(real.core, namespace)
        echo = program_pod("direct-echo", "edge-1", namespace, ["/programs/ros_ping.py", "echo", *TOPICS], env)
        real.core.create_namespaced_pod(namespace, echo)
        seen["direct_ms"] = _ping_samples(real, namespace, "direct-ping", env, samples)
        real.core.delete_namespaced_pod("direct-echo", namespace, grace_period_seconds=0)
        wait_for(lambda: not _exists(real.core, namespace, "direct-echo"), 60, "the direct echo gone")

        deployed = real.deploy(str(spec), folder / "render", *extra)
        assert deployed.returncode == 0, deployed.stdout[-8000:]
        seen["token_printed"] = site["token"] in deployed.stdout + deployed.stderr
        seen["server_nodes"] = [
            p.spec.node_name
            for p in real.core.list_namespaced_pod(namespace, label_selector=f"kuberos.io/instance={server}").items
        ]
        seen["partner_pods"] = {
            p.metadata.name.rsplit("-", 2)[0]: p.spec.node_name for p in partner.core.list_namespaced_pod(namespace).items
        }
        client = next(p for p in partner.core.list_namespaced_pod(namespace).items if "bridge-client" in p.metadata.name)
        wait_for(
            lambda: "connected to " in logs(partner.core, namespace, client.metadata.name), 120, "the bridge client connected"
        )
        seen["through_ms"] = _ping_samples(real, namespace, "bridge-ping", env, samples)
    finally:
        for name in ("direct-ping", "direct-echo", "bridge-ping"):
            if _exists(real.core, namespace, name):
                real.core.delete_namespaced_pod(name, namespace, grace_period_seconds=0)
        try:
            real.core.delete_namespaced_config_map("programs", namespace)
        except Exception:
            pass
        if extra:
            removed = real.undeploy(str(spec), *extra)
            assert removed.returncode == 0, removed.stdout[-4000:]
            seen["partner_left"] = [d.metadata.name for d in partner.apps.list_namespaced_deployment(namespace).items]
        stopped = partner.stop(state="absent")
        assert stopped.returncode == 0, stopped.stdout[-4000:]
    return seen


def _exists(core, namespace, pod) -> bool:
    try:
        core.read_namespaced_pod(pod, namespace)
        return True
    except Exception:
        return False


# -- a Prometheus in the cluster (no Operator), scraping the controller -------------------------------------------------
PROMETHEUS_IMAGE = "kuberos.local/prometheus:debian"  # Debian's Prometheus as an image (local_images)
PROMETHEUS = "kuberos-prometheus"


def prometheus_objects(namespace: str, tls_secret: str) -> list[dict]:
    """A plain Prometheus in ``namespace``: its ServiceAccount is bound to ``kuberos-metrics-reader`` (and may
    discover endpoints, for a job by Kubernetes discovery); its configuration is the controller's scrape job
    (``monitoring.scrape_config``, the ServiceMonitor's equivalent) over TLS with ``tls_secret``'s ca.crt, and the
    collection's rule file."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import monitoring

    with open(os.path.join(ROOT, "roles", "controller", "files", "prometheus", "kuberos-rules.yml"), encoding="utf-8") as handle:
        rules = handle.read()
    config = {
        "global": {"scrape_interval": "5s", "evaluation_interval": "5s"},
        "rule_files": ["/etc/prometheus/kuberos-rules.yml"],
        # Debian's Prometheus is built without Kubernetes discovery: the replicas by DNS (the headless Service).
        "scrape_configs": [monitoring.scrape_config(namespace, ca_file="/etc/prometheus/tls/ca.crt", discovery="dns")],
    }
    rbac = "rbac.authorization.k8s.io/v1"
    discover = [{"apiGroups": [""], "resources": ["services", "endpoints", "pods"], "verbs": ["get", "list", "watch"]}]
    subjects = [{"kind": "ServiceAccount", "name": PROMETHEUS, "namespace": namespace}]
    volumes = [
        {"name": "config", "configMap": {"name": PROMETHEUS}},
        {"name": "tls", "secret": {"secretName": tls_secret, "items": [{"key": "ca.crt", "path": "ca.crt"}]}},
        {"name": "data", "emptyDir": {}},
    ]
    mounts = [
        {"name": "config", "mountPath": "/etc/prometheus"},
        {"name": "tls", "mountPath": "/etc/prometheus/tls"},
        {"name": "data", "mountPath": "/prometheus"},
    ]
    container = {
        "name": "prometheus",
        "image": PROMETHEUS_IMAGE,
        "imagePullPolicy": "IfNotPresent",
        "args": ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"],
        "ports": [{"name": "web", "containerPort": 9090}],
        "readinessProbe": {"httpGet": {"path": "/-/ready", "port": 9090}, "periodSeconds": 2},
        "volumeMounts": mounts,
    }
    return [
        {"apiVersion": "v1", "kind": "ServiceAccount", "metadata": {"name": PROMETHEUS, "namespace": namespace}},
        {"apiVersion": rbac, "kind": "ClusterRole", "metadata": {"name": PROMETHEUS}, "rules": discover},
        {
            "apiVersion": rbac,
            "kind": "ClusterRole",
            "metadata": {"name": monitoring.READER_ROLE},
            "rules": monitoring.READER_RULES,
        },
        *(
            {
                "apiVersion": rbac,
                "kind": "ClusterRoleBinding",
                "metadata": {"name": f"{PROMETHEUS}-{role}"},
                "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": role},
                "subjects": subjects,
            }
            for role in (PROMETHEUS, monitoring.READER_ROLE)
        ),
        {
            "apiVersion": "v1",
            "kind": "ConfigMap",
            "metadata": {"name": PROMETHEUS, "namespace": namespace},
            "data": {"prometheus.yml": yaml.safe_dump(config, sort_keys=False), "kuberos-rules.yml": rules},
        },
        {
            "apiVersion": "v1",
            "kind": "Pod",
            "metadata": {"name": PROMETHEUS, "namespace": namespace, "labels": {"app.kubernetes.io/name": PROMETHEUS}},
            # as restricted as the collection's pods: the namespace may enforce it (the controller's does)
            "spec": pod_security.harden(
                {
                    "serviceAccountName": PROMETHEUS,
                    "securityContext": {"runAsUser": 65534, "runAsGroup": 65534, "runAsNonRoot": True, "fsGroup": 65534},
                    "terminationGracePeriodSeconds": 2,
                    "containers": [container],
                    "volumes": volumes,
                },
                user=65534,
            ),
        },
    ]


def apply_objects(api_client, objects: list[dict], delete: bool = False) -> None:
    """Create (or, with ``delete``, remove in reverse order) plain objects through the dynamic client."""
    from kubernetes import dynamic
    from kubernetes.dynamic.exceptions import NotFoundError

    client = dynamic.DynamicClient(api_client)
    for obj in reversed(objects) if delete else objects:
        resource = client.resources.get(api_version=obj["apiVersion"], kind=obj["kind"])
        namespace = obj["metadata"].get("namespace")
        if delete:
            try:
                resource.delete(name=obj["metadata"]["name"], namespace=namespace)
            except NotFoundError:
                pass
        else:
            resource.create(body=obj, namespace=namespace)


def prometheus_api(address: str, path: str, **params) -> dict | None:
    """``data`` of an answer of the Prometheus HTTP API at ``address`` (its pod IP, reached from the host), or None
    while it does not answer."""
    import urllib.parse
    import urllib.request

    url = f"http://{address}:9090/api/v1/{path}?" + urllib.parse.urlencode(params)
    try:
        with urllib.request.build_opener().open(url, timeout=5) as answer:
            return json.loads(answer.read())["data"]
    except OSError:
        return None


# -- a robot cut off the network (docs/connectivity.md) ---------------------------------------------------------
def pods_on(core, namespace, node) -> dict[str, tuple[str, int, bool]]:
    """The pods on a node: name -> (UID, restarts of its containers, being deleted)."""
    found = {}
    for pod in core.list_namespaced_pod(namespace, field_selector=f"spec.nodeName={node}").items:
        restarts = sum(s.restart_count for s in pod.status.container_statuses or [])
        found[pod.metadata.name] = (pod.metadata.uid, restarts, pod.metadata.deletion_timestamp is not None)
    return found


def node_unreachable(core, node) -> bool:
    taints = core.read_node(node).spec.taints or []
    return any(t.key == "node.kubernetes.io/unreachable" and t.effect == "NoExecute" for t in taints)


def node_ready(core, node) -> bool:
    conditions = core.read_node(node).status.conditions or []
    return any(c.type == "Ready" and c.status == "True" for c in conditions) and not node_unreachable(core, node)


def events_of(core, namespace, reason) -> dict[str, tuple[str, str]]:
    """Event UID -> (the object it is about, its message), of one reason."""
    items = core.list_namespaced_event(namespace, field_selector=f"reason={reason}").items
    return {e.metadata.uid: (e.involved_object.name, e.message) for e in items}


def new_events(core, namespace, reason, before: dict) -> list[tuple[str, str]]:
    return [event for uid, event in events_of(core, namespace, reason).items() if uid not in before]


def placed_instances(placement: dict) -> dict[str, str]:
    """Deployment name -> node, for every module instance and discovery server (the fleet's and each robot's own) of
    a placement (placement.json)."""
    wanted = {inst["name"]: inst["node"] for inst in placement["instances"]}
    wanted.update({server["name"]: server["node"] for fleet in placement["discovery"] for server in fleet["servers"]})
    wanted.update({server["name"]: server["node"] for server in placement.get("robot_discovery", [])})
    return wanted


# A talker or a listener (argv: role, topic, seconds, servers), run inside a module's container. Its
# ROS_DISCOVERY_SERVER (as the kubelet expanded it) is the container's with servers "all"; loses its last entry, the
# robot's own server, with "fleet"; keeps only the entry at position k (the others empty, so k stays its id) with "k".
PAIR_PROGRAM = """
import os, sys, time
role, topic, seconds, servers = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
if servers == "fleet":
    os.environ["ROS_DISCOVERY_SERVER"] = os.environ["ROS_DISCOVERY_SERVER"].rsplit(";", 1)[0]
elif servers.isdigit():
    entries = os.environ["ROS_DISCOVERY_SERVER"].split(";")
    os.environ["ROS_DISCOVERY_SERVER"] = ";".join(e if i == int(servers) else "" for i, e in enumerate(entries))
import rclpy
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("kuberos_offline_" + role)
start = time.monotonic()
if role == "talker":
    pub = node.create_publisher(String, topic, 10)
    count = 0
    def tick():
        global count
        count += 1
        pub.publish(String(data=str(count)))
    node.create_timer(0.1, tick)
else:
    node.create_subscription(String, topic, lambda m: print(f"received {m.data} {time.monotonic() - start:.2f}", flush=True), 10)
print("servers " + os.environ.get("ROS_DISCOVERY_SERVER", ""), flush=True)
while time.monotonic() - start < seconds:
    rclpy.spin_once(node, timeout_sec=0.1)
"""


def container_of(core, namespace: str, node: str, component: str = "ros-module") -> str:
    """The containerd id of the first container of a KubeROS pod of ``component`` on ``node``."""
    for pod in core.list_namespaced_pod(namespace, field_selector=f"spec.nodeName={node}").items:
        if (pod.metadata.labels or {}).get("kuberos.io/component") == component and pod.status.container_statuses:
            return pod.status.container_statuses[0].container_id.split("://", 1)[1]
    raise AssertionError(f"no {component} pod runs on {node}")


def ros_in_container(socket: str, container: str, role: str, topic: str, seconds: float, fleet_only: bool | int):
    """A talker or a listener (``PAIR_PROGRAM``) started now inside ``container`` through its node's containerd
    (``socket``; no API server needed, so also on a robot that is cut off), with the container's environment
    (``fleet_only``: without the robot's own discovery server; an int k: with the fleet's server k only), for
    ``seconds``: its ``ctr`` process."""
    tag = f"{role[0]}-{topic.strip('/')}-{int(time.time() * 1000) % 10**8}"
    servers = ("fleet" if fleet_only else "all") if isinstance(fleet_only, bool) else str(fleet_only)
    command = ["ctr", "-a", socket, "-n", "k8s.io", "tasks", "exec", "--exec-id", tag, container,
               "python3", "-c", PAIR_PROGRAM, role, topic, str(seconds), servers]  # fmt: skip
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def heard(listener, seconds: float) -> dict:
    """What a ``ros_in_container`` listener heard, once it ends: seconds from its start to its first message (None:
    none), how many, the servers it was given, and the end of its output."""
    try:
        out, _ = listener.communicate(timeout=seconds + 60)
    except subprocess.TimeoutExpired:
        listener.kill()
        out, _ = listener.communicate()
    times = [float(t) for t in re.findall(r"^received \d+ ([\d.]+)$", out, re.MULTILINE)]
    servers = re.search(r"^servers (.*)$", out, re.MULTILINE)
    return {
        "first_s": times[0] if times else None,
        "messages": len(times),
        "servers": servers.group(1) if servers else None,
        "out": out[-2000:],
    }


def pair_in_container(socket: str, container: str, topic: str, seconds: float, fleet_only: bool) -> dict:
    """A talker and a listener started now side by side in one container (``ros_in_container``): ``heard``."""
    talker = ros_in_container(socket, container, "talker", topic, seconds, fleet_only)
    try:
        return heard(ros_in_container(socket, container, "listener", topic, seconds, fleet_only), seconds)
    finally:
        try:
            talker.wait(timeout=seconds + 30)
        except subprocess.TimeoutExpired:
            talker.kill()


def udp_flows(netns: str, port: int) -> list[str]:
    """The connection-tracking entries of UDP flows to ``port`` in a node's network namespace (where kube-proxy's
    rules translate a Service's address to a pod's), as `conntrack -L` prints them."""
    done = subprocess.run(["ip", "netns", "exec", netns, "conntrack", "-L", "-p", "udp", "--dport", str(port)],
                          capture_output=True, text=True, timeout=30)  # fmt: skip
    return [line for line in done.stdout.splitlines() if line.startswith("udp")]


def running_instances(core, namespace) -> dict[str, str]:
    """Instance -> node of the KubeROS pods that are Running and Ready (not being deleted)."""
    return {
        p.metadata.labels.get("kuberos.io/instance"): p.spec.node_name
        for p in core.list_namespaced_pod(namespace, label_selector="kuberos.io/instance").items
        if pod_ready(p)
    }


def running_where_placed(core, namespace, placed: dict) -> dict | None:
    """``running_instances``, when every placed instance (``placed``: instance -> node) has one on its node; else
    None."""
    now = running_instances(core, namespace)
    return now if all(now.get(name) == node for name, node in placed.items()) else None


def cut_off_robot(real, namespace: str, placed: dict, robot: str, control_namespace: str, status: str, hold_s: float,
                  toleration_s: float, pair_s: float = 0.0, during=None) -> dict:  # fmt: skip
    """Cut ``robot`` off the network (every packet of its control link and its link to the other nodes dropped)
    until a pod without the platform's tolerations (the negative control, in ``control_namespace``, which has the
    ``programs`` ConfigMap) is evicted and ``hold_s`` more, with a controller running; reconnect it. What was seen,
    for a test to assert and a benchmark to record: the robot's pods before, during and after (UID, restarts,
    deleting), when the node was tainted and the control evicted, the status rows of ``status``, the RobotOffline
    and ModuleMoved events of the partition, and how long after reconnecting the node was Ready and every placed
    instance (``placed``: instance -> node) Running and Ready where placed. ``pair_s``: once the control is evicted,
    two talker-listener pairs run that long in an onboard module's container (``pair_in_container``), with and
    without the robot's own discovery server. ``during``: called once the control is evicted (its result in
    ``during_result``)."""
    from concurrent.futures import ThreadPoolExecutor

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import RealNodes

    core = real.core
    nodes = RealNodes.from_state(real.plane(), {})
    control = program_pod("offline-control", robot, control_namespace, ["-c", "import time; time.sleep(100000)"], {}, robot)
    core.create_namespaced_pod(control_namespace, control)
    seen: dict = {"robot": robot, "toleration_s": toleration_s}
    try:
        wait_for(lambda: pod_ready(core.read_namespaced_pod("offline-control", control_namespace)), 120, "the control Running")
        seen["running_before"] = wait_for(lambda: running_where_placed(core, namespace, placed), 120, "every module placed")
        moves, offline = events_of(core, namespace, "ModuleMoved"), events_of(core, namespace, "RobotOffline")
        seen["before"] = pods_on(core, namespace, robot)
        container = container_of(core, namespace, robot) if pair_s else ""
        seen["cut"] = nodes.partition(robot) and nodes.partitioned(robot)
        cut = time.monotonic()
        wait_for(lambda: node_unreachable(core, robot), 120, f"{robot} tainted unreachable")
        seen["tainted_after_s"] = round(time.monotonic() - cut, 1)
        wait_for(lambda: core.read_namespaced_pod("offline-control", control_namespace).metadata.deletion_timestamp,
                 60 + toleration_s, "the negative control evicted from the unreachable robot")  # fmt: skip
        seen["control_evicted_after_s"] = round(time.monotonic() - cut, 1)
        if pair_s:
            # Two modules that start while the robot is cut off: one pair with the container's environment (the
            # robot's own discovery server listed), one without it (the negative control), side by side.
            with ThreadPoolExecutor(2) as pool:
                own = pool.submit(pair_in_container, nodes.socket(robot), container, "/kuberos_cut_own", pair_s, False)
                fleet = pool.submit(pair_in_container, nodes.socket(robot), container, "/kuberos_cut_fleet", pair_s, True)
                seen["pair_with_own_server"], seen["pair_fleet_only"] = own.result(), fleet.result()
        if during is not None:
            seen["during_result"] = during()  # e.g. a rollout while the robot is away
        time.sleep(hold_s)

        def offline_rows():
            rows = json.loads(core.read_namespaced_config_map(status, namespace).data["status.json"])["rows"]
            mine = [r for r in rows if r["node"] == robot]
            return mine if mine and all(r["phase"] == "Offline" for r in mine) else None

        seen["offline_rows"] = wait_for(offline_rows, 30, f"the status showing {robot}'s modules Offline")
        seen["during"] = pods_on(core, namespace, robot)
        seen["robot_offline_events"] = [message for _object, message in new_events(core, namespace, "RobotOffline", offline)]
        seen["moves_during"] = new_events(core, namespace, "ModuleMoved", moves)
        seen["partition_s"] = round(time.monotonic() - cut, 1)
        seen["reconnected"] = nodes.partition(robot, cut=False) and not nodes.partitioned(robot)
        back = time.monotonic()
        wait_for(lambda: node_ready(core, robot), 120, f"{robot} Ready again", 0.2)
        seen["ready_after_reconnect_s"] = round(time.monotonic() - back, 1)
        seen["running_after"] = wait_for(lambda: running_where_placed(core, namespace, placed), 120, "every module placed", 0.2)
        seen["rematch_after_reconnect_s"] = round(time.monotonic() - back, 1)
        seen["after"] = pods_on(core, namespace, robot)
        seen["control_gone"] = bool(
            wait_for(lambda: "offline-control" not in pods_on(core, control_namespace, robot), 120, "the evicted control gone")
        )
        seen["moves_after"] = new_events(core, namespace, "ModuleMoved", moves)
        return seen
    finally:
        nodes.partition(robot, cut=False)
        try:
            core.delete_namespaced_pod("offline-control", control_namespace, grace_period_seconds=0)
        except Exception:
            pass
