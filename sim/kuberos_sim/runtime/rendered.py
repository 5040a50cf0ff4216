"""A rendered directory read back: the Deployments, Services and ConfigMaps the runtime runs, as rendered.

``load_rendered(root)`` reads ``root/manifests/<namespace>/<kind>-<name>.yaml`` (what
``render_dir.plan_render_dir`` writes) and checks what the runtime relies on: every Deployment pinned to a
node (``nodeSelector: device.kuberos.io/hostname``), containers with a command, environment entries it can
resolve, and volumes it can materialize (configMap, emptyDir). Every problem is reported at once, naming
the file, the field and the reason (``SpecError``). Nothing is re-derived from the spec or the placement.
"""

from __future__ import annotations

import base64
import os
from dataclasses import dataclass, field

import yaml

from ._core import Problem, SpecError, labels, manifests, naming

MANIFEST_DIR = "manifests"
DISCOVERY_COMPONENTS = ("discovery-server", manifests.ROBOT_DISCOVERY)  # the fleet's, and a robot's own
# valueFrom.fieldRef paths the runtime can answer, as the kubelet would
FIELD_PATHS = ("spec.nodeName", "metadata.name", "metadata.namespace", "status.podIP", "status.hostIP")
_UNSAFE_PATH_CHARS = (",", ":", "\n", "\0")  # they would break the overlay mount options


@dataclass(frozen=True)
class Mount:
    """A container's volumeMount."""

    volume: str
    path: str
    read_only: bool


@dataclass(frozen=True)
class Container:
    name: str
    argv: tuple[str, ...]  # command + args, as rendered (args alone when the image's entrypoint would run them)
    env: tuple[dict, ...]  # the rendered env entries, resolved per host by resolve_env
    mounts: tuple[Mount, ...] = ()
    udp_ports: tuple[int, ...] = ()  # containerPorts with protocol UDP: bound once the process serves


@dataclass(frozen=True)
class Deployment:
    name: str
    namespace: str
    node: str
    component: str
    pod_labels: dict
    containers: tuple[Container, ...]
    volumes: dict  # volume name -> its rendered definition
    source: str  # the file, relative to the rendered directory
    replicas: int = 1

    @property
    def is_discovery_server(self) -> bool:
        return self.component in DISCOVERY_COMPONENTS


@dataclass(frozen=True)
class Service:
    name: str
    namespace: str
    selector: dict
    source: str
    local: bool = False  # internalTrafficPolicy Local: on each node, only a pod on that node answers


@dataclass
class RenderedDir:
    root: str
    deployments: dict[str, Deployment] = field(default_factory=dict)  # discovery servers first, then by name
    services: list[Service] = field(default_factory=list)
    configmaps: dict[tuple[str, str], dict] = field(default_factory=dict)  # (namespace, name) -> the object

    @property
    def nodes(self) -> list[str]:
        """Nodes any Deployment is pinned to, by name."""
        return sorted({d.node for d in self.deployments.values()})

    def service_nodes(self) -> list[tuple[Service, str]]:
        """Each Service that has a Deployment with the node that answers for it here: one Deployment per Service as
        rendered; the first node by name otherwise (a host stands for the cluster IP and for the DNS name)."""
        return [(svc, min(d.node for d in targets)) for svc, targets in self.service_targets() if targets]

    def service_links(self, namespace: str, address_of, node: str | None = None) -> dict[str, str]:
        """The service links the kubelet gives every container in ``namespace`` (of a pod on ``node``): each Service's
        ``<NAME>_SERVICE_HOST``, here the address (``address_of(node)``) of its node (``service_nodes``); a node-local
        Service's, the pod's own node when a Deployment of it runs there (none otherwise: nothing would answer)."""
        links = {}
        for svc, targets in self.service_targets():
            if svc.namespace != namespace or not targets:
                continue
            if svc.local:
                if node in {d.node for d in targets}:
                    links[naming.service_host_variable(svc.name)] = address_of(node)
                continue
            links[naming.service_host_variable(svc.name)] = address_of(min(d.node for d in targets))
        return links

    def service_targets(self) -> list[tuple[Service, list[Deployment]]]:
        """Each Service with its Deployments: same namespace, pod labels matching its selector."""
        return [
            (
                svc,
                [
                    d
                    for d in self.deployments.values()
                    if d.namespace == svc.namespace
                    and svc.selector
                    and all(d.pod_labels.get(k) == v for k, v in svc.selector.items())
                ],
            )
            for svc in self.services
        ]


def _problem(problems: list[Problem], source: str, path: str, message: str) -> None:
    problems.append(Problem(source, path, message))


def _read_objects(root: str, problems: list[Problem]) -> list[tuple[str, dict]]:
    """(file relative to root, object) for every YAML document under root/manifests."""
    top = os.path.join(root, MANIFEST_DIR)
    objects = []
    for dirpath, dirs, names in os.walk(top):
        dirs.sort()
        for name in sorted(names):
            if not name.endswith((".yaml", ".yml")):
                continue
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, root)
            try:
                with open(path, encoding="utf-8") as handle:
                    documents = list(yaml.safe_load_all(handle))
            except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
                _problem(problems, rel, "", f"cannot be read as YAML: {str(error).splitlines()[0] if str(error) else error}")
                continue
            for index, document in enumerate(d for d in documents if d is not None):
                if not isinstance(document, dict) or not isinstance(document.get("kind"), str):
                    _problem(problems, rel, f"document {index + 1}", "is not a Kubernetes object; expected a mapping with kind")
                    continue
                objects.append((rel, document))
    return objects


def _metadata(obj: dict, rel: str, problems: list[Problem]) -> tuple[str, str]:
    meta = obj.get("metadata") if isinstance(obj.get("metadata"), dict) else {}
    name, namespace = meta.get("name"), meta.get("namespace", "default")
    if not isinstance(name, str) or not name:
        _problem(problems, rel, "metadata.name", "is missing; expected the object's name")
    if not isinstance(namespace, str) or not namespace:
        _problem(problems, rel, "metadata.namespace", f"{namespace!r} is not valid; expected a namespace name")
    return str(name), str(namespace)


def _string_list(value, rel: str, path: str, problems: list[Problem]) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        _problem(problems, rel, path, f"{value!r} is not valid; expected a list of strings")
        return []
    return list(value)


def _env_entry(entry, rel: str, path: str, problems: list[Problem]) -> None:
    if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
        _problem(problems, rel, path, f"{entry!r} is not valid; expected a mapping with name and value or valueFrom")
        return
    if "value" in entry:
        if not isinstance(entry["value"], str):
            _problem(problems, rel, f"{path}.value", f"{entry['value']!r} is not valid; expected a string")
        return
    source = entry.get("valueFrom")
    field_path = (source or {}).get("fieldRef", {}).get("fieldPath") if isinstance(source, dict) else None
    if field_path in FIELD_PATHS:
        return
    if isinstance(source, dict) and isinstance(source.get("configMapKeyRef"), dict):
        return
    _problem(
        problems,
        rel,
        f"{path}.valueFrom",
        f"{source!r} is not supported by the simulator; expected a value, a fieldRef ({', '.join(FIELD_PATHS)}) "
        "or a configMapKeyRef",
    )


def _container(raw, rel: str, path: str, volumes: dict, problems: list[Problem]) -> Container | None:
    if not isinstance(raw, dict):
        _problem(problems, rel, path, f"{raw!r} is not valid; expected a container mapping")
        return None
    argv = _string_list(raw.get("command"), rel, f"{path}.command", problems) + _string_list(
        raw.get("args"), rel, f"{path}.args", problems
    )
    if not argv:
        _problem(problems, rel, path, "has neither command nor args; the simulator has no image entrypoint to run")
    env = raw.get("env") or []
    if not isinstance(env, list):
        _problem(problems, rel, f"{path}.env", f"{env!r} is not valid; expected a list")
        env = []
    for index, entry in enumerate(env):
        _env_entry(entry, rel, f"{path}.env[{index}]", problems)
    mounts = []
    for index, mount in enumerate(raw.get("volumeMounts") or []):
        where = f"{path}.volumeMounts[{index}]"
        target = mount.get("mountPath") if isinstance(mount, dict) else None
        if not isinstance(target, str) or not os.path.isabs(target) or any(c in target for c in _UNSAFE_PATH_CHARS):
            _problem(
                problems, rel, f"{where}.mountPath", f"{target!r} is not valid; expected an absolute path without ',' or ':'"
            )
            continue
        if os.path.normpath(target) == "/":
            _problem(problems, rel, f"{where}.mountPath", "'/' cannot be a mount path")
            continue
        if mount.get("subPath"):
            _problem(problems, rel, f"{where}.subPath", "is not supported by the simulator; expected whole-volume mounts")
            continue
        if mount.get("name") not in volumes:
            _problem(problems, rel, f"{where}.name", f"{mount.get('name')!r} names no volume of the pod")
            continue
        mounts.append(Mount(mount["name"], os.path.normpath(target), bool(mount.get("readOnly", False))))
    ports = tuple(
        int(p["containerPort"])
        for p in raw.get("ports") or []
        if isinstance(p, dict) and isinstance(p.get("containerPort"), int) and p.get("protocol", "TCP") == "UDP"
    )
    return Container(str(raw.get("name", "")), tuple(argv), tuple(env), tuple(mounts), ports)


def _volumes(pod: dict, rel: str, namespace: str, configmaps: dict, problems: list[Problem]) -> dict:
    volumes = {}
    for index, volume in enumerate(pod.get("volumes") or []):
        where = f"spec.template.spec.volumes[{index}]"
        if not isinstance(volume, dict) or not isinstance(volume.get("name"), str):
            _problem(problems, rel, where, f"{volume!r} is not valid; expected a mapping with name")
            continue
        if "emptyDir" in volume:
            volumes[volume["name"]] = volume
        elif isinstance(volume.get("configMap"), dict):
            ref = volume["configMap"].get("name")
            if (namespace, ref) not in configmaps and not volume["configMap"].get("optional"):
                _problem(problems, rel, f"{where}.configMap.name", f"{ref!r} is no rendered ConfigMap of namespace {namespace}")
            volumes[volume["name"]] = volume
        else:
            kinds = sorted(k for k in volume if k != "name")
            _problem(
                problems, rel, where, f"volume type {', '.join(kinds) or 'none'} is not supported; expected configMap or emptyDir"
            )
    return volumes


def _deployment(obj: dict, rel: str, configmaps: dict, problems: list[Problem]) -> Deployment | None:
    name, namespace = _metadata(obj, rel, problems)
    template = ((obj.get("spec") or {}).get("template") or {}) if isinstance(obj.get("spec"), dict) else {}
    pod = template.get("spec") if isinstance(template, dict) else None
    if not isinstance(pod, dict):
        _problem(problems, rel, "spec.template.spec", "is missing; expected the pod template")
        return None
    node = (pod.get("nodeSelector") or {}).get(labels.HOSTNAME)
    if not isinstance(node, str) or not node:
        _problem(
            problems, rel, f"spec.template.spec.nodeSelector.{labels.HOSTNAME}", "is missing; the Deployment is pinned to no node"
        )
    volumes = _volumes(pod, rel, namespace, configmaps, problems)
    raw_containers = pod.get("containers")
    if not isinstance(raw_containers, list) or not raw_containers:
        _problem(problems, rel, "spec.template.spec.containers", "is missing or empty; expected at least one container")
        raw_containers = []
    containers = [
        _container(c, rel, f"spec.template.spec.containers[{i}]", volumes, problems) for i, c in enumerate(raw_containers)
    ]
    pod_labels = (template.get("metadata") or {}).get("labels") or {}
    replicas = (obj.get("spec") or {}).get("replicas", 1)
    return Deployment(
        name=name,
        namespace=namespace,
        node=str(node),
        component=str(pod_labels.get(labels.COMPONENT, "")),
        pod_labels=dict(pod_labels),
        containers=tuple(c for c in containers if c is not None),
        volumes=volumes,
        source=rel,
        replicas=replicas if isinstance(replicas, int) else 1,
    )


def parse_deployment(obj: dict, configmaps: dict, source: str = "<added>") -> Deployment:
    """One rendered Deployment object, checked as ``load_rendered`` checks those of a directory."""
    problems: list[Problem] = []
    deployment = _deployment(obj, source, configmaps, problems)
    if problems or deployment is None:
        raise SpecError(problems, title=f"{source} is not a Deployment the runtime can run")
    return deployment


def load_rendered(root: str) -> RenderedDir:
    """The rendered directory's Deployments, Services and ConfigMaps; ``SpecError`` with every problem otherwise."""
    root = os.path.abspath(root)
    title = f"{root} is not a rendered KubeROS directory"
    if not os.path.isdir(root):
        raise SpecError([Problem(root, "", "does not exist or is not a directory")], title=title)
    if not os.path.isdir(os.path.join(root, MANIFEST_DIR)):
        raise SpecError(
            [Problem(root, MANIFEST_DIR, "is missing; expected manifests/<namespace>/<kind>-<name>.yaml")], title=title
        )
    problems: list[Problem] = []
    objects = _read_objects(root, problems)
    rendered = RenderedDir(root)
    for rel, obj in objects:
        if obj["kind"] == "ConfigMap":
            name, namespace = _metadata(obj, rel, problems)
            rendered.configmaps[(namespace, name)] = obj
    deployments = []
    for rel, obj in objects:
        if obj["kind"] == "Deployment":
            deployment = _deployment(obj, rel, rendered.configmaps, problems)
            if deployment is not None:
                deployments.append(deployment)
        elif obj["kind"] == "Service":
            name, namespace = _metadata(obj, rel, problems)
            spec = obj.get("spec") or {}
            selector = spec.get("selector") or {}
            local = spec.get("internalTrafficPolicy") == "Local"
            rendered.services.append(Service(name, namespace, dict(selector) if isinstance(selector, dict) else {}, rel, local))
    names = [d.name for d in deployments]
    for d in deployments:
        if names.count(d.name) > 1:
            _problem(
                problems, d.source, "metadata.name", f"'{d.name}' names Deployments in two namespaces; expected unique names"
            )
    if not deployments and not problems:
        _problem(problems, root, MANIFEST_DIR, "holds no Deployment; nothing to run")
    if problems:
        raise SpecError(problems, title=title)
    for deployment in sorted(deployments, key=lambda d: (not d.is_discovery_server, d.name)):
        rendered.deployments[deployment.name] = deployment
    return rendered


def configmap_files(configmap: dict, volume: dict) -> dict[str, bytes]:
    """Relative file path -> content of a configMap volume: every key, or the volume's items."""
    data = {k: str(v).encode() for k, v in (configmap.get("data") or {}).items()}
    data.update({k: base64.b64decode(v) for k, v in (configmap.get("binaryData") or {}).items()})
    items = volume.get("configMap", {}).get("items")
    if not items:
        return data
    return {item["path"]: data[item["key"]] for item in items if item.get("key") in data}


def resolve_env(
    container: Container, deployment: Deployment, pod_ip: str, configmaps: dict, services: dict[str, str] | None = None
) -> dict[str, str]:
    """The container's environment as the kubelet would set it on ``deployment.node`` at ``pod_ip``: ``$(NAME)`` in a
    value expanded from the entries before it and ``services`` (the service links of the pod's namespace, variable ->
    value: ``RenderedDir.service_links``)."""
    fields = {
        "spec.nodeName": deployment.node,
        "metadata.name": f"{deployment.name}-sim",
        "metadata.namespace": deployment.namespace,
        "status.podIP": pod_ip,
        "status.hostIP": pod_ip,
    }
    env: dict[str, str] = {}
    for entry in container.env:
        if "value" in entry:
            env[entry["name"]] = manifests.expand_references(entry["value"], {**(services or {}), **env})
            continue
        source = entry["valueFrom"]
        if "fieldRef" in source:
            env[entry["name"]] = fields[source["fieldRef"]["fieldPath"]]
            continue
        ref = source["configMapKeyRef"]
        data = (configmaps.get((deployment.namespace, ref.get("name"))) or {}).get("data") or {}
        if ref.get("key") in data:
            env[entry["name"]] = str(data[ref["key"]])
        elif not ref.get("optional"):
            raise SpecError(
                [Problem(deployment.source, f"env {entry['name']}", f"configMapKeyRef {ref!r} names no rendered key")],
                title="an environment entry cannot be resolved",
            )
    return env
