"""RosDeployment: parsing and validation of the developer's one YAML file.

``load_rosdeployments(text, source)`` turns file text into validated ``RosDeployment`` objects
or raises ``SpecError`` listing every problem (file, line, field path, value, expectation).
``parse_rosdeployment(data, source)`` does the same for already-loaded data.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field

import jsonschema

from . import quantities
from .errors import Problem, SpecError, describe, did_you_mean
from .schema import API_VERSION, KIND, SCHEMA, TIERS
from .yaml_source import Document, format_path, load_documents

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
RESERVED_ENV = ("ROS_DISCOVERY_SERVER", "RMW_IMPLEMENTATION", "ROS_DOMAIN_ID")

_VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)


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


@dataclass(frozen=True)
class BridgeTopic:
    name: str
    type: str
    direction: str  # to_module | from_module


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

    @property
    def path(self) -> str:
        return f"rosModules[{self.index}]"


@dataclass(frozen=True)
class RosDeployment:
    name: str
    fleet: str
    robots: tuple[str, ...] | None
    modules: tuple[RosModule, ...]
    ros_domain_id: int = 0
    discovery_servers: int = 2
    discovery_port: int = 11811
    labels: tuple[tuple[str, str], ...] = ()
    source: str = "<spec>"
    lines: dict = field(default_factory=dict, compare=False, repr=False)

    def line_of(self, path: str) -> int | None:
        return self.lines.get(path)


def _parts(data, parts) -> tuple:
    """Path parts with list positions as ints and mapping keys as strings (``1: x`` is field '1')."""
    out, node = [], data
    for part in parts:
        if isinstance(node, list) and isinstance(part, int):
            out.append(part)
            node = node[part] if 0 <= part < len(node) else None
        else:
            out.append(str(part))
            node = node.get(part) if isinstance(node, dict) else None
    return tuple(out)


def _problem(doc: Document, parts: tuple, message: str) -> Problem:
    return Problem(doc.source, format_path(parts), message, doc.line_of(parts))


def _problems_of(error: jsonschema.ValidationError, doc: Document) -> list[Problem]:
    parts = _parts(doc.data, error.absolute_path)
    schema = error.schema if isinstance(error.schema, dict) else {}
    expected = schema.get("x-expected", "")
    value = error.instance
    if "propertyNames" in error.absolute_schema_path:
        return [_problem(doc, (*parts, str(value)), f"{describe(value)} is not a valid name; expected {expected}")]
    if error.validator == "additionalProperties" and isinstance(value, dict):
        allowed = sorted(schema.get("properties", {}))
        extras = sorted((k for k in value if k not in allowed), key=str)
        return [
            _problem(doc, (*parts, str(key)), f"unknown field{did_you_mean(key, allowed)} (allowed here: {', '.join(allowed)})")
            for key in extras
        ]
    if error.validator == "required":
        missing = error.message.split("'")[1] if "'" in error.message else error.message
        return [_problem(doc, parts, f"missing required field '{missing}'")]
    if error.validator == "uniqueItems":
        return [_problem(doc, parts, f"has repeated entries; expected {expected}")]
    return [_problem(doc, parts, f"{describe(value)} is not valid; expected {expected or error.message}")]


def _schema_problems(doc: Document) -> list[Problem]:
    problems = []
    seen = set()
    errors = sorted(_VALIDATOR.iter_errors(doc.data), key=lambda e: ([str(p) for p in e.absolute_path], e.validator))
    for error in errors:
        for problem in _problems_of(error, doc):
            # A value that is both of the wrong type and fails a pattern is reported once.
            if problem.path in seen and error.validator in ("pattern", "minimum", "type"):
                continue
            if (problem.path, problem.message) not in seen:
                problems.append(problem)
                seen.update([(problem.path, problem.message), problem.path])
    return problems


def _as_tuple(value) -> tuple:
    if value is None:
        return ()
    if isinstance(value, (list, tuple)):
        return tuple(value)
    return (value,)


def _tiers_for(module: dict, problems: list[Problem], doc: Document, index: int) -> tuple[str, ...]:
    requirements = module.get("requirements") or {}
    strategy = module.get("strategy", "dedicated")
    preference = module.get("preference")
    path = ("rosModules", index, "preference")
    if isinstance(preference, list):
        tiers = tuple(preference)
    else:
        tiers = FALLBACK_ORDER[preference or ("onboard" if requirements.get("onboard") else DEFAULT_PREFERENCE)]
    if requirements.get("onboard"):
        if preference is not None and "onboard" not in _as_tuple(preference)[:1]:
            problems.append(
                _problem(
                    doc,
                    path,
                    f"{describe(preference)} contradicts requirements.onboard: true; "
                    "expected preference onboard (or leave preference out)",
                )
            )
        tiers = ("onboard",)
    if strategy == "shared":
        if requirements.get("onboard") or (preference is not None and _as_tuple(preference) == ("onboard",)):
            problems.append(
                _problem(
                    doc,
                    ("rosModules", index, "strategy"),
                    "'shared' cannot run onboard (a robot's computer serves only that robot); "
                    "expected preference edge or cloud, or strategy dedicated",
                )
            )
        tiers = tuple(t for t in tiers if t != "onboard") or tiers
    return tiers


def _launch_lines(module: dict, problems: list[Problem], doc: Document, index: int) -> tuple[str, ...]:
    lines = _as_tuple(module["launch"])
    for number, line in enumerate(lines):
        path = ("rosModules", index, "launch") + ((number,) if isinstance(module["launch"], list) else ())
        try:
            if not shlex.split(line):
                raise ValueError("empty command")
        except ValueError as exc:
            problems.append(
                _problem(
                    doc,
                    path,
                    f"{describe(line)} is not a valid command line ({exc}); expected e.g. 'ros2 launch pkg file.launch.py'",
                )
            )
    return lines


def _semantic_module(module: dict, index: int, doc: Document, problems: list[Problem]) -> RosModule:
    requirements = module.get("requirements") or {}
    resources = module.get("resources") or {}
    base = ("rosModules", index)

    def problem(parts, message):
        problems.append(_problem(doc, base + parts, message))

    def quantity(section, key, parser, default):
        try:
            return parser(section.get(key, default))
        except ValueError as exc:
            section_name = "requirements" if section is requirements else "resources"
            problem((section_name, key), f"{describe(section.get(key))} is not valid; {exc}")
            return 0

    max_latency = None
    if "max_latency" in requirements:
        max_latency = quantity(requirements, "max_latency", quantities.parse_latency_ms, None)
    cpu = quantity(resources, "cpu", quantities.parse_cpu, DEFAULT_CPU)
    memory = quantity(resources, "memory", quantities.parse_memory, DEFAULT_MEMORY)
    if memory == 0 and "memory" in resources:
        problem(("resources", "memory"), "must be more than zero; expected e.g. '128Mi'")

    strategy = module.get("strategy", "dedicated")
    if "robotsPerInstance" in module and strategy != "shared":
        problem(("robotsPerInstance",), "only applies with strategy: shared; expected strategy: shared or no robotsPerInstance")
    per_instance = int(module.get("robotsPerInstance", DEFAULT_ROBOTS_PER_INSTANCE)) if strategy == "shared" else 1

    cluster = module.get("cluster", "")
    topics = (module.get("bridge") or {}).get("topics") or []
    if cluster and not topics:
        problem(("cluster",), "needs bridge.topics: the topics the module exchanges with the robots' side")
    if topics and not cluster:
        problem(("bridge",), "only applies with cluster (a third-party cluster); expected cluster or no bridge")
    if cluster and requirements.get("onboard"):
        problem(("cluster",), "contradicts requirements.onboard: true; a module runs onboard or in another cluster")
    if cluster and strategy == "shared":
        problem(("cluster",), "needs strategy dedicated: the bridge connects one instance per robot")
    seen_topics: dict[str, int] = {}
    for position, topic in enumerate(topics):
        if topic["name"] in seen_topics:
            problem(
                ("bridge", "topics", position, "name"),
                f"'{topic['name']}' is already bridged by bridge.topics[{seen_topics[topic['name']]}]; expected each topic once",
            )
        seen_topics.setdefault(topic["name"], position)

    env = module.get("env") or {}
    for name in env:
        if not isinstance(name, str):
            problem(("env", str(name)), f"{describe(name)} is not a valid name; expected a string of letters, digits and '_'")
        elif name in RESERVED_ENV:
            problem(("env", name), "is set by KubeROS (use rosDomainId and discovery instead); remove it")
        elif name.startswith("KUBEROS_"):
            problem(("env", name), "names starting with KUBEROS_ are reserved for KubeROS; rename it")

    return RosModule(
        name=module["name"],
        image=module["image"],
        launch=_launch_lines(module, problems, doc, index),
        tiers=_tiers_for(module, problems, doc, index),
        requirements=Requirements(
            onboard=bool(requirements.get("onboard", False)),
            max_latency_ms=max_latency,
            arch=tuple(_as_tuple(requirements.get("arch"))),
            devices=tuple(requirements.get("devices") or ()),
        ),
        resources=Resources(cpu, memory, int(resources.get("gpu", 0))),  # 2.0 is an integer to JSON Schema
        strategy=strategy,
        robots_per_instance=per_instance,
        env=tuple((str(k), _env_value(v)) for k, v in env.items()),
        ros_parameters=dict(module.get("rosParameters") or {}),
        index=index,
        cluster=cluster,
        bridge_topics=tuple(BridgeTopic(t["name"], t["type"], t["direction"]) for t in topics),
    )


def _env_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _parse_document(doc: Document) -> RosDeployment:
    data = doc.data
    problems = _schema_problems(doc)
    broken = {p.path for p in problems}
    modules = []
    names: dict[str, int] = {}
    raw_modules = data.get("rosModules") if isinstance(data, dict) else None
    for index, module in enumerate(raw_modules if isinstance(raw_modules, list) else []):
        prefix = f"rosModules[{index}]"
        if any(path == prefix or path.startswith(prefix + ".") or path.startswith(prefix + "[") for path in broken):
            continue  # already reported; semantic checks need a well-formed module
        if module["name"] in names:
            path = ("rosModules", index, "name")
            problems.append(
                _problem(
                    doc,
                    path,
                    f"'{module['name']}' is already the name of rosModules[{names[module['name']]}]; "
                    "expected a unique module name",
                )
            )
        names.setdefault(module["name"], index)
        modules.append(_semantic_module(module, index, doc, problems))
    if problems:
        raise SpecError(sorted(problems, key=lambda p: (p.line or 0, p.path)), title=f"{doc.source} is not a valid RosDeployment")
    metadata = data["metadata"]
    discovery = data.get("discovery") or {}
    selector = (metadata.get("robotSelector") or {}).get("robot")
    return RosDeployment(
        name=metadata["name"],
        fleet=metadata["targetFleet"],
        robots=tuple(selector) if selector else None,
        modules=tuple(modules),
        # JSON Schema counts 2.0 as an integer; the rest of the code wants real ints.
        ros_domain_id=int(data.get("rosDomainId", 0)),
        discovery_servers=int(discovery.get("servers", 2)),
        discovery_port=int(discovery.get("port", 11811)),
        labels=tuple(sorted((metadata.get("labels") or {}).items())),
        source=doc.source,
        lines={format_path(k): v for k, v in doc.lines.items()},
    )


def parse_rosdeployment(data, source: str = "<spec>", lines: dict | None = None) -> RosDeployment:
    """Validate one loaded spec (a dict) and return it as a ``RosDeployment``."""
    return _parse_document(Document(data, source, 0, lines or {}))


def load_rosdeployments(text: str, source: str = "<spec>") -> list[RosDeployment]:
    """Parse and validate every document of a spec file; all problems of all documents at once."""
    documents = [doc for doc in load_documents(text, source) if doc.data is not None]
    if not documents:
        raise SpecError([Problem(source, "", "no RosDeployment found; the file is empty")], title=f"{source} is not valid")
    deployments, problems = [], []
    for doc in documents:
        if len(documents) > 1:
            doc.source = f"{source} (document {doc.index + 1})"
        try:
            deployments.append(_parse_document(doc))
        except SpecError as exc:
            problems.extend(exc.problems)
    names: dict[str, str] = {}
    for deployment in deployments:
        if deployment.name in names:
            problems.append(
                Problem(
                    deployment.source,
                    "metadata.name",
                    f"'{deployment.name}' is already used by {names[deployment.name]}; expected a unique name",
                    deployment.line_of("metadata.name"),
                )
            )
        names.setdefault(deployment.name, deployment.source)
    if problems:
        raise SpecError(problems, title=f"{source} is not a valid RosDeployment")
    return deployments


def load_rosdeployment_file(path: str, display: str | None = None) -> list[RosDeployment]:
    """Read ``path`` and validate it; errors name ``display`` (the path as the user wrote it)."""
    display = display or path
    try:
        with open(path, "rb") as handle:
            raw = handle.read(2 * 1024 * 1024)
    except OSError as exc:
        raise SpecError(
            [Problem(display, "", f"cannot read the file: {exc.strerror or exc}")], title="cannot read the spec"
        ) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError([Problem(display, "", f"not UTF-8 text (byte {exc.start})")], title=f"{display} is not valid") from None
    return load_rosdeployments(text, display)


__all__ = [
    "API_VERSION",
    "KIND",
    "TIERS",
    "Requirements",
    "Resources",
    "RosDeployment",
    "RosModule",
    "load_rosdeployment_file",
    "load_rosdeployments",
    "parse_rosdeployment",
]
