"""RosDeployment: parsing and validation of the developer's one YAML file.

``load_rosdeployments(text, source)`` turns file text into validated ``RosDeployment`` objects
or raises ``SpecError`` listing every problem (file, line, field path, value, expectation).
``parse_rosdeployment(data, source)`` does the same for already-loaded data. Both take an optional
``catalog`` (``catalog.Catalog``) that resolves modules naming a catalog module instead of an image.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field, replace

from . import naming, quantities
from .catalog import Catalog, CatalogEntry
from .errors import Problem, SpecError, describe
from .pod_security import DEFAULT_USER
from .schema import API_VERSION, KIND, MAX_MODULES, MAX_MODULES_PER_FILE, SCHEMA, TIERS
from .spec_catalog import _catalog_problems, _resolve
from .spec_maps import _broken, _parameter_maps
from .spec_model import (
    _UNITS,
    BATCH_KINDS,
    DEFAULT_CPU,
    DEFAULT_MEMORY,
    DEFAULT_PREFERENCE,
    DEFAULT_ROBOTS_PER_INSTANCE,
    FALLBACK_ORDER,
    MAX_QUANTITY,
    BridgeTopic,
    ImageRegistry,
    LaunchArgument,
    ParameterMap,
    Requirements,
    Resources,
    RosDeployment,
    RosModule,
    ScalingPolicy,
    _env_value,
    _problem,
)
from .spec_names import name_clash_problems
from .third_party import yaml
from .topics import declaration_findings, declared
from .validation import (
    RESERVED_ENV,
    as_tuple,
    env_name_problem,
    image_reference_problem,
    label_key_problem,
    launch_problems,
    ros_parameter_problems,
    schema_problems,
    strict_validator,
)
from .yaml_source import Document, format_path, load_documents, read_text


@functools.cache
def _validator():
    """Built on first use, not at import: jsonschema may be missing where the core is only imported (third_party.py)."""
    return strict_validator(SCHEMA)


def _schema_problems(doc: Document) -> list[Problem]:
    return schema_problems(_validator(), doc)


_as_tuple = as_tuple


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
    problems.extend(launch_problems(module["launch"], doc, ("rosModules", index)))
    return _as_tuple(module["launch"])


@dataclass
class _Context:
    """What a module's fields refer to: the deployment's parameter maps, registries and resource groups."""

    maps: dict = field(default_factory=dict)
    unreadable: set = field(default_factory=set)  # maps already reported (their file cannot be used)
    registries: dict = field(default_factory=dict)
    resource_groups: tuple[str, ...] = ()
    reference: bool = False  # translated from the reference format: map keys that are no variable names are noted
    notes: list = field(default_factory=list)


ENV_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


_REFERENCE = re.compile(r"\{([^{}]*)\}")


DEVICE_PREFIX = "device:"


def _launch_argument(name: str, raw, ctx: _Context, shared: bool, problem) -> LaunchArgument | None:
    """One launch argument: a literal, '{map.key}' (resolved now) or '{device:<device>.<parameter>}' (at render: the
    device of the instance's node, else of its robot's computer)."""
    text = _env_value(raw)
    found = _REFERENCE.fullmatch(text.strip())
    if found is None:
        if "{" in text or "}" in text:
            problem(
                ("launchArguments", name),
                f"{describe(text)} is not valid; expected a value, '{{map.key}}' or '{{device:<device>.<parameter>}}'",
            )
            return None
        return LaunchArgument(name, text)
    inner = found.group(1).strip()
    if inner.startswith(DEVICE_PREFIX):
        device, _dot, parameter = inner[len(DEVICE_PREFIX) :].rpartition(".")
        if not device or not parameter:
            problem(("launchArguments", name), f"{describe(text)} is not valid; expected '{{device:<device>.<parameter>}}'")
            return None
        if shared:
            problem(
                ("launchArguments", name),
                "takes a device parameter, but a shared instance serves several robots; expected strategy dedicated",
            )
            return None
        return LaunchArgument(name, device=device, parameter=parameter)
    names = sorted((m for m in ctx.maps if inner.startswith(m + ".")), key=len, reverse=True)
    if not names and any(inner.startswith(m + ".") for m in ctx.unreadable):
        return None  # its map is reported already
    if not names:
        known = ", ".join(sorted(ctx.maps)) or "none"
        problem(("launchArguments", name), f"{describe(text)} names no parameter map; expected '{{map.key}}' of one of: {known}")
        return None
    pmap, key = ctx.maps[names[0]], inner[len(names[0]) + 1 :]
    if pmap.type != "key-value":
        problem(("launchArguments", name), f"parameter map {pmap.name} is a yaml file; expected a key-value map")
        return None
    value = pmap.value(key)
    if value is None:
        keys = ", ".join(k for k, _v in pmap.values) or "none"
        problem(("launchArguments", name), f"parameter map {pmap.name} has no key {key!r}; its keys: {keys}")
        return None
    return LaunchArgument(name, value, map=pmap.name, key=key)


def _map_of(name: str, kind: str, ctx: _Context, problem, parts: tuple) -> ParameterMap | None:
    pmap = ctx.maps.get(name)
    if pmap is None and name in ctx.unreadable:
        return None
    if pmap is None:
        problem(
            parts,
            f"'{name}' is not a parameter map; expected one of: {', '.join(sorted(ctx.maps)) or 'none (parameterMaps is empty)'}",
        )
    elif pmap.type != kind:
        problem(parts, f"parameter map {name} is {pmap.type}; expected a {kind} map")
        return None
    return pmap


def _module_extras(module: dict, ctx: _Context, problem) -> dict:
    """The fields of a module that refer to the deployment: environment and files from parameter maps, launch
    arguments, the image registry; and privileged, user, workspace and shell."""
    shared = module.get("strategy") == "shared"
    env_from = []
    for position, name in enumerate(module.get("envFrom") or ()):
        pmap = _map_of(name, "key-value", ctx, problem, ("envFrom", position))
        if pmap is None:
            continue
        env_from.append(name)
        for key, _value in pmap.values:
            why = env_name_problem(key) if ENV_NAME_RE.fullmatch(key) else "is not an environment variable name"
            if why and ctx.reference:
                reason = "KubeROS sets it" if key in RESERVED_ENV or key.startswith("KUBEROS_") else "not a variable name"
                ctx.notes.append(
                    f"module {module['name']}: key {key!r} of parameter map {name} is not an environment variable ({reason})"
                )
            elif why:
                problem(("envFrom", position), f"parameter map {name} key {key!r} {why}; expected keys that name variables")
    files = []
    for position, entry in enumerate(module.get("parameterFiles") or ()):
        if _map_of(entry["map"], "yaml", ctx, problem, ("parameterFiles", position, "map")) is not None:
            files.append((entry["map"], entry["mountPath"].rstrip("/") or "/"))
    arguments = []
    for name, raw in (module.get("launchArguments") or {}).items():
        argument = _launch_argument(name, raw, ctx, shared, problem)
        if argument is not None:
            arguments.append(argument)
    registry = None
    if "imageRegistry" in module:
        registry = ctx.registries.get(module["imageRegistry"])
        if registry is None:
            known = ", ".join(sorted(ctx.registries)) or "none (imageRegistries is empty)"
            problem(("imageRegistry",), f"'{module['imageRegistry']}' is not in imageRegistries; expected one of: {known}")
    else:
        registry = ctx.registries.get("default")
    return dict(
        env_from=tuple(env_from),
        launch_arguments=tuple(arguments),
        parameter_files=tuple(files),
        registry=registry,
        privileged=bool(module.get("privileged", False)),
        # a privileged container's powers are root's: privileged without a user named runs as root
        user=int(module.get("user", 0 if module.get("privileged") else DEFAULT_USER)),
        workspace=(module.get("workspace") or "").rstrip("/"),
        shell=bool(module.get("shell", False)),
    )


def _semantic_module(module: dict, index: int, doc: Document, problems: list[Problem], ctx: _Context | None = None) -> RosModule:
    ctx = ctx or _Context()
    requirements = module.get("requirements") or {}
    resources = module.get("resources") or {}
    base = ("rosModules", index)

    def problem(parts, message):
        problems.append(_problem(doc, base + parts, message))

    def quantity(section, key, parser, default):
        section_name = "requirements" if section is requirements else "resources"
        try:
            amount = parser(section.get(key, default))
        except ValueError as exc:
            problem((section_name, key), f"{describe(section.get(key))} is not valid; {exc}")
            return 0
        except OverflowError:  # the schema bounds every quantity far below; this keeps a traceback out regardless
            amount = MAX_QUANTITY + 1
        if amount > MAX_QUANTITY:
            problem(
                (section_name, key),
                f"{describe(section.get(key))} is too large for Kubernetes; expected at most {MAX_QUANTITY} {_UNITS[key]}",
            )
            return 0
        return amount

    max_latency = None
    if "max_latency" in requirements:
        max_latency = quantity(requirements, "max_latency", quantities.parse_latency_ms, None)
        if max_latency <= 0 and not any(p.path == format_path((*base, "requirements", "max_latency")) for p in problems):
            problem(
                ("requirements", "max_latency"),
                f"{describe(requirements['max_latency'])} is not more than zero; expected a latency such as '200 ms'",
            )
    why = image_reference_problem(module["image"])
    if why:
        problem(("image",), why)
    problems.extend(ros_parameter_problems(module.get("rosParameters") or {}, doc, (*base, "rosParameters")))
    cpu = quantity(resources, "cpu", quantities.parse_cpu, DEFAULT_CPU)
    memory = quantity(resources, "memory", quantities.parse_memory, DEFAULT_MEMORY)
    if memory == 0 and "memory" in resources and not any(p.path == format_path((*base, "resources", "memory")) for p in problems):
        problem(("resources", "memory"), "must be more than zero; expected e.g. '128Mi'")

    strategy = module.get("strategy", "dedicated")
    if "robotsPerInstance" in module and strategy != "shared":
        problem(("robotsPerInstance",), "only applies with strategy: shared; expected strategy: shared or no robotsPerInstance")
    per_instance = int(module.get("robotsPerInstance", DEFAULT_ROBOTS_PER_INSTANCE)) if strategy == "shared" else 1
    scaling = _scaling_policy(module, strategy, problem)

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
        why = env_name_problem(name)
        if why:
            problem(("env", str(name)), why)

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
            resource_groups=ctx.resource_groups,
        ),
        resources=Resources(cpu, memory, int(resources.get("gpu", 0))),  # 2.0 is an integer to JSON Schema
        strategy=strategy,
        robots_per_instance=per_instance,
        env=tuple((str(k), _env_value(v)) for k, v in env.items()),
        ros_parameters=dict(module.get("rosParameters") or {}),
        index=index,
        cluster=cluster,
        bridge_topics=tuple(BridgeTopic(t["name"], t["type"], t["direction"]) for t in topics),
        upgrade=module.get("upgrade") or ("recreate" if requirements.get("devices") else "surge"),
        scaling=scaling,
        topics=declared(module.get("topics")),
        **_module_extras(module, ctx, problem),
    )


def _scaling_policy(module: dict, strategy: str, problem) -> ScalingPolicy | None:
    """The module's scaling policy (the schema checked each field's shape), or None without one."""
    raw = module.get("scaling")
    if raw is None:
        return None
    if strategy != "shared":
        problem(("scaling",), "only applies with strategy: shared; expected strategy: shared or no scaling")
        return None
    low, high = int(raw.get("minInstances", 1)), int(raw["maxInstances"])
    if high < low:
        problem(("scaling", "maxInstances"), f"{high} is below minInstances {low}; expected at least {low}")
    metric = raw.get("metric", "cpu")
    if "target" in raw:
        target = float(raw["target"])
    elif metric == "cpu":
        target = 0.8
    else:
        problem(("scaling", "target"), f"is required with metric {metric}; expected the gauge's value per instance to keep")
        target = 1.0

    def seconds(key, default):
        return quantities.parse_latency_ms(raw[key]) / 1000.0 if key in raw else default

    return ScalingPolicy(
        min_instances=low,
        max_instances=max(high, low),
        metric=metric,
        target=target,
        metrics_port=int(raw.get("metricsPort", 9464)),
        scale_up_window_s=seconds("scaleUpWindow", 0.0),
        scale_down_window_s=seconds("scaleDownWindow", 60.0),
        drain_s=seconds("drainTime", 15.0),
    )


def _metadata_problems(doc: Document, broken: set[str]) -> list[Problem]:
    """Labels the collection owns, and a name KubeROS keeps for its own objects."""
    metadata = doc.data.get("metadata") if isinstance(doc.data, dict) else None
    if not isinstance(metadata, dict):
        return []
    problems = []
    name = metadata.get("name")
    if isinstance(name, str) and "metadata.name" not in broken:
        why = naming.reserved_name_problem(name)
        if why:
            problems.append(_problem(doc, ("metadata", "name"), why))
    if (
        metadata.get("developer")
        and "metadata.developer" not in broken
        and not (metadata.get("robotSelector") or {}).get("robot")
    ):
        problems.append(
            _problem(
                doc,
                ("metadata", "developer"),
                "needs metadata.robotSelector.robot: the robots the developer holds in "
                "the robot pool, which this development deployment runs on",
            )
        )
    labels = metadata.get("labels")
    for key in labels if isinstance(labels, dict) else ():
        why = label_key_problem(key)
        if why and f"metadata.labels.{key}" not in broken:
            problems.append(_problem(doc, ("metadata", "labels", key), f"{describe(key)} {why}"))
    return problems


def _registries(data: dict, doc: Document, problems: list[Problem]) -> dict:
    registries: dict[str, ImageRegistry] = {}
    for index, raw in enumerate(data.get("imageRegistries") or ()):
        if raw["name"] in registries:
            problems.append(
                _problem(doc, ("imageRegistries", index, "name"), f"'{raw['name']}' is already a registry; expected unique names")
            )
        registries.setdefault(raw["name"], ImageRegistry(raw["name"], raw.get("pullSecret", ""), raw.get("pullPolicy", "")))
    return registries


def _parse_document(doc: Document, catalog: Catalog | None = None, read_file=None, ctx: _Context | None = None) -> RosDeployment:
    if catalog is not None and not isinstance(catalog, Catalog):
        raise TypeError(f"catalog must be a Catalog or None, not {type(catalog).__name__}")
    data = doc.data
    problems = _schema_problems(doc)
    broken = {p.path for p in problems}
    files: list = []
    ctx = ctx or _Context()
    if isinstance(data, dict):
        ctx.maps = _parameter_maps(data, doc, broken, read_file, problems, files, ctx.unreadable)
        ctx.registries = _registries(data, doc, problems) if not _broken(broken, "imageRegistries") else {}
        ctx.resource_groups = tuple(data.get("resourceGroups") or ()) if not _broken(broken, "resourceGroups") else ()
    modules = []
    resolved: list[tuple[RosModule, CatalogEntry]] = []
    unresolved: set[str] = set()
    names: dict[str, int] = {}
    raw_modules = data.get("rosModules") if isinstance(data, dict) else None
    for index, module in enumerate(raw_modules if isinstance(raw_modules, list) else []):
        if _broken(broken, f"rosModules[{index}]"):
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
        if "module" not in module:
            modules.append(_semantic_module(module, index, doc, problems, ctx))
            continue
        found = _resolve(module, index, doc, catalog, problems)
        if found is None:
            unresolved.add(module["module"].partition("@")[0].strip())
            continue
        merged, entry = found
        semantic = _semantic_module(merged, index, doc, problems, ctx)
        own = set(module.get("topics") or ())  # the directions the spec declares; the others are the catalog's
        resolved_module = replace(
            semantic,
            topics=tuple(t if t.direction in own else replace(t, origin=entry.label) for t in semantic.topics),
            version=entry.version,
            catalog_module=entry.name,
            ros_distro=entry.ros_distro,
        )
        modules.append(resolved_module)
        resolved.append((resolved_module, entry))
    problems.extend(_catalog_problems(doc, resolved, unresolved))
    problems.extend(_topic_problems(doc, modules))
    problems.extend(_metadata_problems(doc, {p.path for p in problems}))
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
        robot_servers=bool(discovery.get("robotServers", True)),
        labels=tuple(sorted((metadata.get("labels") or {}).items())),
        developer=metadata.get("developer", ""),
        source=doc.source,
        lines={format_path(k): v for k, v in doc.lines.items()},
        rmw=data.get("rmw", "fastdds"),
        parameter_maps=tuple(ctx.maps.values()),
        resource_groups=ctx.resource_groups,
        notes=tuple(ctx.notes) + _security_notes(modules, metadata["targetFleet"]),
        files=tuple(files),
    )


def _topic_problems(doc: Document, modules: list[RosModule]) -> list[Problem]:
    """The declared topics that cannot match (``kuberos.topics``), each at its declaration, or at ``module`` with the
    catalog entry named when the catalog declares it: the first ``topics.MAX_FINDINGS``, then one line counting the
    others (after the last one listed)."""
    problems = []
    findings = declaration_findings(modules)
    for finding in findings.shown:
        module, topic = finding.module, finding.topic
        if topic.origin:
            parts = ("rosModules", module.index, "module")
            message = f"{finding.message} ({topic.direction} from the catalog's {topic.origin})"
        else:
            parts, message = ("rosModules", module.index, "topics", topic.direction, topic.position), finding.message
        problems.append(_problem(doc, parts, message))
    if findings.more:
        # At the place of the last one listed, so that it follows them once the problems are sorted by line.
        last = max(problems, key=lambda p: (p.line or 0, p.path))
        message = f"... and {findings.more} more problems of declared topics like these (the first {findings.limit} are listed)"
        problems.append(Problem(last.source, last.path, message, last.line))
    return problems


def _security_notes(modules, fleet: str) -> tuple[str, ...]:
    """What deploy says of modules whose pods the restricted Pod Security level does not admit, and why."""
    namespace = naming.fleet_namespace(fleet)
    notes = []
    for module in modules:
        if module.privileged:
            notes.append(
                f"module {module.name}: privileged: true; its pods pass only the privileged Pod Security level, "
                f"which namespace {namespace} then enforces"
            )
        elif module.user == 0:
            notes.append(
                f"module {module.name}: user: 0 runs it as root; its pods pass the baseline Pod Security level, not "
                f"restricted, which namespace {namespace} then enforces"
            )
    return tuple(notes)


def parse_rosdeployment(data, source: str = "<spec>", lines: dict | None = None, catalog: Catalog | None = None) -> RosDeployment:
    """Validate one loaded spec (a dict) and return it as a ``RosDeployment``.

    ``catalog`` resolves the modules that name a catalog module (``module: pnp-planner@^0.2``).
    """
    return _parse_any(Document(data, source, 0, lines or {}), catalog, None)


def _module_count_problems(documents: list[Document]) -> list[Problem]:
    """More modules than a deployment (``MAX_MODULES``) or a file (``MAX_MODULES_PER_FILE``) may hold: refused
    before the schema looks at them, so that the time a refusal takes stays bounded."""
    total = 0
    for doc in documents:
        modules = doc.data.get("rosModules") if isinstance(doc.data, dict) else None
        if not isinstance(modules, list):
            continue
        if len(modules) > MAX_MODULES:
            message = f"has {len(modules)} modules; expected at most {MAX_MODULES} in one RosDeployment"
            return [_problem(doc, ("rosModules",), message)]
        total += len(modules)
        if total > MAX_MODULES_PER_FILE:
            message = f"brings the file past {MAX_MODULES_PER_FILE} modules; expected at most {MAX_MODULES_PER_FILE} in one file"
            return [_problem(doc, ("rosModules",), message)]
    return []


def _parse_any(doc: Document, catalog: Catalog | None, read_file) -> RosDeployment:
    """One document in our format, or in the reference format (``kind: ApplicationDeployment``) translated."""
    from . import reference_format

    kind = doc.data.get("kind") if isinstance(doc.data, dict) else None
    if kind in BATCH_KINDS:
        message = f"'{kind}' is a batch job, not a deployment; run it with playbooks/batch.yml (docs/batch.md)"
        raise SpecError([Problem(doc.source, "kind", message, doc.line_of(("kind",)))], title=f"{doc.source} is a batch job")
    if kind != reference_format.KIND:
        return _parse_document(doc, catalog, read_file)
    translation = reference_format.translate(doc)
    if translation.problems:
        raise SpecError(translation.problems, title=f"{doc.source} is not a valid {reference_format.KIND}")
    ctx = _Context(reference=True, notes=translation.notes)
    try:
        parsed = _parse_document(translation.doc, catalog, read_file, ctx)
        return replace(parsed, kind=reference_format.KIND, field_names=translation.field_names)
    except SpecError as exc:
        raise SpecError([translation.rename(p) for p in exc.problems], title=exc.title) from None


def file_reader(spec_path: str, files: dict | None = None):
    """What a spec's ``parameterMaps[].path`` are read with: files relative to the spec file's directory (or, given
    ``files``, that mapping of the paths as the spec wrote them to their text: a deployment record's copy).
    Returns ``read(path) -> (display name, text)``; a file that cannot be read raises ``SpecError``."""
    import os

    base = os.path.dirname(os.path.abspath(spec_path)) if spec_path else ""

    def read(path: str) -> tuple[str, str]:
        if files is not None:
            if path not in files:
                raise SpecError([Problem(path, "", "is not among the files the record keeps")])
            return path, files[path]
        full = os.path.join(base, path)
        return full, read_text(full, full, "parameter file")

    return read


def document_text(doc: Document) -> str:
    """What a record keeps of a document: its text as written, preceded by blank lines so that every line keeps its
    number in the file, when that alone reads as the same data (it does unless a directive above it gives it its
    meaning); else its data written out again, its first line still where it was."""
    if doc.directives:
        return "\n" * (doc.line - 1) + yaml.safe_dump(doc.data, sort_keys=False, default_flow_style=False)
    return "\n" * (doc.line - 1) + doc.text + ("" if doc.text.endswith("\n") else "\n")


def load_rosdeployments(
    text: str, source: str = "<spec>", catalog: Catalog | None = None, read_file=None, documents: list[Document] | None = None
) -> list[RosDeployment]:
    """Parse and validate every document of a spec file; all problems of all documents at once. ``read_file``
    (``file_reader``) reads the files parameter maps name; without it a map must give its data inline. ``documents``
    are the file's documents when the caller has read them from ``text`` already (``load_documents``)."""
    documents = [doc for doc in (load_documents(text, source) if documents is None else documents) if doc.data is not None]
    if not documents:
        raise SpecError([Problem(source, "", "no RosDeployment found; the file is empty")], title=f"{source} is not valid")
    deployments, problems = [], []
    for doc in documents:
        if len(documents) > 1:
            doc.source = f"{source} (document {doc.index + 1})"
    too_many = _module_count_problems(documents)
    if too_many:
        raise SpecError(too_many, title=f"{source} is not a valid RosDeployment")
    for doc in documents:
        try:
            deployments.append(replace(_parse_any(doc, catalog, read_file), document=document_text(doc)))
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
    if not problems:
        problems.extend(name_clash_problems(deployments, lambda dep: dep.robots))
    if problems:
        raise SpecError(problems, title=f"{source} is not a valid RosDeployment")
    return deployments


def load_rosdeployment_file(path: str, display: str | None = None, catalog: Catalog | None = None) -> list[RosDeployment]:
    """Read ``path`` and validate it; errors name ``display`` (the path as the user wrote it)."""
    display = display or path
    text = read_text(path, display)
    return load_rosdeployments(text, display, catalog, file_reader(path))


__all__ = [
    "API_VERSION",
    "KIND",
    "TIERS",
    "Requirements",
    "Resources",
    "RosDeployment",
    "RosModule",
    "file_reader",
    "load_rosdeployment_file",
    "load_rosdeployments",
    "name_clash_problems",
    "parse_rosdeployment",
]
