"""Rendering of a placement into Kubernetes objects (plain dicts, ready for server-side apply).

Per fleet: a namespace and its redundant Fast DDS discovery servers (a Deployment and a UDP
Service each). Per module instance: a Deployment pinned to its node by the unique hostname
label, with ROS_DISCOVERY_SERVER, RMW_IMPLEMENTATION and ROS_DOMAIN_ID set, resources, the
launch command, and a ConfigMap for ROS parameters.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass

import yaml

from . import labels as node_labels
from . import naming
from .quantities import format_cpu, format_memory
from .scheduler import DISCOVERY_CPU_MILLIS, DISCOVERY_MEMORY_BYTES, DiscoveryServer, Instance, Placement
from .spec import RosDeployment, RosModule

MANAGED_BY = "app.kubernetes.io/managed-by"
COMPONENT = "kuberos.io/component"
DEPLOYMENT = "kuberos.io/deployment"
MODULE = "kuberos.io/module"
INSTANCE = "kuberos.io/instance"
DISCOVERY_ID = "kuberos.io/discovery-id"
ROBOTS_ANNOTATION = "kuberos.io/robots"
REASON_ANNOTATION = "kuberos.io/placement-reason"
TIER_ANNOTATION = "kuberos.io/tier"
PARAMS_DIR = "/etc/kuberos"
PARAMS_FILE = "params.yaml"
RMW = "rmw_fastrtps_cpp"


@dataclass(frozen=True)
class RenderOptions:
    cluster_domain: str = "cluster.local"
    discovery_image: str = "ros:jazzy-ros-base"
    image_pull_policy: str = "IfNotPresent"


def discovery_server_list(servers: list[DiscoveryServer], cluster_domain: str) -> str:
    """ROS_DISCOVERY_SERVER value: addresses separated by ';', the position being the server id."""
    by_id = {s.server_id: s for s in servers}
    slots = []
    for server_id in range(max(by_id) + 1 if by_id else 0):
        server = by_id.get(server_id)
        slots.append(
            naming.discovery_server_address(server.namespace, server.server_id, server.port, cluster_domain) if server else ""
        )
    return ";".join(slots)


def _selector_and_tolerations(node: str, tier: str, robot: str | None) -> dict:
    spec = {"nodeSelector": {node_labels.HOSTNAME: node}}
    if tier == "onboard":
        toleration = {"key": node_labels.ROBOT_TAINT, "operator": "Exists", "effect": "NoSchedule"}
        if robot:
            toleration = {"key": node_labels.ROBOT_TAINT, "operator": "Equal", "value": robot, "effect": "NoSchedule"}
        spec["tolerations"] = [toleration]
    return spec


def _namespace(fleet: str, namespace: str) -> dict:
    return {
        "apiVersion": "v1",
        "kind": "Namespace",
        "metadata": {"name": namespace, "labels": {MANAGED_BY: "kuberos", node_labels.FLEET: fleet}},
    }


def _discovery_objects(server: DiscoveryServer, options: RenderOptions) -> list[dict]:
    labels = {
        MANAGED_BY: "kuberos",
        COMPONENT: "discovery-server",
        node_labels.FLEET: server.fleet,
        DISCOVERY_ID: str(server.server_id),
        INSTANCE: server.name,
    }
    selector = {COMPONENT: "discovery-server", DISCOVERY_ID: str(server.server_id)}
    pod_spec = {
        **_selector_and_tolerations(server.node, server.tier, None),
        "containers": [
            {
                "name": "discovery-server",
                "image": options.discovery_image,
                "imagePullPolicy": options.image_pull_policy,
                "command": [
                    "fast-discovery-server",
                    "-i",
                    str(server.server_id),
                    "-l",
                    "0.0.0.0",
                    "-p",
                    str(server.port),
                ],
                "ports": [{"name": "discovery", "containerPort": server.port, "protocol": "UDP"}],
                "resources": {
                    "requests": {"cpu": format_cpu(DISCOVERY_CPU_MILLIS), "memory": format_memory(DISCOVERY_MEMORY_BYTES)},
                    "limits": {"memory": format_memory(DISCOVERY_MEMORY_BYTES)},
                },
            }
        ],
    }
    deployment = {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {
            "name": server.name,
            "namespace": server.namespace,
            "labels": labels,
            "annotations": {REASON_ANNOTATION: server.reason, TIER_ANNOTATION: server.tier},
        },
        "spec": {
            "replicas": 1,
            "strategy": {"type": "Recreate"},
            "selector": {"matchLabels": selector},
            "template": {"metadata": {"labels": dict(labels)}, "spec": pod_spec},
        },
    }
    service = {
        "apiVersion": "v1",
        "kind": "Service",
        "metadata": {"name": server.name, "namespace": server.namespace, "labels": labels},
        "spec": {
            "selector": selector,
            "ports": [{"name": "discovery", "port": server.port, "targetPort": server.port, "protocol": "UDP"}],
        },
    }
    return [deployment, service]


def params_configmap_name(deployment: str, module: str) -> str:
    return naming.dns_label(deployment, module, "params")


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


def container_args(launch: tuple[str, ...]) -> list[str]:
    """One command line runs as it is; several run side by side and the module ends when one ends."""
    if len(launch) == 1:
        return shlex.split(launch[0])
    return ["/bin/bash", "-c", " & ".join(launch) + " & wait -n"]


def _module_deployment(
    dep: RosDeployment, module: RosModule, inst: Instance, discovery: str, base_labels: dict, options: RenderOptions
) -> dict:
    labels = {**base_labels, MODULE: module.name, INSTANCE: inst.name}
    if not inst.shared:
        labels[node_labels.ROBOT] = inst.robots[0]
    env = [
        {"name": "ROS_DISCOVERY_SERVER", "value": discovery},
        {"name": "RMW_IMPLEMENTATION", "value": RMW},
        {"name": "ROS_DOMAIN_ID", "value": str(dep.ros_domain_id)},
        {"name": "KUBEROS_FLEET", "value": dep.fleet},
        {"name": "KUBEROS_ROBOTS", "value": ",".join(inst.robots)},
        {"name": "KUBEROS_NODE_NAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}},
    ]
    if not inst.shared:
        env.append({"name": "KUBEROS_ROBOT_NAME", "value": inst.robots[0]})
    container = {
        "name": module.name,
        "image": module.image,
        "imagePullPolicy": options.image_pull_policy,
        "args": container_args(module.launch),
        "env": env,
        "resources": {
            "requests": {"cpu": format_cpu(inst.cpu_millis), "memory": format_memory(inst.memory_bytes)},
            "limits": {"memory": format_memory(inst.memory_bytes)},
        },
    }
    if inst.gpu:
        container["resources"]["requests"]["nvidia.com/gpu"] = str(inst.gpu)
        container["resources"]["limits"]["nvidia.com/gpu"] = str(inst.gpu)
    pod_spec = {**_selector_and_tolerations(inst.node, inst.tier, inst.robots[0]), "containers": [container]}
    if module.ros_parameters:
        env.append({"name": "KUBEROS_PARAMS_FILE", "value": f"{PARAMS_DIR}/{PARAMS_FILE}"})
        container["volumeMounts"] = [{"name": "ros-parameters", "mountPath": PARAMS_DIR, "readOnly": True}]
        pod_spec["volumes"] = [{"name": "ros-parameters", "configMap": {"name": params_configmap_name(dep.name, module.name)}}]
    env.extend({"name": name, "value": value} for name, value in sorted(module.env))
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
            },
        },
        "spec": {
            "replicas": 1,
            "strategy": {"type": "Recreate"},
            "selector": {"matchLabels": {INSTANCE: inst.name}},
            "template": {"metadata": {"labels": dict(labels)}, "spec": pod_spec},
        },
    }


_KIND_ORDER = {"Namespace": 0, "ConfigMap": 1, "Service": 2, "Deployment": 3}


def object_order(obj: dict) -> tuple:
    """Apply order: namespaces, then ConfigMaps, Services and Deployments, each by namespace and name."""
    return (_KIND_ORDER[obj["kind"]], obj["metadata"].get("namespace", ""), obj["metadata"]["name"])


def render_deployment(deployments: list[RosDeployment], placement: Placement, options: RenderOptions | None = None) -> list[dict]:
    """Every object the placement needs, ordered for applying (namespaces first)."""
    options = options or RenderOptions()
    by_name = {d.name: d for d in deployments}
    objects: list[dict] = []
    fleets = sorted(placement.discovery)
    for fleet in fleets:
        servers = placement.discovery[fleet]
        namespace = naming.fleet_namespace(fleet)
        objects.append(_namespace(fleet, namespace))
        for server in servers:
            objects.extend(_discovery_objects(server, options))
    addresses = {f: discovery_server_list(placement.discovery[f], options.cluster_domain) for f in fleets}
    modules = {(d.name, m.name): m for d in deployments for m in d.modules}
    seen_params = set()
    for inst in placement.instances:
        dep = by_name[inst.deployment]
        module = modules[(inst.deployment, inst.module)]
        base_labels = {
            **dict(dep.labels),
            MANAGED_BY: "kuberos",
            COMPONENT: "ros-module",
            DEPLOYMENT: dep.name,
            node_labels.FLEET: dep.fleet,
        }
        if module.ros_parameters and (dep.name, module.name) not in seen_params:
            seen_params.add((dep.name, module.name))
            objects.append(_params_configmap(dep, module, inst.namespace, base_labels))
        objects.append(_module_deployment(dep, module, inst, addresses[dep.fleet], base_labels, options))
    objects.sort(key=object_order)
    return objects
