"""The RosDeployment model: what a validated spec holds (modules, their requirements, resources, launch arguments,
parameter maps, registries, scaling policies, bridge topics) and the defaults a spec may leave out."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from .errors import Problem
from .pod_security import DEFAULT_USER
from .schema import KIND
from .validation import (
    problem,
)
from .yaml_source import Document, path_prefix

# A single preferred tier falls back to the others in this order.
FALLBACK_ORDER = {
    "onboard": ("onboard", "edge", "cloud"),
    "edge": ("edge", "cloud", "onboard"),
    "cloud": ("cloud", "edge", "onboard"),
}


DEFAULT_PREFERENCE = "edge"


DEFAULT_CPU = "100m"


DEFAULT_MEMORY = "128Mi"


DEFAULT_ROBOTS_PER_INSTANCE = 4


BATCH_KINDS = ("RosBatchJob", "BatchJob")  # batch.py reads these


MAX_QUANTITY = 2**63 - 1  # Kubernetes keeps quantities in 64-bit integers (cpu in millicores)


_UNITS = {"cpu": "millicores", "memory": "bytes", "max_latency": "milliseconds"}


@dataclass(frozen=True)
class Resources:
    cpu_millis: int
    memory_bytes: int
    gpu: int = 0


@dataclass(frozen=True)
class Requirements:
    onboard: bool = False
    max_latency_ms: float | None = None
    arch: tuple[str, ...] = ()
    devices: tuple[str, ...] = ()
    resource_groups: tuple[str, ...] = ()  # the deployment's resourceGroups: edge and cloud nodes must be in one


@dataclass(frozen=True)
class ParameterMap:
    """A parameter map (``parameterMaps``; the reference format's ``rosParamMap``), a ConfigMap of the fleet."""

    name: str
    type: str  # key-value | yaml
    values: tuple[tuple[str, str], ...] = ()  # key-value: each key and its value as text
    text: str = ""  # yaml: the file's text
    path: str = ""  # the file it was read from, as the spec wrote it ("" for inline data)

    @property
    def file_name(self) -> str:
        """The yaml map's file in its mount directory (and its key in the ConfigMap)."""
        return self.name if self.name.endswith((".yaml", ".yml")) else f"{self.name}.yaml"

    def value(self, key: str) -> str | None:
        return dict(self.values).get(key)


@dataclass(frozen=True)
class ImageRegistry:
    name: str
    pull_secret: str = ""
    pull_policy: str = ""


@dataclass(frozen=True)
class LaunchArgument:
    """``name:=value`` appended to the first launch line; a device's parameter is known once the instance is placed."""

    name: str
    value: str = ""
    device: str = ""  # with parameter: the value is this device's parameter on the instance's node
    parameter: str = ""
    map: str = ""  # with key: the value came from this key of this key-value parameter map
    key: str = ""


@dataclass(frozen=True)
class ScalingPolicy:
    """How the controller scales a shared module (docs/scaling.md); durations in seconds."""

    min_instances: int
    max_instances: int
    metric: str = "cpu"  # "cpu" or the name of a gauge the module serves in Prometheus format
    target: float = 0.8
    metrics_port: int = 9464
    scale_up_window_s: float = 0.0
    scale_down_window_s: float = 60.0
    drain_s: float = 15.0

    @property
    def uses_cpu(self) -> bool:
        return self.metric == "cpu"


@dataclass(frozen=True)
class BridgeTopic:
    name: str
    type: str
    direction: str  # to_module | from_module


@dataclass(frozen=True)
class DeclaredTopic:
    """A topic a module declares it publishes or subscribes (``topics``; ``kuberos.topics`` checks them)."""

    name: str  # as the spec wrote it; kuberos.topics.scoped gives the form compared across modules
    type: str
    direction: str  # publishes | subscribes
    reliability: str = "reliable"
    durability: str = "volatile"
    depth: int = 10
    deadline_ms: float | None = None  # None: no deadline (ROS's infinite)
    liveliness: str = "automatic"
    lease_ms: float | None = None  # the liveliness lease; None: infinite
    rate_min: float | None = None  # Hz
    rate_max: float | None = None
    external: bool = False  # subscribes: published outside the deployment
    position: int = 0  # its place in the module's list of that direction
    # the catalog entry it came from ('pnp-planner 0.2.0'); '' when the spec declares it
    origin: str = field(default="", compare=False)


@dataclass(frozen=True)
class RosModule:
    name: str
    image: str
    launch: tuple[str, ...]
    tiers: tuple[str, ...]
    requirements: Requirements
    resources: Resources
    strategy: str = "dedicated"
    robots_per_instance: int = 1
    env: tuple[tuple[str, str], ...] = ()
    ros_parameters: dict = field(default_factory=dict, compare=False)
    index: int = 0
    cluster: str = ""  # a registered third-party cluster; its topics cross the bridge
    bridge_topics: tuple[BridgeTopic, ...] = ()
    version: str = ""  # the catalog version it was resolved to; "" for a module that gives its image
    catalog_module: str = ""  # the catalog module it names (``module: <name>@<range>``)
    upgrade: str = "surge"  # surge | recreate (never two at once: modules that hold hardware)
    ros_distro: str = ""  # the catalog entry's rosDistro
    scaling: ScalingPolicy | None = None  # shared modules the controller scales
    env_from: tuple[str, ...] = ()  # key-value parameter maps given as environment
    launch_arguments: tuple[LaunchArgument, ...] = ()
    parameter_files: tuple[tuple[str, str], ...] = ()  # (yaml parameter map, mount directory)
    registry: ImageRegistry | None = None
    privileged: bool = False
    user: int = DEFAULT_USER  # the user ID its containers run as; 0 is root (pod_security)
    workspace: str = ""  # a ROS workspace's install directory, sourced before each launch line
    shell: bool = False  # each launch line runs with /bin/bash -c as written
    topics: tuple[DeclaredTopic, ...] = ()  # its declared ROS 2 interfaces

    @property
    def path(self) -> str:
        return f"rosModules[{self.index}]"

    @property
    def maps(self) -> tuple[str, ...]:
        """The parameter maps the module's containers read (environment and files), each once."""
        return tuple(dict.fromkeys((*self.env_from, *(m for m, _d in self.parameter_files))))


@dataclass(frozen=True)
class RosDeployment:
    name: str
    fleet: str
    robots: tuple[str, ...] | None
    modules: tuple[RosModule, ...]
    ros_domain_id: int = 0
    discovery_servers: int = 2
    discovery_port: int = 11811
    robot_servers: bool = True  # a discovery server on each robot computer that runs its onboard modules
    labels: tuple[tuple[str, str], ...] = ()
    developer: str = ""  # a development deployment: it runs on robots this developer holds in the pool
    source: str = "<spec>"
    lines: dict = field(default_factory=dict, compare=False, repr=False)
    rmw: str = "fastdds"  # fastdds | cyclonedds
    parameter_maps: tuple[ParameterMap, ...] = ()
    resource_groups: tuple[str, ...] = ()
    kind: str = KIND  # RosDeployment, or ApplicationDeployment (the reference format, translated)
    notes: tuple[str, ...] = field(default=(), compare=False)  # what the translation ignored or changed, and why
    files: tuple[tuple[str, str], ...] = field(default=(), compare=False, repr=False)  # (path, text) read for maps
    field_names: tuple[tuple[str, str], ...] = field(default=(), compare=False, repr=False)  # our path -> the spec's
    # Its document as the record keeps it (``document_text``), read with the rest of the file: every line at its number
    # in the file; '' when it was not read from a file's text.
    document: str = field(default="", compare=False, repr=False)

    def parameter_map(self, name: str) -> ParameterMap | None:
        return next((m for m in self.parameter_maps if m.name == name), None)

    @property
    def uses_robot_servers(self) -> bool:
        """Its onboard modules list a discovery server on their robot's computer (Fast DDS; docs/connectivity.md)."""
        return self.robot_servers and self.rmw == "fastdds"

    def field(self, path: str) -> str:
        """``path`` as the spec's own format names it (a reference-format spec's ``metadata.targetRobots[0]`` for
        ``metadata.robotSelector.robot[0]``)."""
        names = dict(self.field_names)
        prefix = path_prefix(path, names)
        return path if prefix is None else names[prefix] + path[len(prefix) :]

    def line_of(self, path: str) -> int | None:
        """The line of ``path``, else of the nearest field holding it (a translated spec knows its fields' lines)."""
        while path and path not in self.lines:
            path, cut = _LAST_FIELD.subn("", path)
            path = path if cut else ""
        return self.lines[path] if path else None


def _problem(doc: Document, parts: tuple, message: str) -> Problem:
    return problem(doc, parts, message)


_LAST_FIELD = re.compile(r"(\.[^.\[]*|\[\d+\])\Z")  # metadata.robotSelector.robot[0] -> metadata.robotSelector.robot


def _env_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
