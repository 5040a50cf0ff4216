"""The reference KubeROS format (``kind: ApplicationDeployment``, ``apiVersion: v1``) as a RosDeployment.

``translate(doc)`` turns one reference document into the document of a RosDeployment with the same meaning, so that
the same validation, placement and rendering serve both formats (docs/rosdeployment.md, "The reference format"):

- ``metadata.targetRobots`` becomes ``robotSelector.robot`` (empty or absent: every robot of the fleet);
  ``edgeResourceGroup`` becomes ``resourceGroups`` (``public``, the reference's default, restricts nothing);
  ``rmwImplementation`` becomes ``rmw``; ``rosVersion`` and ``appVersion`` are informational.
- A module's ``entrypoint[0]`` is its one launch line, run with ``/bin/bash -c`` as the reference runs it
  (``shell: true``), after sourcing ``sourceWs`` (default ``/workspace/install``); ``launchParameters`` are appended
  as ``name:=value``: ``{map.key}`` (lowercase) takes a key of the parameter map that the module's ``rosParameters``
  entry of that name (or the ``rosParamMap`` of that name) holds, ``{DEVICE.PARAM}`` (uppercase) the parameter the
  inventory gives the device (``sim-arm``'s ``robot-ip`` for ``{SIM_ARM.ROBOT_IP}``).
- ``rosParameters`` of type key-value become ``envFrom`` (every key a variable of the containers), of type yaml
  ``parameterFiles`` (mounted at ``mountPath``); ``rosParamMap`` becomes ``parameterMaps``, ``containerRegistry``
  ``imageRegistries`` and ``containerRegistryName`` ``imageRegistry``.
- ``requirements.latency`` is ``max_latency``, ``privileged`` (or ``privilege``) a privileged container,
  ``peripheral_devices`` (or ``peripheral``) ``requirements.devices``, ``nvidia: true`` one GPU.

Every field the translation ignores, and every choice it makes that a user might not expect, becomes a note; the
placeholders the reference parses but does not use are accepted. A problem found later, by the RosDeployment's own
validation, names the reference field (``aliases``), at its line.

Pure: no Ansible, no Kubernetes, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from .errors import Problem, describe
from .yaml_source import Document, format_path, path_prefix

KIND = "ApplicationDeployment"
API_VERSION = "v1"
DEFAULT_WORKSPACE = "/workspace/install"
DEFAULT_RESOURCE_GROUP = "public"
RMW = {"fastdds": "fastdds", "cyclonedds": "cyclonedds"}
RMW_VARIABLE = {"rmw_cyclonedds_cpp": "cyclonedds", "rmw_fastrtps_cpp": "fastdds"}
METADATA_NOTES = {
    "rosVersion": "informational: the module images bring their ROS distribution",
    "appVersion": "informational: versions of modules are tracked per image (and per catalog module)",
    "description": "informational",
}
REQUIREMENT_NOTES = {
    "dynamicRescheduling": "the controller re-places every module when its node fails or its link breaks max_latency",
    "containerRuntime": "the nodes' container runtime runs every module",
    "useBridge": "modules in a third-party cluster are given with `cluster:` (docs/bridge.md)",
}
MODULE_NOTES = {
    "lifecycleTopic": "a batch run ends when its lifecycle module exits; no topic is watched",
    "staticFiles": "static files are not supported; put them in the image or in a parameter map",
    "requiredLaunchParamList": "placeholder of the reference; launch arguments come from launchParameters",
}
TOP_NOTES = {
    "staticFileMap": "static files are not supported; put them in the image or in a parameter map",
    "plugins": "plugins (e.g. a second network interface) are not supported",
}
TOP_FIELDS = ("apiVersion", "kind", "metadata", "rosModules", "rosParamMap", "containerRegistry")
MODULE_FIELDS = (
    "name", "image", "entrypoint", "sourceWs", "containerRegistryName", "preference", "requirements",
    "launchParameters", "rosParameters",
)  # fmt: skip


@dataclass
class Translation:
    """The translated document, what the translation says about it, and where each of its fields came from."""

    doc: Document
    notes: list[str] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    aliases: dict[tuple, tuple] = field(default_factory=dict)  # our path -> the reference's path

    @property
    def field_names(self) -> tuple[tuple[str, str], ...]:
        """Each of our fields and the reference's field it came from, as formatted paths."""
        return tuple(sorted((format_path(ours), format_path(theirs)) for ours, theirs in self.aliases.items()))

    def rename(self, problem: Problem) -> Problem:
        """``problem`` (found on the translated document) naming the reference's field and its line."""
        by_path = {format_path(ours): theirs for ours, theirs in self.aliases.items()}
        prefix = path_prefix(problem.path, by_path)
        if prefix is None:
            return problem
        theirs = by_path[prefix]
        path = format_path(theirs) + problem.path[len(prefix) :]
        return replace(problem, path=path, line=problem.line or self.source.line_of(theirs))

    source: Document | None = None


class _Builder:
    def __init__(self, doc: Document):
        self.doc = doc
        self.out = Translation(Document({}, doc.source, doc.index, {}), source=doc)

    def note(self, parts: tuple, message: str) -> None:
        line = self.doc.line_of(parts)
        where = f"{self.doc.source}:{line}" if line else self.doc.source
        self.out.notes.append(f"{where}: {format_path(parts)}: {message}")

    def problem(self, parts: tuple, message: str) -> None:
        self.out.problems.append(Problem(self.doc.source, format_path(parts), message, self.doc.line_of(parts)))

    def alias(self, ours: tuple, theirs: tuple) -> None:
        self.out.aliases[ours] = theirs
        line = self.doc.line_of(theirs)
        if line is not None:
            self.out.doc.lines[ours] = line


def _mapping(builder: _Builder, value, parts: tuple, what: str) -> dict | None:
    if value is None:
        return {}
    if not isinstance(value, dict):
        builder.problem(parts, f"{describe(value)} is not valid; expected {what}")
        return None
    return value


def _list(builder: _Builder, value, parts: tuple, what: str) -> list | None:
    if value is None:
        return []
    if not isinstance(value, list):
        builder.problem(parts, f"{describe(value)} is not valid; expected {what}")
        return None
    return value


def _metadata(b: _Builder, raw: dict, out: dict) -> None:
    meta = _mapping(b, raw.get("metadata"), ("metadata",), "a mapping with name and targetFleet")
    if meta is None:
        return
    ours: dict = {}
    for key in ("name", "targetFleet"):
        if key in meta:
            ours[key] = meta[key]
            b.alias(("metadata", key), ("metadata", key))
    out["metadata"] = ours
    b.alias(("metadata",), ("metadata",))
    robots = meta.get("targetRobots")
    if robots not in (None, [], ""):
        ours["robotSelector"] = {"robot": robots}
        b.alias(("metadata", "robotSelector", "robot"), ("metadata", "targetRobots"))
    groups = meta.get("edgeResourceGroup")
    if groups not in (None, []):
        listed = groups if isinstance(groups, list) else [groups]
        if listed == [DEFAULT_RESOURCE_GROUP]:
            b.note(("metadata", "edgeResourceGroup"), "'public' (the default): every edge and cloud node the fleet may use")
        else:
            out["resourceGroups"] = [g for g in listed if g != DEFAULT_RESOURCE_GROUP] or listed
            b.alias(("resourceGroups",), ("metadata", "edgeResourceGroup"))
            b.note(
                ("metadata", "edgeResourceGroup"),
                "edge and cloud nodes must be in one of these groups (kuberos_resource_group in the inventory)",
            )
    if "rmwImplementation" in meta:
        rmw = meta["rmwImplementation"]
        if rmw not in RMW:
            b.problem(("metadata", "rmwImplementation"), f"{describe(rmw)} is not valid; expected fastdds or cyclonedds")
        else:
            out["rmw"] = RMW[rmw]
            b.alias(("rmw",), ("metadata", "rmwImplementation"))
    for key in meta:
        if key in METADATA_NOTES:
            b.note(("metadata", key), f"{describe(meta[key])} is {METADATA_NOTES[key]}")
        elif key not in ("name", "targetFleet", "targetRobots", "edgeResourceGroup", "rmwImplementation"):
            b.note(("metadata", key), "is not a field of the reference format; ignored")


def _param_maps(b: _Builder, raw: dict, out: dict) -> tuple[dict[str, str], dict[str, set]]:
    """rosParamMap as parameterMaps; returns each map's type by name, and the keys of those given inline."""
    maps = _list(b, raw.get("rosParamMap"), ("rosParamMap",), "a list of parameter maps")
    types: dict[str, str] = {}
    keys: dict[str, set] = {}
    if not maps:
        return types, keys
    out["parameterMaps"] = []
    for index, entry in enumerate(maps):
        theirs = ("rosParamMap", index)
        if not isinstance(entry, dict):
            b.problem(theirs, f"{describe(entry)} is not valid; expected a mapping with name, type and data or path")
            continue
        ours = {k: entry[k] for k in ("name", "type", "data", "path") if k in entry}
        for key in entry:
            if key not in ours:
                b.note((*theirs, key), "is not a field of a rosParamMap; ignored")
        position = len(out["parameterMaps"])
        out["parameterMaps"].append(ours)
        b.alias(("parameterMaps", position), theirs)
        if isinstance(entry.get("name"), str):
            types[entry["name"]] = entry.get("type")
            if isinstance(entry.get("data"), dict):
                keys[entry["name"]] = set(entry["data"])
    return types, keys


def _registries(b: _Builder, raw: dict, out: dict) -> None:
    registries = _list(b, raw.get("containerRegistry"), ("containerRegistry",), "a list of container registries")
    if not registries:
        return
    out["imageRegistries"] = []
    for index, entry in enumerate(registries):
        theirs = ("containerRegistry", index)
        if not isinstance(entry, dict):
            b.problem(theirs, f"{describe(entry)} is not valid; expected a mapping with name and imagePullSecretName")
            continue
        ours = {}
        for key, mine in (("name", "name"), ("imagePullSecretName", "pullSecret"), ("imagePullPolicy", "pullPolicy")):
            if entry.get(key) not in (None, ""):
                ours[mine] = entry[key]
                b.alias(("imageRegistries", len(out["imageRegistries"]), mine), (*theirs, key))
        for key in entry:
            if key not in ("name", "imagePullSecretName", "imagePullPolicy"):
                b.note((*theirs, key), "is not a field of a containerRegistry; ignored")
        b.alias(("imageRegistries", len(out["imageRegistries"])), theirs)
        out["imageRegistries"].append(ours)


def module_name(name):
    """A reference module's name as a RosDeployment's: lowercase, '_' as '-' (other characters stay, and are refused
    with the reason if they are still not a Kubernetes name)."""
    return name.lower().replace("_", "-") if isinstance(name, str) else name


def _is_zero(value) -> bool:
    text = str(value).strip().lower().removesuffix("ms").removesuffix("s").strip()
    try:
        return float(text) == 0
    except ValueError:
        return False


def _norm(name: str) -> str:
    return name.replace("_", "-")


class _Module:
    """One rosModules entry, translated into ``self.ours``."""

    def __init__(self, b: _Builder, raw: dict, index: int, map_types: dict[str, str], map_keys: dict[str, set]):
        self.b, self.raw, self.index, self.map_types, self.map_keys = b, raw, index, map_types, map_keys
        self.theirs = ("rosModules", index)
        self.ours: dict = {}
        self.requirements: dict = {}
        self.by_parameter_name: dict[str, str] = {}  # rosParameters[].name (normalised) -> its map

    def put(self, key: str, value, theirs: tuple) -> None:
        self.ours[key] = value
        self.b.alias(("rosModules", self.index, key), (*self.theirs, *theirs))

    def translate(self) -> dict:
        raw, b = self.raw, self.b
        if "image" in raw:
            self.put("image", raw["image"], ("image",))
        if "name" in raw:
            name = module_name(raw["name"])
            if name != raw["name"]:
                b.note((*self.theirs, "name"), f"the module is named {name!r} (a Kubernetes name: lowercase, '-' for '_')")
            self.put("name", name, ("name",))
        self.entrypoint()
        if "containerRegistryName" in raw:
            self.put("imageRegistry", raw["containerRegistryName"], ("containerRegistryName",))
        self.preference()
        self.requirements_()
        self.ros_parameters()
        self.launch_parameters()
        if self.requirements:
            self.ours["requirements"] = self.requirements
            b.alias(("rosModules", self.index, "requirements"), (*self.theirs, "requirements"))
        for key in raw:
            if key in MODULE_NOTES:
                b.note((*self.theirs, key), MODULE_NOTES[key])
            elif key not in MODULE_FIELDS:
                b.note((*self.theirs, key), "is not a field of a reference rosModule; ignored")
        return self.ours

    def entrypoint(self) -> None:
        raw, b = self.raw, self.b
        entry = raw.get("entrypoint")
        if isinstance(entry, str):
            entry = [entry]
        if not isinstance(entry, list) or not entry or not all(isinstance(e, str) for e in entry):
            b.problem(
                (*self.theirs, "entrypoint"),
                f"{describe(raw.get('entrypoint'))} is not valid; expected a list whose first item is the command line",
            )
            return
        self.put("launch", [entry[0]], ("entrypoint",))
        if len(entry) > 1:
            b.note((*self.theirs, "entrypoint"), f"only the first item runs, as in the reference; {len(entry) - 1} more ignored")
        self.ours["shell"] = True
        workspace = raw.get("sourceWs", DEFAULT_WORKSPACE)
        if isinstance(workspace, str) and workspace.strip():
            self.put("workspace", workspace.strip().rstrip("/") or "/", ("sourceWs",) if "sourceWs" in raw else ("entrypoint",))
        else:
            b.problem(
                (*self.theirs, "sourceWs"),
                f"{describe(workspace)} is not valid; expected a directory such as /workspace/install/",
            )

    def preference(self) -> None:
        raw = self.raw
        pref = raw.get("preference")
        if pref is None or pref == []:
            self.put("preference", "onboard", ("preference",) if "preference" in raw else ("name",))
            self.b.note((*self.theirs, "preference"), "not given: onboard (the reference's default) first, then edge and cloud")
            return
        listed = pref if isinstance(pref, list) else [pref]
        self.put("preference", list(dict.fromkeys(listed)), ("preference",))

    def requirements_(self) -> None:
        b = self.b
        theirs = (*self.theirs, "requirements")
        req = _mapping(b, self.raw.get("requirements"), theirs, "a mapping of requirements")
        if not req:
            return
        for key, value in req.items():
            where = (*theirs, key)
            if key == "latency":
                if _is_zero(value):
                    b.note(where, f"{describe(value)}: no latency requirement, as in the reference")
                    continue
                self.requirements["max_latency"] = value
                b.alias(("rosModules", self.index, "requirements", "max_latency"), where)
            elif key in ("privileged", "privilege"):
                self.put("privileged", value, ("requirements", key))
            elif key in ("peripheral_devices", "peripheral"):
                devices = value if isinstance(value, list) else [value]
                self.requirements["devices"] = list(dict.fromkeys([*self.requirements.get("devices", []), *devices]))
                b.alias(("rosModules", self.index, "requirements", "devices"), where)
            elif key == "nvidia":
                if value is True:
                    self.ours.setdefault("resources", {})["gpu"] = 1
                    b.alias(("rosModules", self.index, "resources", "gpu"), where)
                    b.note(where, "true: the module requests one GPU (nvidia.com/gpu)")
            elif key in REQUIREMENT_NOTES:
                b.note(where, f"{describe(value)} is accepted and not used: {REQUIREMENT_NOTES[key]}")
            else:
                b.note(where, "is not a requirement of the reference format; ignored")

    def ros_parameters(self) -> None:
        b = self.b
        theirs = (*self.theirs, "rosParameters")
        entries = _list(b, self.raw.get("rosParameters"), theirs, "a list of parameters (name, type, valueFrom)")
        for position, entry in enumerate(entries or ()):
            where = (*theirs, position)
            if not isinstance(entry, dict) or not isinstance(entry.get("valueFrom"), str):
                b.problem(where, f"{describe(entry)} is not valid; expected a mapping with name, type and valueFrom")
                continue
            source = entry["valueFrom"]
            if isinstance(entry.get("name"), str):
                self.by_parameter_name[_norm(entry["name"])] = source
            kind = entry.get("type") or self.map_types.get(source)
            if "type" not in entry and source not in self.map_types:
                known = ", ".join(sorted(self.map_types)) or "none"
                b.problem(
                    (*where, "valueFrom"), f"'{source}' names no rosParamMap (and type is not given); expected one of: {known}"
                )
            elif kind not in ("key-value", "yaml"):
                b.problem((*where, "type"), f"{describe(entry.get('type'))} is not valid; expected key-value or yaml")
            elif kind == "yaml":
                if not isinstance(entry.get("mountPath"), str):
                    b.problem((*where, "mountPath"), "is required for a yaml parameter; expected the directory to mount it in")
                    continue
                files = self.ours.setdefault("parameterFiles", [])
                b.alias(("rosModules", self.index, "parameterFiles", len(files)), where)
                b.alias(("rosModules", self.index, "parameterFiles", len(files), "map"), (*where, "valueFrom"))
                files.append({"map": source, "mountPath": entry["mountPath"]})
            else:
                env = self.ours.setdefault("envFrom", [])
                if source not in env:
                    b.alias(("rosModules", self.index, "envFrom", len(env)), (*where, "valueFrom"))
                    env.append(source)
                if "mountPath" in entry:
                    b.note((*where, "mountPath"), "a key-value parameter is given as environment, not mounted; ignored")

    def launch_parameters(self) -> None:
        b = self.b
        theirs = (*self.theirs, "launchParameters")
        params = _mapping(b, self.raw.get("launchParameters"), theirs, "a mapping of launch arguments to {map.key}")
        if not params:
            return
        arguments = {}
        for name, value in params.items():
            where = (*theirs, name)
            # `robot_ip: {SIM_ARM.ROBOT_IP}` is a YAML flow mapping: {'SIM_ARM.ROBOT_IP': None}
            if isinstance(value, dict) and len(value) == 1 and next(iter(value.values())) is None:
                value = next(iter(value))
            elif isinstance(value, str) and value.startswith("{") and value.endswith("}"):
                value = value[1:-1]
            else:
                if isinstance(value, (str, int, float, bool)):
                    arguments[name] = value
                    b.alias(("rosModules", self.index, "launchArguments", name), where)
                else:
                    b.problem(where, f"{describe(value)} is not valid; expected {{map.key}} or {{DEVICE.PARAMETER}}")
                continue
            reference = self.reference(str(value), where)
            if reference is not None:
                arguments[name] = reference
                b.alias(("rosModules", self.index, "launchArguments", name), where)
        if arguments:
            self.ours["launchArguments"] = arguments

    def reference(self, text: str, where: tuple) -> str | None:
        namespace, dot, key = text.strip().partition(".")
        if not dot or not namespace or not key:
            self.b.problem(where, f"'{{{text}}}' is not valid; expected {{map.key}} or {{DEVICE.PARAMETER}}")
            return None
        if namespace.isupper():
            device, parameter = namespace.lower().replace("_", "-"), key.lower().replace("_", "-")
            self.b.note(
                where,
                f"takes parameter {parameter} of device {device} from the inventory (kuberos_device_parameters of the "
                "module's node, else of its robot's computer)",
            )
            return f"{{device:{device}.{parameter}}}"
        if not namespace.islower():
            self.b.problem(where, f"'{{{text}}}' is neither a device (UPPERCASE) nor a parameter map (lowercase) reference")
            return None
        source = self.by_parameter_name.get(_norm(namespace))
        if source is not None and source not in self.map_types:
            known = ", ".join(sorted(self.map_types)) or "none"
            self.b.problem(
                where,
                f"'{{{text}}}': the module's rosParameters entry {namespace} takes valueFrom '{source}', which names no "
                f"rosParamMap; expected one of: {known}",
            )
            return None
        if source is None:
            source = (
                namespace if namespace in self.map_types else _norm(namespace) if _norm(namespace) in self.map_types else None
            )
        if source is None:
            self.b.problem(
                where,
                f"'{{{text}}}': {namespace} is neither a rosParameters entry of the module nor a rosParamMap; "
                "expected the name of one",
            )
            return None
        known = self.map_keys.get(source)
        if known is not None and key not in known:
            # The reference looks a launch parameter up in every key-value map the module attaches.
            for other in dict.fromkeys(self.by_parameter_name.values()):
                if key in self.map_keys.get(other, ()) and self.map_types.get(other) == "key-value":
                    self.b.note(where, f"key {key} is not in {source} but in {other}, which the module attaches: read there")
                    return f"{{{other}.{key}}}"
        return f"{{{source}.{key}}}"


def _rmw_from_maps(b: _Builder, out: dict) -> None:
    """A key-value map the modules use that sets RMW_IMPLEMENTATION chooses the middleware when metadata does not."""
    used = {m for module in out.get("rosModules", []) for m in module.get("envFrom", [])}
    for index, entry in enumerate(out.get("parameterMaps", [])):
        data = entry.get("data")
        if entry.get("name") not in used or not isinstance(data, dict) or "RMW_IMPLEMENTATION" not in data:
            continue
        chosen = RMW_VARIABLE.get(str(data["RMW_IMPLEMENTATION"]))
        theirs = ("rosParamMap", index, "data", "RMW_IMPLEMENTATION")
        if chosen is None:
            b.problem(
                theirs, f"{describe(data['RMW_IMPLEMENTATION'])} is not valid; expected rmw_fastrtps_cpp or rmw_cyclonedds_cpp"
            )
        elif "rmw" not in out:
            out["rmw"] = chosen
            b.alias(("rmw",), theirs)
            b.note(theirs, f"chooses {chosen} for the whole deployment (metadata.rmwImplementation is not given)")
        elif out["rmw"] != chosen:
            b.problem(theirs, f"chooses {chosen}, but metadata.rmwImplementation is {out['rmw']}; expected one middleware")


def translate(doc: Document) -> Translation:
    """The RosDeployment document of a reference ``ApplicationDeployment`` document, with notes and problems."""
    b = _Builder(doc)
    raw = doc.data
    out: dict = {"apiVersion": "kuberos.io/v1alpha1", "kind": "RosDeployment"}
    b.out.doc.data = out
    if raw.get("apiVersion") != API_VERSION:
        b.note(("apiVersion",), f"{describe(raw.get('apiVersion'))}: read as the reference format's {API_VERSION}")
    _metadata(b, raw, out)
    map_types, map_keys = _param_maps(b, raw, out)
    _registries(b, raw, out)
    modules = _list(b, raw.get("rosModules"), ("rosModules",), "a non-empty list of modules")
    if modules is not None and "rosModules" in raw:  # absent: the RosDeployment's validation says it is required
        out["rosModules"] = []
        b.alias(("rosModules",), ("rosModules",))
        for index, module in enumerate(modules):
            if not isinstance(module, dict):
                b.problem(
                    ("rosModules", index), f"{describe(module)} is not valid; expected a mapping with name, image and entrypoint"
                )
                continue
            out["rosModules"].append(_Module(b, module, index, map_types, map_keys).translate())
    _rmw_from_maps(b, out)
    for key in raw:
        if key in TOP_NOTES:
            b.note((key,), TOP_NOTES[key])
        elif key not in TOP_FIELDS:
            b.note((key,), "is not a field of the reference format; ignored")
    return b.out
