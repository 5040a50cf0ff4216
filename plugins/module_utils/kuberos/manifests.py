"""Rendering of a placement into Kubernetes objects (plain dicts, ready for server-side apply).

Per fleet: a namespace and its redundant Fast DDS discovery servers (a Deployment and a UDP
Service each). Per module instance: a Deployment pinned to its node by the unique hostname
label, with ROS_DISCOVERY_SERVER, RMW_IMPLEMENTATION and ROS_DOMAIN_ID set, resources, one
container per launch line (each a literal argv, no shell: ``launch.py``), and a ConfigMap for
ROS parameters.
"""

from __future__ import annotations

import copy
import hashlib
import re
from dataclasses import dataclass

from . import cyclonedds, image_pins, naming, network_policy, pod_security, scaling
from . import labels as node_labels
from .fastdds import TRANSPORT_ENV
from .labels import (
    CATALOG_MODULE,
    CLUSTER_ANNOTATION,
    COMPONENT,
    DEPLOYMENT,
    DEVELOPER_ANNOTATION,
    DISCOVERY_ID,
    INSTANCE,
    MANAGED_BY,
    MAPS_ANNOTATION,
    MODULE,
    REASON_ANNOTATION,
    ROBOTS_ANNOTATION,
    TIER_ANNOTATION,
    VERSION,
)
from .launch import container_name, launch_argv, split_amount
from .placement import (
    BRIDGE_CPU_MILLIS,
    BRIDGE_MEMORY_BYTES,
    DISCOVERY_CPU_MILLIS,
    DISCOVERY_MEMORY_BYTES,
    BridgeServer,
    DiscoveryServer,
    Instance,
    Placement,
    RobotServer,
)
from .quantities import format_cpu, format_memory
from .spec import RosDeployment, RosModule
from .third_party import yaml

ROBOT_DISCOVERY = "robot-discovery-server"  # the component of a deployment's discovery server on a robot's computer
# How a module's pod is replaced (an upgrade, a move): surge starts the new pod and stops the old one once the new
# one is Ready; recreate stops the old pod first (a module that must never run twice, e.g. one holding hardware).
UPGRADE_STRATEGIES = {
    "surge": {"type": "RollingUpdate", "rollingUpdate": {"maxSurge": 1, "maxUnavailable": 0}},
    "recreate": {"type": "Recreate"},
}
BRIDGE_ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge"
BRIDGE_TLS_DIR = "/etc/kuberos-bridge/tls"
BRIDGE_TOPICS_DIR = "/etc/kuberos-bridge/topics"
BRIDGE_METRICS_PORT = 9090
PARAMS_DIR = "/etc/kuberos"
PARAMS_FILE = "params.yaml"
ROBOTS_DIR = "/etc/kuberos-robots"  # a scaled module's robots: one file per instance (beside the parameters volume)
RMW = "rmw_fastrtps_cpp"


CYCLONEDDS_VOLUME = "cyclonedds"


@dataclass(frozen=True)
class RenderOptions:
    cluster_domain: str = "cluster.local"
    discovery_image: str = "ros:jazzy-ros-base"
    image_pull_policy: str = "IfNotPresent"
    bridge_image: str = "ghcr.io/kuberos/bridge:0.2.0"
    # The inventory's device parameters per node (inventory.device_parameters): ((node, ((device, ((name, value),
    # ...)), ...)), ...); launch arguments '{device:<device>.<parameter>}' take their value from the instance's node.
    device_parameters: tuple = ()
    robot_nodes: tuple = ()  # ((robot, its onboard computer's node), ...)
    # The namespaces whose pods may read the fleet's metrics ports (NetworkPolicy): the controller's, by default.
    metrics_namespaces: tuple = network_policy.DEFAULT_METRICS_NAMESPACES
    # ((image, digest), ...): what deploy resolved each image's tag to (image_pins); rendered as image@digest.
    image_digests: tuple = ()

    def pin(self, image: str) -> str:
        """``image`` as rendered: ``image@digest`` once its tag is resolved, as given when it has a digest already."""
        return image_pins.pinned(image, dict(self.image_digests))

    def device_parameter(self, node: str, device: str, parameter: str, robot: str | None = None) -> str | None:
        """The parameter of ``device`` of ``node`` when the node carries it, else of ``robot``'s computer."""
        nodes = dict(self.device_parameters)
        if device not in dict(nodes.get(node, ())) and robot is not None:
            node = dict(self.robot_nodes).get(robot, node)
        return dict(dict(nodes.get(node, ())).get(device, ())).get(parameter)


def device_options(inventory) -> dict:
    """The ``RenderOptions`` fields an inventory model (``inventory.Inventory``) gives: its device parameters."""
    return {
        "device_parameters": tuple(
            sorted((name, node.device_parameters) for name, node in inventory.nodes.items() if node.device_parameters)
        ),
        "robot_nodes": tuple(sorted((name, robot.node) for name, robot in inventory.robots.items())),
    }


def launch_argument_problems(deployments: list[RosDeployment], placement: Placement, options: RenderOptions) -> list:
    """(deployment, module, node, argument, device, parameter) of every device parameter a placed instance's launch
    arguments take that its node's inventory entry does not give (kuberos_device_parameters)."""
    modules = {(d.name, m.name): m for d in deployments for m in d.modules}
    missing = []
    for inst in placement.instances:
        module = modules.get((inst.deployment, inst.module))
        for argument in module.launch_arguments if module else ():
            if _argument_value(argument, inst, options) is None:
                missing.append((inst.deployment, inst.module, inst.node, argument.name, argument.device, argument.parameter))
    return missing


def _argument_value(argument, inst: Instance, options: RenderOptions) -> str | None:
    """A launch argument's value for one instance: its own, or its device's parameter (of the instance's node, else
    of its robot's computer); None when the inventory gives neither."""
    if not argument.device:
        return argument.value
    robot = inst.robots[0] if len(inst.robots) == 1 else None
    return options.device_parameter(inst.node, argument.device, argument.parameter, robot)


def discovery_server_list(servers: list[DiscoveryServer]) -> str:
    """ROS_DISCOVERY_SERVER value: addresses separated by ';', the position being the server id.

    Each address is its Service's cluster IP as the kubelet expands it (``$(KUBEROS_DISCOVERY_0_SERVICE_HOST)``,
    from the Services of the pod's namespace, which is the servers'), not its DNS name: Fast DDS rejects the whole
    list when one name does not resolve and falls back to multicast discovery, which finds nothing here. A module
    that starts while the cluster's DNS cannot be reached (a robot cut off from the edge servers that run it) would
    stay deaf until restarted; with the cluster IP it meets the servers as soon as it reaches them."""
    by_id = {s.server_id: s for s in servers}
    slots = []
    for server_id in range(max(by_id) + 1 if by_id else 0):
        server = by_id.get(server_id)
        slots.append(f"$({naming.service_host_variable(server.name)}):{server.port}" if server else "")
    return ";".join(slots)


_REFERENCE = re.compile(r"\$\$|\$\(([A-Za-z_][A-Za-z0-9_.-]*)\)")


def linked_server_list(servers: list[DiscoveryServer], server: DiscoveryServer) -> str:
    """ROS_DISCOVERY_SERVER of one of the fleet's servers: the others, its own position empty. Linked, a server that
    starts copies what the others know: a replaced pod (a new address with the old identity) learns the fleet's
    topics again from the other server (docs/connectivity.md)."""
    slots = discovery_server_list(servers).split(";")
    return ";".join("" if index == server.server_id else slot for index, slot in enumerate(slots))


def expand_references(value: str, variables: dict[str, str]) -> str:
    """An env value as the kubelet expands it: ``$(NAME)`` becomes ``variables[NAME]`` when defined and stays as it
    is otherwise, ``$$`` becomes ``$`` (for tools that start containers without a kubelet: the simulator, tests)."""
    return _REFERENCE.sub(lambda m: "$" if m.group(0) == "$$" else variables.get(m.group(1), m.group(0)), value)


# A robot that drops off the network (dead zones, roaming, lifts) is tainted unreachable or not-ready after the node
# grace period; by default Kubernetes then evicts its pods 300 s later, and the robot's kubelet kills them the moment
# it is back. An onboard pod tolerates both for as long as the robot is away: it keeps running on the robot, untouched
# (docs/connectivity.md).
OFFLINE_TOLERATIONS = tuple(
    {"key": taint, "operator": "Exists", "effect": "NoExecute"}
    for taint in (node_labels.UNREACHABLE_TAINT, node_labels.NOT_READY_TAINT)
)


def _selector_and_tolerations(node: str, tier: str, robot: str | None) -> dict:
    spec = {"nodeSelector": {node_labels.HOSTNAME: node}}
    if tier == "onboard":
        toleration = {"key": node_labels.ROBOT_TAINT, "operator": "Exists", "effect": "NoSchedule"}
        if robot:
            toleration = {"key": node_labels.ROBOT_TAINT, "operator": "Equal", "value": robot, "effect": "NoSchedule"}
        spec["tolerations"] = [toleration, *(dict(t) for t in OFFLINE_TOLERATIONS)]
    return spec


def _namespace(fleet: str, namespace: str) -> dict:
    return {
        "apiVersion": "v1",
        "kind": "Namespace",
        "metadata": {"name": namespace, "labels": {MANAGED_BY: "kuberos", node_labels.FLEET: fleet}},
    }


def fleet_policies(fleet: str, namespace: str = "") -> list[dict]:
    """The fleet namespace's default deny and its pods open to one another (network_policy)."""
    namespace = namespace or naming.fleet_namespace(fleet)
    labels = {MANAGED_BY: "kuberos", COMPONENT: network_policy.COMPONENT_VALUE, node_labels.FLEET: fleet}
    return network_policy.fleet_policies(namespace, labels)


def _metrics_policy(dep: RosDeployment, module: RosModule, base_labels: dict, options: RenderOptions) -> dict:
    """A scaled module's gauge port, open to the namespaces that read it (the controller's)."""
    return network_policy.metrics_policy(
        naming.metrics_policy_name(dep.name, module.name),
        naming.fleet_namespace(dep.fleet),
        {**base_labels, MODULE: module.name},
        {"matchLabels": {DEPLOYMENT: dep.name, MODULE: module.name}},
        [module.scaling.metrics_port],
        options.metrics_namespaces,
    )


def namespace_levels(objects: list[dict]) -> dict[str, str]:
    """The Pod Security level each namespace of ``objects`` can enforce: the loosest its rendered pods need."""
    levels: dict[str, list[str]] = {}
    for obj in objects:
        spec = pod_security.pod_spec_of(obj)
        if spec is not None:
            levels.setdefault(obj["metadata"].get("namespace", ""), []).append(pod_security.level(spec)[0])
    return {namespace: pod_security.loosest(found) for namespace, found in levels.items()}


def label_namespaces(objects: list[dict]) -> list[dict]:
    """``objects`` with each Namespace labelled to enforce the level its pods allow (restricted when it has none)."""
    levels = namespace_levels(objects)
    for obj in objects:
        if obj["kind"] == "Namespace":
            enforced = levels.get(obj["metadata"]["name"], "restricted")
            obj["metadata"]["labels"].update(pod_security.namespace_labels(enforced))
    return objects


# How long a discovery server's clients keep it without hearing from it (the lease it announces, with an announcement
# every DISCOVERY_ANNOUNCE_S), and how long a server waits before it serves. Fast DDS clients that hear a server again
# within its lease take it for the one they knew and never send it their endpoints again (eProsima/Fast-DDS#2534):
# a server restarted that quickly knows the old participants but not their publishers and subscriptions, so a module
# started afterwards never meets them. A server that starts only once its predecessor's lease has run out meets
# clients that have let it go, and every one of them registers anew (measured: docs/connectivity.md).
DISCOVERY_LEASE_S = 4
DISCOVERY_ANNOUNCE_S = 1
DISCOVERY_START_DELAY_S = DISCOVERY_LEASE_S + 1
DISCOVERY_PROFILE_ENV = "KUBEROS_DISCOVERY_PROFILE"
DISCOVERY_PROFILE = f"""<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <participant profile_name="kuberos_discovery_server" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <discoveryProtocol>SERVER</discoveryProtocol>
            <leaseDuration><sec>{DISCOVERY_LEASE_S}</sec></leaseDuration>
            <leaseAnnouncement><sec>{DISCOVERY_ANNOUNCE_S}</sec></leaseAnnouncement>
          </discovery_config>
        </builtin>
      </rtps>
    </participant>
  </profiles>
</dds>
"""
# The address a server announces: its Service's (the cluster IP, in the container's environment from the Service's
# link). A server announcing its pod's address sends its clients there; when its pod is replaced (a new address behind
# the same Service) they keep sending to the old one and never hear what the new one relays (measured:
# docs/connectivity.md). Announcing the Service's address, a replaced server is to its clients one restarted in place.
DISCOVERY_ADDRESS_ENV = "KUBEROS_DISCOVERY_ADDRESS"
# The server's container: checks that its Service's address is known (a pod started before its Service was made has
# no link; it exits and starts again, when the kubelet gives it one), waits out the delay (a stop meanwhile ends it at
# once), writes the profile from the environment to a file of its own, and becomes fast-discovery-server (PID 1 of
# the container, so a stop reaches it: it says goodbye to its clients, who then let it go at once). $0 is the delay,
# "$@" the server's arguments; without an address (as before) it announces every address of its pod.
DISCOVERY_START = (
    f'address="${{{DISCOVERY_ADDRESS_ENV}:-0.0.0.0}}"; case "$address" in [$]*) echo "kuberos: no address for this '
    'discovery server yet ($address: its Service did not exist when the container started); starting again" >&2; '
    'exit 1;; esac; trap "exit 0" TERM INT; sleep "$0" & wait $!; profile="${TMPDIR:-/tmp}/kuberos-discovery-$$.xml"; '
    f'printf %s "${DISCOVERY_PROFILE_ENV}" > "$profile" && exec fast-discovery-server -x "$profile" -l "$address" "$@"'
)


def discovery_server_args(server_id: int, port: int, delay_s: int = DISCOVERY_START_DELAY_S) -> list[str]:
    """The container args of a discovery server (run by the image's entrypoint, as any module's)."""
    return ["sh", "-c", DISCOVERY_START, str(delay_s), "-i", str(server_id), "-p", str(port)]


def discovery_readiness_probe(port: int) -> dict:
    """Ready once the server listens: its UDP port is bound (the kernel's socket table, read by ``grep``; a UDP server
    answers no HTTP, TCP or gRPC probe). Until then, and while it waits out its predecessor's lease, it is not Ready,
    so a deploy's wait and a rollout's gate wait for the server itself, not only for its container."""
    return {
        "exec": {"command": ["grep", "-qsi", f":{port:04X} ", "/proc/net/udp", "/proc/net/udp6"]},
        "periodSeconds": 2,
        "failureThreshold": 1,
    }


def discovery_server_env(service: str, peers: str = "") -> list[dict]:
    """A discovery server container's environment: its profile, the address it announces (its Service's ``service``),
    and the servers it is linked to (``peers``: a ROS_DISCOVERY_SERVER value, its own position empty)."""
    return [
        {"name": DISCOVERY_PROFILE_ENV, "value": DISCOVERY_PROFILE},
        {"name": DISCOVERY_ADDRESS_ENV, "value": f"$({naming.service_host_variable(service)})"},
        *([{"name": "ROS_DISCOVERY_SERVER", "value": peers}] if peers.strip(";") else []),
    ]


def _discovery_deployment(
    name: str, namespace: str, labels: dict, selector: dict, server_id: int, port: int, node: str, tier: str,
    robot: str | None, annotations: dict, options: RenderOptions, service: str, peers: str = "",
) -> dict:  # fmt: skip
    """A Fast DDS discovery server: one pod pinned to ``node``, serving UDP ``port`` as server ``server_id`` at the
    address of its Service ``service``, linked to the servers ``peers`` names (a ROS_DISCOVERY_SERVER value, its own
    position empty)."""
    pod_spec = {
        **_selector_and_tolerations(node, tier, robot),
        "containers": [
            {
                "name": "discovery-server",
                "image": options.pin(options.discovery_image),
                "imagePullPolicy": options.image_pull_policy,
                # args, not command: the image's entrypoint runs first (the published ROS images source their
                # setup there; nothing of ROS is on their PATH before it)
                "args": discovery_server_args(server_id, port),
                "env": discovery_server_env(service, peers),
                "ports": [{"name": "discovery", "containerPort": port, "protocol": "UDP"}],
                "readinessProbe": discovery_readiness_probe(port),
                "resources": {
                    "requests": {"cpu": format_cpu(DISCOVERY_CPU_MILLIS), "memory": format_memory(DISCOVERY_MEMORY_BYTES)},
                    "limits": {"memory": format_memory(DISCOVERY_MEMORY_BYTES)},
                },
            }
        ],
    }
    pod_security.harden(pod_spec)
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {"name": name, "namespace": namespace, "labels": labels, "annotations": annotations},
        "spec": {
            "replicas": 1,
            "strategy": {"type": "Recreate"},
            "selector": {"matchLabels": selector},
            "template": {"metadata": {"labels": dict(labels)}, "spec": pod_spec},
        },
    }


def _discovery_service(name: str, namespace: str, labels: dict, selector: dict, port: int, local: bool = False) -> dict:
    spec = {
        "selector": selector,
        "ports": [{"name": "discovery", "port": port, "targetPort": port, "protocol": "UDP"}],
    }
    if local:
        spec["internalTrafficPolicy"] = "Local"  # on each node, only the server that runs there answers
    return {
        "apiVersion": "v1",
        "kind": "Service",
        "metadata": {"name": name, "namespace": namespace, "labels": labels},
        "spec": spec,
    }


def _discovery_objects(server: DiscoveryServer, options: RenderOptions, fleet: list[DiscoveryServer] = ()) -> list[dict]:
    """A fleet server's Deployment and Service, linked to the others of ``fleet``."""
    labels = {
        MANAGED_BY: "kuberos",
        COMPONENT: "discovery-server",
        node_labels.FLEET: server.fleet,
        DISCOVERY_ID: str(server.server_id),
        INSTANCE: server.name,
    }
    selector = {COMPONENT: "discovery-server", DISCOVERY_ID: str(server.server_id)}
    annotations = {REASON_ANNOTATION: server.reason, TIER_ANNOTATION: server.tier}
    return [
        _discovery_deployment(
            server.name, server.namespace, labels, selector, server.server_id, server.port, server.node, server.tier,
            None, annotations, options, server.name, linked_server_list(list(fleet), server),
        ),
        _discovery_service(server.name, server.namespace, labels, selector, server.port),
    ]  # fmt: skip


def robot_discovery_slot(servers: list[DiscoveryServer]) -> int:
    """The id (and ``ROS_DISCOVERY_SERVER`` position) of the robot discovery servers: the first after the fleet's."""
    return max((s.server_id for s in servers), default=-1) + 1


def robot_discovery_address(dep: RosDeployment) -> str:
    """One robot discovery server as its modules name it: the deployment's node-local Service's address."""
    return f"$({naming.service_host_variable(naming.robot_discovery_service_name(dep.name))}):{dep.discovery_port}"


def fleet_discovery_part(value: str) -> str:
    """A ``ROS_DISCOVERY_SERVER`` value without its robot's own server (an onboard module's lists it last): the
    fleet's servers, as every module of the fleet lists them."""
    marker = "$(" + naming.service_host_variable(naming.ROBOT_DISCOVERY_PREFIX)[: -len("_SERVICE_HOST")]
    return ";".join(entry for entry in value.split(";") if not entry.startswith(marker))


def robot_discovery_objects(dep: RosDeployment, servers: list[RobotServer], slot: int, options: RenderOptions) -> list[dict]:
    """``dep``'s discovery servers on its robots' computers (``servers``: the placement's, one Deployment each, pinned
    there and tolerating the robot being offline like its onboard modules) and their one node-local Service.

    A robot's onboard modules list its server after the fleet's: while the robot is cut off from the edge servers
    they still meet each other through it, also a module that starts during the cut (docs/connectivity.md). It is
    linked to nothing: the fleet's servers keep telling the rest of the fleet about the robot's modules."""
    namespace = naming.fleet_namespace(dep.fleet)
    common = {MANAGED_BY: "kuberos", COMPONENT: ROBOT_DISCOVERY, DEPLOYMENT: dep.name, node_labels.FLEET: dep.fleet}
    objects, service = [], naming.robot_discovery_service_name(dep.name)
    for server in servers:
        labels = {**common, node_labels.ROBOT: server.robot, DISCOVERY_ID: str(slot), INSTANCE: server.name}
        annotations = {
            ROBOTS_ANNOTATION: server.robot,
            TIER_ANNOTATION: "onboard",
            REASON_ANNOTATION: "the robot's own discovery server: its onboard modules meet through it while it is cut off",
        }
        objects.append(
            _discovery_deployment(
                server.name, namespace, labels, {INSTANCE: server.name}, slot, dep.discovery_port, server.node, "onboard",
                server.robot, annotations, options, service,
            )
        )  # fmt: skip
    if objects:
        selector = {COMPONENT: ROBOT_DISCOVERY, DEPLOYMENT: dep.name}
        objects.append(_discovery_service(service, namespace, dict(common), selector, dep.discovery_port, local=True))
    return objects


def discovery_from_deployments(objects: list[dict]) -> dict[str, list[DiscoveryServer]]:
    """The fleets' discovery servers as they run: read back from their live Deployments (plain dicts).

    A fleet's discovery servers are the fleet's, not one deployment's: the Deployments in the cluster say where
    each one runs, for deploy (which keeps them there) and for the controller (which reads every record of the
    fleet against them)."""
    fleets: dict[str, list[DiscoveryServer]] = {}
    for obj in objects:
        meta = obj.get("metadata") or {}
        labels = meta.get("labels") or {}
        if labels.get(COMPONENT) != "discovery-server" or meta.get("deletionTimestamp"):
            continue
        pod = ((obj.get("spec") or {}).get("template") or {}).get("spec") or {}
        node = (pod.get("nodeSelector") or {}).get(node_labels.HOSTNAME)
        ports = [p.get("containerPort") for c in pod.get("containers") or [] for p in c.get("ports") or []]
        try:
            server_id = int(labels.get(DISCOVERY_ID, ""))
        except ValueError:
            continue
        if not node or not ports:
            continue
        annotations = meta.get("annotations") or {}
        fleet = labels.get(node_labels.FLEET, "")
        fleets.setdefault(fleet, []).append(
            DiscoveryServer(
                fleet, meta.get("namespace", ""), server_id, meta.get("name", naming.discovery_server_name(server_id)), node,
                annotations.get(TIER_ANNOTATION, "edge"), int(ports[0]), annotations.get(REASON_ANNOTATION, ""),
            )
        )  # fmt: skip
    return {fleet: sorted(servers, key=lambda s: s.server_id) for fleet, servers in sorted(fleets.items())}


params_configmap_name = naming.parameters_configmap_name  # one rule, also for the name clash check


def _params_configmap(dep: RosDeployment, module: RosModule, namespace: str, base_labels: dict) -> dict:
    document = {"/**": {"ros__parameters": module.ros_parameters}}
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": params_configmap_name(dep.name, module.name),
            "namespace": namespace,
            "labels": {**base_labels, MODULE: module.name},
        },
        "data": {PARAMS_FILE: yaml.safe_dump(document, sort_keys=True, default_flow_style=False)},
    }


def parameter_map_configmap(dep: RosDeployment, pmap, base_labels: dict) -> dict:
    """A parameter map as a ConfigMap of the fleet's namespace: key-value maps key by key, a yaml map as its file."""
    data = {pmap.file_name: pmap.text} if pmap.type == "yaml" else dict(pmap.values)
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": naming.parameter_map_name(dep.name, pmap.name),
            "namespace": naming.fleet_namespace(dep.fleet),
            "labels": dict(base_labels),
            "annotations": {"kuberos.io/parameter-map": pmap.name},
        },
        "data": data,
    }


def _maps_hash(dep: RosDeployment, module: RosModule) -> str:
    digest = hashlib.sha256()
    for name in module.maps:
        pmap = dep.parameter_map(name)
        digest.update(repr((pmap.name, pmap.type, pmap.values, pmap.text)).encode())
    return digest.hexdigest()[:16]


def cyclonedds_peers(dep: RosDeployment, placement: Placement, cluster_domain: str) -> dict[str, list[str]]:
    """Each instance of a Cyclone DDS deployment and the DNS names of the instances it talks with: those serving one
    of its robots (so that the lists are symmetric: a moved instance is found again through the others' lists)."""
    instances = [i for i in placement.instances if i.deployment == dep.name and not i.cluster]
    peers = {}
    for inst in instances:
        robots = set(inst.robots)
        peers[inst.name] = sorted(
            f"{other.name}.{other.namespace}.svc.{cluster_domain}"
            for other in instances
            if other.name != inst.name and robots & set(other.robots)
        )
    return peers


def cyclonedds_objects(dep: RosDeployment, placement: Placement, base_labels: dict, options: RenderOptions) -> list[dict]:
    """A Cyclone DDS deployment's peer lists (one ConfigMap, a configuration file per instance) and a Service per
    instance: its name always resolves (Cyclone DDS aborts a process whose peer name does not) and forwards the
    discovery ports to whichever pod runs the instance now; the participants then talk pod to pod."""
    namespace = naming.fleet_namespace(dep.fleet)
    peers = cyclonedds_peers(dep, placement, options.cluster_domain)
    objects = [
        {
            "apiVersion": "v1",
            "kind": "ConfigMap",
            "metadata": {"name": naming.cyclonedds_configmap_name(dep.name), "namespace": namespace, "labels": dict(base_labels)},
            "data": {f"{name}.xml": cyclonedds.config_xml(names, dep.ros_domain_id) for name, names in sorted(peers.items())},
        }
    ]
    for inst in placement.instances:
        if inst.deployment != dep.name or inst.cluster:
            continue
        objects.append(
            {
                "apiVersion": "v1",
                "kind": "Service",
                "metadata": {
                    "name": inst.name,
                    "namespace": inst.namespace,
                    "labels": {**base_labels, MODULE: inst.module, INSTANCE: inst.name},
                },
                "spec": {
                    "selector": {INSTANCE: inst.name},
                    "ports": [
                        {"name": f"spdp-{index}", "port": port, "targetPort": port, "protocol": "UDP"}
                        for index, port in enumerate(cyclonedds.discovery_ports(dep.ros_domain_id))
                    ],
                },
            }
        )
    return objects


def _launch_words(module: RosModule, inst: Instance, options: RenderOptions) -> list[str]:
    """``name:=value`` of each launch argument (``_argument_value``)."""
    return [f"{argument.name}:={_argument_value(argument, inst, options) or ''}" for argument in module.launch_arguments]


# Sources ROS (the image's distribution) and the module's workspace, then runs the launch line: "$@" as given (a
# literal argv), or the one word after the workspace as a bash command line (shell: true).
_SOURCE = (
    'if [ -n "${ROS_DISTRO:-}" ] && [ -f "/opt/ros/$ROS_DISTRO/setup.bash" ]; then . "/opt/ros/$ROS_DISTRO/setup.bash"; fi; '
    'if [ -f "$0/setup.bash" ]; then . "$0/setup.bash"; else echo "kuberos: no $0/setup.bash to source" >&2; fi; '
)


def _command(module: RosModule, number: int, line: str, inst: Instance, options: RenderOptions) -> dict:
    """The container's command and args for launch line ``number``: a literal argv (the image's entrypoint kept),
    or through bash when the module sources a workspace or runs its lines as shell command lines."""
    words = _launch_words(module, inst, options) if number == 0 else []
    if module.shell:
        script = " ".join([line, *words])  # bash words, as written (the reference format quotes its values itself)
        if module.workspace:
            return {"command": ["/bin/bash", "-c", _SOURCE + 'eval "$1"', module.workspace, script]}
        return {"command": ["/bin/bash", "-c", script]}
    argv = launch_argv(line) + words
    if module.workspace:
        return {"command": ["/bin/bash", "-c", _SOURCE + 'exec "$@"', module.workspace, *argv]}
    # args, not command: the image's entrypoint stays (ROS images source their setup there)
    return {"args": argv}


def _module_containers(
    module: RosModule, inst: Instance, env: list[dict], options: RenderOptions, dep_name: str, peer_list: bool
) -> list[dict]:
    """One container per launch line, all of the module's image, environment and volumes. The placement counted
    the instance's cpu and memory once: the containers' requests add up to exactly that (divided evenly, the
    first container taking the remainder), each container's memory limit is its memory request, and GPUs go to
    the first container (a GPU serves one container)."""
    cpu = split_amount(inst.cpu_millis, len(module.launch))
    memory = split_amount(inst.memory_bytes, len(module.launch))
    containers = []
    registry = module.registry
    for number, line in enumerate(module.launch):
        resources = {
            "requests": {"cpu": format_cpu(cpu[number]), "memory": format_memory(memory[number])},
            "limits": {"memory": format_memory(memory[number])},
        }
        if inst.gpu and number == 0:
            resources["requests"]["nvidia.com/gpu"] = str(inst.gpu)
            resources["limits"]["nvidia.com/gpu"] = str(inst.gpu)
        container = {
            "name": container_name(module.name, number),
            "image": options.pin(module.image),
            "imagePullPolicy": (registry.pull_policy if registry else "") or options.image_pull_policy,
            **_command(module, number, line, inst, options),
            "env": copy.deepcopy(env),
            "resources": resources,
        }
        if module.env_from:
            container["envFrom"] = [
                {"configMapRef": {"name": naming.parameter_map_name(dep_name, name)}} for name in module.env_from
            ]
        container["securityContext"] = pod_security.container_security_context(module.user, module.privileged)
        mounts = []
        if module.ros_parameters:
            mounts.append({"name": "ros-parameters", "mountPath": PARAMS_DIR, "readOnly": True})
        if module.scaling:
            mounts.append({"name": "robots", "mountPath": ROBOTS_DIR, "readOnly": True})
        for position, (_map, directory) in enumerate(module.parameter_files):
            mounts.append({"name": f"parameter-file-{position}", "mountPath": directory, "readOnly": True})
        if peer_list:
            mounts.append({"name": CYCLONEDDS_VOLUME, "mountPath": cyclonedds.CONFIG_DIR, "readOnly": True})
        if mounts:
            container["volumeMounts"] = mounts
        containers.append(container)
    return containers


def robots_configmap(dep: RosDeployment, module: RosModule, placement: Placement, base_labels: dict, handover=None) -> dict:
    """The robots every instance of a scaled module serves now (``scaling.serving``: while a change is handed over,
    a robot stays with its old instance until its new one is Ready), one key per instance."""
    instances = [i for i in placement.instances if i.deployment == dep.name and i.module == module.name and not i.cluster]
    now = scaling.serving({i.name: i.robots for i in instances}, scaling.ScaleState(dict(handover or {})))
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": naming.robots_configmap_name(dep.name, module.name),
            "namespace": naming.fleet_namespace(dep.fleet),
            "labels": {**base_labels, MODULE: module.name},
        },
        "data": {name: ",".join(robots) for name, robots in sorted(now.items())},
    }


def module_labels(dep: RosDeployment) -> dict:
    """The labels every object of a deployment's modules carries."""
    return {
        **dict(dep.labels),
        MANAGED_BY: "kuberos",
        COMPONENT: "ros-module",
        DEPLOYMENT: dep.name,
        node_labels.FLEET: dep.fleet,
    }


def _middleware_env(dep: RosDeployment, inst: Instance, discovery: str | None) -> list[dict]:
    """How the module finds its peers: the fleet's discovery servers (Fast DDS), its peer list (Cyclone DDS), or,
    with ``discovery`` None (a batch job's run, all of whose modules share one pod), this pod only."""
    if discovery is None:
        rmw = cyclonedds.RMW_CYCLONEDDS if dep.rmw == "cyclonedds" else RMW
        return [{"name": "RMW_IMPLEMENTATION", "value": rmw}, {"name": "ROS_AUTOMATIC_DISCOVERY_RANGE", "value": "LOCALHOST"}]
    if dep.rmw == "cyclonedds":
        return [
            {"name": "RMW_IMPLEMENTATION", "value": cyclonedds.RMW_CYCLONEDDS},
            {"name": "CYCLONEDDS_URI", "value": f"file://{cyclonedds.CONFIG_DIR}/{inst.name}.xml"},
        ]
    return [
        {"name": "ROS_DISCOVERY_SERVER", "value": discovery},
        {"name": "RMW_IMPLEMENTATION", "value": RMW},
        *({"name": name, "value": value} for name, value in TRANSPORT_ENV),
    ]


def module_pod(
    dep: RosDeployment, module: RosModule, inst: Instance, discovery: str | None, pod_labels: dict, options: RenderOptions
) -> dict:
    """The pod template (metadata and spec) of one module instance on its node. ``discovery`` None: a batch run's
    pod, whose modules find one another on localhost only."""
    env = [
        *_middleware_env(dep, inst, discovery),
        {"name": "ROS_DOMAIN_ID", "value": str(dep.ros_domain_id)},
        {"name": "KUBEROS_FLEET", "value": dep.fleet},
        # A scaled module's robots change while it runs: they are in a file it watches, not in its pod template.
        {"name": "KUBEROS_ROBOTS_FILE", "value": f"{ROBOTS_DIR}/{inst.name}"}
        if module.scaling
        else {"name": "KUBEROS_ROBOTS", "value": ",".join(inst.robots)},
        {"name": "KUBEROS_NODE_NAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}},
    ]
    if not inst.shared:
        env.append({"name": "KUBEROS_ROBOT_NAME", "value": inst.robots[0]})
    if module.ros_parameters:
        env.append({"name": "KUBEROS_PARAMS_FILE", "value": f"{PARAMS_DIR}/{PARAMS_FILE}"})
    env.extend({"name": name, "value": value} for name, value in sorted(module.env))
    if module.user and not {"ROS_HOME", "ROS_LOG_DIR"} & {name for name, _value in module.env}:
        # ROS logs under ~/.ros; a user the image does not know has the home "/", where it may not write
        env.append({"name": "ROS_HOME", "value": pod_security.ROS_HOME})
    peer_list = dep.rmw == "cyclonedds" and discovery is not None  # a batch run's pod finds its peers on localhost
    pod_spec = {
        **_selector_and_tolerations(inst.node, inst.tier, inst.robots[0] if inst.robots else None),
        "securityContext": pod_security.pod_security_context(),
        "containers": _module_containers(module, inst, env, options, dep.name, peer_list),
    }
    volumes = []
    if module.ros_parameters:
        volumes.append({"name": "ros-parameters", "configMap": {"name": params_configmap_name(dep.name, module.name)}})
    if module.scaling:
        volumes.append({"name": "robots", "configMap": {"name": naming.robots_configmap_name(dep.name, module.name)}})
    for position, (name, _directory) in enumerate(module.parameter_files):
        volumes.append({"name": f"parameter-file-{position}", "configMap": {"name": naming.parameter_map_name(dep.name, name)}})
    if peer_list:
        volumes.append({"name": CYCLONEDDS_VOLUME, "configMap": {"name": naming.cyclonedds_configmap_name(dep.name)}})
    if volumes:
        pod_spec["volumes"] = volumes
    if module.registry and module.registry.pull_secret:
        pod_spec["imagePullSecrets"] = [{"name": module.registry.pull_secret}]
    template_meta = {"labels": pod_labels}
    if module.maps:
        template_meta["annotations"] = {MAPS_ANNOTATION: _maps_hash(dep, module)}
    return {"metadata": template_meta, "spec": pod_spec}


def _module_deployment(
    dep: RosDeployment, module: RosModule, inst: Instance, discovery: str, base_labels: dict, options: RenderOptions
) -> dict:
    labels = {**base_labels, MODULE: module.name, INSTANCE: inst.name}
    if not inst.shared:
        labels[node_labels.ROBOT] = inst.robots[0]
    pod_labels = dict(labels)  # a version only in the Deployment's labels: relabelling alone restarts no pod
    if module.version:
        labels[VERSION] = module.version
        labels[CATALOG_MODULE] = module.catalog_module
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {
            "name": inst.name,
            "namespace": inst.namespace,
            "labels": labels,
            "annotations": {
                ROBOTS_ANNOTATION: ",".join(inst.robots),
                TIER_ANNOTATION: inst.tier,
                REASON_ANNOTATION: inst.reason,
                **({DEVELOPER_ANNOTATION: dep.developer} if dep.developer else {}),
            },
        },
        "spec": {
            "replicas": 1,
            "strategy": dict(UPGRADE_STRATEGIES[module.upgrade]),
            "selector": {"matchLabels": {INSTANCE: inst.name}},
            "template": module_pod(dep, module, inst, discovery, pod_labels, options),
        },
    }


def bridge_topics(deployments: list[RosDeployment], placement: Placement, fleet: str, cluster: str) -> list[dict]:
    """The topics one bridge carries, for every robot of every module of the fleet placed in ``cluster``.
    ``{robot}`` in a topic name is the robot's name as a ROS name (``naming.robot_ros_name``). Directions as the
    bridge sees them: to_client goes from this cluster to the module's cluster, to_server comes back."""
    modules = {(d.name, m.name): m for d in deployments for m in d.modules}
    topics: dict[str, dict] = {}
    for inst in placement.instances:
        if inst.cluster != cluster or inst.fleet != fleet:
            continue
        for topic in modules[(inst.deployment, inst.module)].bridge_topics:
            name = topic.name.replace("{robot}", naming.robot_ros_name(inst.robots[0]))
            direction = "to_client" if topic.direction == "to_module" else "to_server"
            topics.setdefault(name, {"name": name, "type": topic.type, "direction": direction})
    return [topics[name] for name in sorted(topics)]


def _bridge_topics_configmap(name: str, namespace: str, labels: dict, topics: list[dict]) -> dict:
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": f"{name}-topics", "namespace": namespace, "labels": labels},
        "data": {"topics.yaml": yaml.safe_dump({"topics": topics}, sort_keys=False)},
    }


def bridge_secret_name(name: str) -> str:
    return f"{name}-tls"


def _bridge_deployment(
    name: str, namespace: str, labels: dict, pod_placement: dict, args: list[str], env: list[dict], options: RenderOptions
) -> dict:
    container = {
        "name": "bridge",
        "image": options.pin(options.bridge_image),
        "imagePullPolicy": options.image_pull_policy,
        "args": ["python", "-m", BRIDGE_ENTRY, *args],
        "env": [*env, {"name": "ROS_HOME", "value": pod_security.ROS_HOME}],
        "ports": [{"name": "metrics", "containerPort": BRIDGE_METRICS_PORT, "protocol": "TCP"}],
        "resources": {
            "requests": {"cpu": format_cpu(BRIDGE_CPU_MILLIS), "memory": format_memory(BRIDGE_MEMORY_BYTES)},
            "limits": {"memory": format_memory(BRIDGE_MEMORY_BYTES)},
        },
        "readinessProbe": {"httpGet": {"path": "/healthz", "port": BRIDGE_METRICS_PORT}},
        "volumeMounts": [
            {"name": "tls", "mountPath": BRIDGE_TLS_DIR, "readOnly": True},
            {"name": "topics", "mountPath": BRIDGE_TOPICS_DIR, "readOnly": True},
        ],
    }
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {"name": name, "namespace": namespace, "labels": labels},
        "spec": {
            "replicas": 1,
            "strategy": {"type": "Recreate"},
            "selector": {"matchLabels": {INSTANCE: labels[INSTANCE]}},
            "template": {
                "metadata": {"labels": dict(labels)},
                "spec": pod_security.harden(
                    {
                        **pod_placement,
                        "containers": [container],
                        "volumes": [
                            {"name": "tls", "secret": {"secretName": bridge_secret_name(name)}},
                            {"name": "topics", "configMap": {"name": f"{name}-topics"}},
                        ],
                    }
                ),
            },
        },
    }


def _tls_args(topics_file: str = f"{BRIDGE_TOPICS_DIR}/topics.yaml") -> list[str]:
    return [
        "--cert", f"{BRIDGE_TLS_DIR}/tls.crt", "--key", f"{BRIDGE_TLS_DIR}/tls.key", "--ca", f"{BRIDGE_TLS_DIR}/ca.crt",
        "--topics", topics_file, "--metrics-port", str(BRIDGE_METRICS_PORT),
    ]  # fmt: skip


def _ros_env(discovery: str, domain_id: int, fleet: str) -> list[dict]:
    return [
        {"name": "ROS_DISCOVERY_SERVER", "value": discovery},
        {"name": "RMW_IMPLEMENTATION", "value": RMW},
        *({"name": name, "value": value} for name, value in TRANSPORT_ENV),
        {"name": "ROS_DOMAIN_ID", "value": str(domain_id)},
        {"name": "KUBEROS_FLEET", "value": fleet},
    ]


def _bridge_server_objects(
    bridge: BridgeServer, topics: list[dict], discovery: str, first: RosDeployment, options: RenderOptions
) -> list[dict]:
    # Labelled with the first deployment that uses it: undeploying that spec removes the bridge too.
    labels = {
        MANAGED_BY: "kuberos", COMPONENT: "bridge-server", node_labels.FLEET: bridge.fleet, INSTANCE: bridge.name,
        DEPLOYMENT: first.name,
    }  # fmt: skip
    args = ["server", "--listen", f"0.0.0.0:{naming.BRIDGE_PORT}", *_tls_args()]
    deployment = _bridge_deployment(
        bridge.name, bridge.namespace, labels, _selector_and_tolerations(bridge.node, bridge.tier, None), args,
        _ros_env(discovery, first.ros_domain_id, bridge.fleet), options,
    )  # fmt: skip
    deployment["metadata"]["annotations"] = {
        REASON_ANNOTATION: bridge.reason, TIER_ANNOTATION: bridge.tier, CLUSTER_ANNOTATION: bridge.cluster,
    }  # fmt: skip
    service = {
        "apiVersion": "v1",
        "kind": "Service",
        "metadata": {"name": bridge.name, "namespace": bridge.namespace, "labels": labels},
        "spec": {
            "type": "NodePort",
            "selector": {INSTANCE: bridge.name},
            "ports": [
                {"name": "grpc", "port": naming.BRIDGE_PORT, "targetPort": naming.BRIDGE_PORT, "nodePort": bridge.node_port}
            ],
        },
    }
    policy = network_policy.bridge_policy(
        bridge.name, bridge.namespace, labels, {"matchLabels": {INSTANCE: bridge.name}}, naming.BRIDGE_PORT,
        BRIDGE_METRICS_PORT, options.metrics_namespaces,
    )  # fmt: skip
    return [_bridge_topics_configmap(bridge.name, bridge.namespace, labels, topics), deployment, service, policy]


def _unpinned(obj: dict) -> dict:
    """A Deployment for a cluster whose nodes KubeROS does not know: that cluster's scheduler picks the node."""
    pod = obj["spec"]["template"]["spec"]
    pod.pop("nodeSelector", None)
    pod.pop("tolerations", None)
    return obj


def render_remote(
    deployments: list[RosDeployment], placement: Placement, clusters: dict, options: RenderOptions | None = None
) -> dict[str, list[dict]]:
    """Per third-party cluster, the objects to apply there: the fleet's namespace, one discovery server, the
    bridge client and every module placed in that cluster. ``clusters`` maps a name to its inventory entry
    (``ExternalCluster``). Secrets (the bridge's TLS keys) are not rendered here."""
    options = options or RenderOptions()
    by_name = {d.name: d for d in deployments}
    modules = {(d.name, m.name): m for d in deployments for m in d.modules}
    out: dict[str, list[dict]] = {}
    for fleet, bridges in sorted(placement.bridges.items()):
        namespace = naming.fleet_namespace(fleet)
        for bridge in bridges:
            cluster = clusters[bridge.cluster]
            remote_options = RenderOptions(
                cluster.cluster_domain, options.discovery_image, options.image_pull_policy, options.bridge_image
            )
            instances = [i for i in placement.instances if i.cluster == bridge.cluster and i.fleet == fleet]
            first = by_name[instances[0].deployment]
            server = DiscoveryServer(fleet, namespace, 0, naming.discovery_server_name(0), "", "cloud", first.discovery_port,
                                     f"the fleet's discovery server in cluster {bridge.cluster}")  # fmt: skip
            discovery = discovery_server_list([server])
            objects = [_namespace(fleet, namespace), *fleet_policies(fleet, namespace)]
            objects.extend(_unpinned(o) if o["kind"] == "Deployment" else o for o in _discovery_objects(server, remote_options))
            labels = {MANAGED_BY: "kuberos", COMPONENT: "bridge-client", node_labels.FLEET: fleet, INSTANCE: naming.BRIDGE_CLIENT}
            topics = bridge_topics(deployments, placement, fleet, bridge.cluster)
            objects.append(_bridge_topics_configmap(naming.BRIDGE_CLIENT, namespace, labels, topics))
            args = [
                "client", "--connect", f"{cluster.bridge_endpoint}:{cluster.bridge_node_port}", "--server-name", bridge.name,
                *_tls_args(),
            ]  # fmt: skip
            objects.append(
                _bridge_deployment(
                    naming.BRIDGE_CLIENT,
                    namespace,
                    labels,
                    {},
                    args,
                    _ros_env(discovery, first.ros_domain_id, fleet),
                    remote_options,
                )
            )
            seen_params = set()
            for inst in instances:
                dep, module = by_name[inst.deployment], modules[(inst.deployment, inst.module)]
                base_labels = module_labels(dep)  # the deployment's fleet is this fleet
                if module.ros_parameters and (dep.name, module.name) not in seen_params:
                    seen_params.add((dep.name, module.name))
                    objects.append(_params_configmap(dep, module, namespace, base_labels))
                for name in module.maps:
                    if (dep.name, "map", name) not in seen_params:
                        seen_params.add((dep.name, "map", name))
                        objects.append(parameter_map_configmap(dep, dep.parameter_map(name), base_labels))
                objects.append(_unpinned(_module_deployment(dep, module, inst, discovery, base_labels, remote_options)))
            for obj in objects:
                obj["metadata"].setdefault("annotations", {})[CLUSTER_ANNOTATION] = bridge.cluster
            out[bridge.cluster] = sorted(out.get(bridge.cluster, []) + objects, key=object_order)
    return {cluster: label_namespaces(objects) for cluster, objects in out.items()}


_KIND_ORDER = {"Namespace": 0, "NetworkPolicy": 1, "ConfigMap": 2, "Service": 3, "Deployment": 4}


def object_order(obj: dict) -> tuple:
    """Apply order: namespaces, then NetworkPolicies (pods start isolated), ConfigMaps, Services and Deployments, each
    by namespace and name."""
    return (_KIND_ORDER[obj["kind"]], obj["metadata"].get("namespace", ""), obj["metadata"]["name"])


def render_deployment(
    deployments: list[RosDeployment], placement: Placement, options: RenderOptions | None = None, scaling_state=None
) -> list[dict]:
    """Every object the placement needs, ordered for applying (namespaces first). ``scaling_state`` maps
    (deployment, module) to the robots still handed over (robot -> instance serving it until its new one is Ready)."""
    options = options or RenderOptions()
    by_name = {d.name: d for d in deployments}
    objects: list[dict] = []
    fleets = sorted(placement.discovery)
    for fleet in fleets:
        servers = placement.discovery[fleet]
        namespace = naming.fleet_namespace(fleet)
        objects.append(_namespace(fleet, namespace))
        objects.extend(fleet_policies(fleet, namespace))
        for server in servers:
            objects.extend(_discovery_objects(server, options, servers))
    addresses = {f: discovery_server_list(placement.discovery[f]) for f in fleets}
    robot_servers = {(r.deployment, r.robot) for r in placement.robot_servers}
    for dep in deployments:
        if dep.fleet in placement.discovery:
            mine = [r for r in placement.robot_servers if r.deployment == dep.name]
            objects.extend(robot_discovery_objects(dep, mine, robot_discovery_slot(placement.discovery[dep.fleet]), options))
    modules = {(d.name, m.name): m for d in deployments for m in d.modules}
    seen_params = set()
    for fleet, bridges in sorted(placement.bridges.items()):
        for bridge in bridges:
            first = next(by_name[i.deployment] for i in placement.instances if i.cluster == bridge.cluster and i.fleet == fleet)
            topics = bridge_topics(deployments, placement, fleet, bridge.cluster)
            objects.extend(_bridge_server_objects(bridge, topics, addresses[fleet], first, options))
    for inst in placement.instances:
        if inst.cluster:
            continue  # rendered for its cluster by render_remote
        dep = by_name[inst.deployment]
        module = modules[(inst.deployment, inst.module)]
        base_labels = module_labels(dep)
        if (dep.name, "deployment") not in seen_params:
            seen_params.add((dep.name, "deployment"))
            objects.extend(parameter_map_configmap(dep, pmap, base_labels) for pmap in dep.parameter_maps)
            if dep.rmw == "cyclonedds":
                objects.extend(cyclonedds_objects(dep, placement, base_labels, options))
        if module.ros_parameters and (dep.name, module.name) not in seen_params:
            seen_params.add((dep.name, module.name))
            objects.append(_params_configmap(dep, module, inst.namespace, base_labels))
        if module.scaling and (dep.name, module.name, "robots") not in seen_params:
            seen_params.add((dep.name, module.name, "robots"))
            handover = (scaling_state or {}).get((dep.name, module.name))
            objects.append(robots_configmap(dep, module, placement, base_labels, handover))
            if not module.scaling.uses_cpu:
                objects.append(_metrics_policy(dep, module, base_labels, options))
        discovery = addresses[dep.fleet]
        if inst.tier == "onboard" and inst.robots and (dep.name, inst.robots[0]) in robot_servers:
            discovery = f"{discovery};{robot_discovery_address(dep)}"  # the robot's own server, after the fleet's
        objects.append(_module_deployment(dep, module, inst, discovery, base_labels, options))
    objects.sort(key=object_order)
    return label_namespaces(objects)
