"""The software catalog: the ROS 2 modules a site may deploy, each in several versions.

A catalog is a directory of YAML files (``*.yml`` and ``*.yaml``, read in sorted order, each with
one or more documents) or a single file; by default ``inventories/<site>/catalog/`` (the variable
``kuberos_catalog``). Each document::

    apiVersion: kuberos.io/v1alpha1
    kind: RosModuleCatalog
    modules:
    - name: pnp-planner
      description: OMPL motion planner
      versions:
      - version: 0.2.0
        image: ghcr.io/kuberos/pnp-planner:0.2.0
        launch: [python3 -m kuberos_pnp.planner]
        ...

``load_catalog(path)`` validates every file (JSON Schema, then versions, image references, digests,
dependencies, quantities and command lines) and returns a ``Catalog`` or raises one ``SpecError``
listing every problem with file, line and field. A RosDeployment names a catalog module with
``module: pnp-planner@^0.2`` (``spec.py`` resolves it); ``Catalog.to_dict()`` / ``Catalog.from_dict()``
keep the entries a deployment used in its record. The format is documented in ``docs/software.md``.
"""

from __future__ import annotations

import copy
import functools
import os
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

from . import quantities
from .errors import Problem, SpecError, describe, did_you_mean
from .schema import (
    API_VERSION,
    DNS_LABEL,
    ENV,
    IMAGE,
    LAUNCH,
    PREFERENCE,
    REQUIREMENTS,
    RESOURCES,
    ROS_PARAMETERS,
    TOPICS,
    UPGRADE,
)
from .semver import MAX_LENGTH, Version, parse_range, parse_version
from .validation import (
    as_tuple,
    env_name_problem,
    image_reference_problem,
    launch_problems,
    problem,
    ros_parameter_problems,
    schema_problems,
    strict_validator,
)
from .yaml_source import MAX_DEPTH, MAX_NODES, Document, format_path, load_documents, read_text, yaml_files

CATALOG_KIND = "RosModuleCatalog"
DEFAULT_DIRECTORY = "catalog"  # inside the inventory: inventories/<site>/catalog/
MAX_FILES = 1000
DIGEST = r"^(sha256:[0-9a-f]{64}|sha512:[0-9a-f]{128})$"
ROS_DISTRO = r"^[a-z][a-z0-9_-]*$"
ARCH = r"^[A-Za-z0-9]([-A-Za-z0-9_.]*[A-Za-z0-9])?$"
INTERFACE = r"^[A-Za-z][A-Za-z0-9_]*$"

_MAX_IMAGE = 255 + 1 + 128

VERSION_SCHEMA = {
    "type": "object",
    "x-expected": "a mapping with version, image and launch",
    "additionalProperties": False,
    "required": ["version", "image", "launch"],
    "properties": {
        "version": {
            "type": "string",
            "minLength": 1,
            "maxLength": MAX_LENGTH,
            "description": "Semantic version (MAJOR.MINOR.PATCH[-prerelease][+build]), unique in the module.",
            "x-expected": "a semantic version string such as '0.2.0' (quote versions YAML reads as numbers)",
        },
        "image": {
            **IMAGE,
            "maxLength": _MAX_IMAGE,
            "description": "Container image of this version, with its tag; the digest goes in 'digest'.",
        },
        "digest": {
            "type": "string",
            "pattern": DIGEST,
            "description": "Content digest of the image; deployments then pull image@digest.",
            "x-expected": "a digest such as 'sha256:' followed by 64 lowercase hex digits",
        },
        "launch": LAUNCH,
        "rosDistro": {
            "type": "string",
            "pattern": ROS_DISTRO,
            "maxLength": 40,
            "description": "The ROS 2 distribution the image is built for; one per deployment.",
            "x-expected": "a ROS 2 distribution such as 'jazzy' or 'humble'",
        },
        "architectures": {
            "type": "array",
            "minItems": 1,
            "uniqueItems": True,
            "items": {"type": "string", "pattern": ARCH, "maxLength": 63, "x-expected": "an architecture such as 'amd64'"},
            "description": "CPU architectures the image is built for; modules run only on nodes of these.",
            "x-expected": "a non-empty list of distinct architectures such as [amd64, arm64]",
        },
        "preference": PREFERENCE,
        "requirements": REQUIREMENTS,
        "resources": RESOURCES,
        "rosParameters": ROS_PARAMETERS,
        "env": ENV,
        "dependencies": {
            "type": "object",
            "propertyNames": {
                "type": "string",
                "pattern": DNS_LABEL,
                "maxLength": 40,
                "x-expected": "the name of a catalog module",
            },
            "additionalProperties": {
                "type": "string",
                "minLength": 1,
                "maxLength": MAX_LENGTH,
                "x-expected": "a version range string such as '>=0.1.0 <1.0.0' or '^0.2'",
            },
            "description": "Other catalog modules this version needs in the same deployment, with version ranges.",
            "x-expected": "a mapping of catalog module names to version ranges",
        },
        "interfaces": {
            "type": "object",
            "propertyNames": {
                "type": "string",
                "pattern": INTERFACE,
                "maxLength": 100,
                "x-expected": "an interface name such as 'pnp_msgs'",
            },
            "additionalProperties": {
                "type": "integer",
                "minimum": 0,
                "maximum": 1000000,
                "x-expected": "a whole number from 0 to 1000000",
            },
            "description": "Message interfaces this version speaks, with their versions; one version per deployment.",
            "x-expected": "a mapping of interface names to whole numbers",
        },
        "topics": TOPICS,
        "upgrade": UPGRADE,
    },
}

MODULE_SCHEMA = {
    "type": "object",
    "x-expected": "a mapping with name and versions",
    "additionalProperties": False,
    "required": ["name", "versions"],
    "properties": {
        "name": {
            "type": "string",
            "pattern": DNS_LABEL,
            "maxLength": 40,
            "description": "Module name, unique in the catalog; specs write it in 'module: <name>@<range>'.",
            "x-expected": "a name of at most 40 lowercase letters, digits and '-', such as 'pnp-planner'",
        },
        "description": {
            "type": "string",
            "maxLength": 2000,
            "description": "What the module does.",
            "x-expected": "a string of at most 2000 characters",
        },
        "versions": {
            "type": "array",
            "minItems": 1,
            "items": VERSION_SCHEMA,
            "x-expected": "a non-empty list of versions",
        },
    },
}

CATALOG_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://kuberos.io/schemas/rosmodulecatalog-v1alpha1.json",
    "title": CATALOG_KIND,
    "description": "ROS 2 modules, each in several versions, that RosDeployments name with 'module: <name>@<range>'.",
    "type": "object",
    "x-expected": "a mapping with apiVersion, kind and modules",
    "additionalProperties": False,
    "required": ["apiVersion", "kind", "modules"],
    "properties": {
        "apiVersion": {"const": API_VERSION, "x-expected": f"'{API_VERSION}'"},
        "kind": {"const": CATALOG_KIND, "x-expected": f"'{CATALOG_KIND}'"},
        "modules": {"type": "array", "items": MODULE_SCHEMA, "x-expected": "a list of modules"},
    },
}


@functools.cache
def _validator():
    """Built on first use, not at import: jsonschema may be missing where the core is only imported (third_party.py)."""
    return strict_validator(CATALOG_SCHEMA)


@dataclass(frozen=True)
class CatalogEntry:
    """One version of one catalog module, as written in the catalog (mappings kept raw)."""

    name: str
    version: str
    image: str
    digest: str = ""
    launch: tuple[str, ...] = ()
    ros_distro: str = ""
    architectures: tuple[str, ...] = ()
    preference: str | tuple[str, ...] | None = None
    requirements: dict = field(default_factory=dict, hash=False)
    resources: dict = field(default_factory=dict, hash=False)
    ros_parameters: dict = field(default_factory=dict, hash=False)
    env: dict = field(default_factory=dict, hash=False)
    dependencies: tuple[tuple[str, str], ...] = ()
    interfaces: tuple[tuple[str, int], ...] = ()
    topics: dict = field(default_factory=dict, hash=False)  # publishes and subscribes, as written
    upgrade: str = ""  # "" when the catalog does not say: recreate with requirements.devices, else surge
    source: str = ""
    line: int | None = None
    description: str = ""

    @property
    def image_ref(self) -> str:
        """The image to pull: ``image@digest`` when a digest is given."""
        return f"{self.image}@{self.digest}" if self.digest else self.image

    @property
    def semver(self) -> Version:
        return parse_version(self.version)

    @property
    def label(self) -> str:
        return f"{self.name} {self.version}"

    def to_dict(self) -> dict:
        """The version entry as the catalog file writes it, plus where it came from."""
        data: dict = {"version": self.version, "image": self.image}
        if self.digest:
            data["digest"] = self.digest
        data["launch"] = list(self.launch)
        optional = (
            ("rosDistro", self.ros_distro),
            ("architectures", list(self.architectures)),
            ("preference", list(self.preference) if isinstance(self.preference, tuple) else self.preference),
            ("requirements", copy.deepcopy(self.requirements)),
            ("resources", copy.deepcopy(self.resources)),
            ("rosParameters", copy.deepcopy(self.ros_parameters)),
            ("env", dict(self.env)),
            ("dependencies", dict(self.dependencies)),
            ("interfaces", dict(self.interfaces)),
            ("topics", copy.deepcopy(self.topics)),
            ("upgrade", self.upgrade),
        )
        data.update((key, value) for key, value in optional if value not in (None, "", [], {}))
        data["source"] = self.source
        data["line"] = self.line
        return data


class Catalog:
    """The catalog's entries by module name, each module's versions in ascending order."""

    def __init__(self, entries: Iterable[CatalogEntry] = (), source: str = "", missing: bool = False):
        self.source = source
        self.missing = missing  # no catalog at ``source``
        grouped: dict[str, list[CatalogEntry]] = {}
        for entry in entries:
            grouped.setdefault(entry.name, []).append(entry)
        self._entries = {name: tuple(sorted(group, key=lambda e: e.semver)) for name, group in sorted(grouped.items())}

    def __repr__(self) -> str:
        count = sum(len(v) for v in self._entries.values())
        return f"Catalog({self.source!r}, {len(self._entries)} modules, {count} versions{', missing' if self.missing else ''})"

    def __eq__(self, other) -> bool:
        if not isinstance(other, Catalog):
            return NotImplemented
        return (self.source, self.missing, self._entries) == (other.source, other.missing, other._entries)

    __hash__ = None  # mutable-looking container; compare, do not hash

    def where(self) -> str:
        """How messages name the catalog."""
        if self.missing:
            return f"no catalog at {self.source}"
        return f"the catalog {self.source}" if self.source else "the catalog"

    def names(self) -> list[str]:
        return list(self._entries)

    def all_entries(self) -> list[CatalogEntry]:
        return [entry for group in self._entries.values() for entry in group]

    def entries(self, name: str) -> list[CatalogEntry]:
        """The versions of module ``name``, lowest first (empty for an unknown module)."""
        return list(self._entries.get(name, ()))

    def get(self, name: str, version: str) -> CatalogEntry | None:
        """The entry of exactly this version (equal by SemVer precedence), or None."""
        try:
            wanted = parse_version(version)
        except ValueError:
            return None
        return next((e for e in self._entries.get(name, ()) if e.semver == wanted), None)

    def unknown_module(self, name: str) -> str:
        """Why ``name`` cannot be looked up: the catalog is missing, empty, or has no such module."""
        if self.missing:
            return f"'{name}' is not in the catalog: {self.where()}"
        if not self._entries:
            return f"'{name}' is not in the catalog: {self.where()} has no modules"
        names = list(self._entries)
        shown = ", ".join(names[:20]) + (f", ... ({len(names)} in all)" if len(names) > 20 else "")
        return f"'{name}' is not a module of {self.where()}{did_you_mean(name, names)} (modules: {shown})"

    def resolve(self, name: str, range_text=None) -> CatalogEntry:
        """The highest version of ``name`` in the range (None or '' means any release).

        Raises ``LookupError`` for an unknown module or when no version satisfies the range, and
        ``ValueError`` for a malformed range; the message says why for a person to read.
        """
        group = self._entries.get(name)
        if not group:
            raise LookupError(self.unknown_module(name))
        text = str(range_text).strip() if range_text is not None else ""
        try:
            wanted = parse_range(text or "*")
        except ValueError as exc:
            raise ValueError(f"invalid version range after '{name}@': {exc}") from None
        best = wanted.best([entry.semver for entry in group])
        if best is None:
            versions = ", ".join(entry.version for entry in group)
            raise LookupError(f"no version of {name} satisfies {text or '*'} (versions: {versions})")
        return next(entry for entry in group if entry.semver == best)

    def subset(self, refs: Iterable[tuple[str, str]]) -> Catalog:
        """A catalog of only the entries ``refs`` names (pairs of module name and version)."""
        chosen = {}
        for name, version in refs:
            entry = self.get(name, version)
            if entry is None:
                known = ", ".join(e.version for e in self.entries(name))
                reason = f"versions: {known}" if known else self.unknown_module(name)
                raise LookupError(f"{name} {version} is not in {self.where()} ({reason})")
            chosen[(entry.name, entry.version)] = entry
        return Catalog(chosen.values(), self.source, self.missing)

    def to_dict(self) -> dict:
        """Plain JSON data: the catalog document of every entry, with source and line; see ``from_dict``."""
        modules = []
        for name, group in self._entries.items():
            module: dict = {"name": name}
            if group[0].description:
                module["description"] = group[0].description
            module["versions"] = [entry.to_dict() for entry in group]
            modules.append(module)
        data = {"apiVersion": API_VERSION, "kind": CATALOG_KIND, "source": self.source, "modules": modules}
        if self.missing:
            data["missing"] = True
        return data

    @classmethod
    def from_dict(cls, data, source: str | None = None) -> Catalog:
        """The catalog ``to_dict`` wrote, validated like a catalog file; ``SpecError`` if it is not one.

        The catalog keeps the ``source`` written in ``data``; errors name ``source`` (e.g. the record read).
        """
        written = data.get("source") if isinstance(data, dict) and isinstance(data.get("source"), str) else None
        where = source or written or "<catalog data>"
        if not isinstance(data, dict):
            raise SpecError([Problem(where, "", f"{describe(data)} is not a catalog; expected a mapping")])
        too_large = _too_large(data)
        if too_large:
            raise SpecError([Problem(where, "", f"catalog data too large: {too_large}")])
        body = copy.deepcopy({k: v for k, v in data.items() if k not in ("source", "missing")})
        origins: dict = {}
        for i, module in enumerate(body.get("modules") if isinstance(body.get("modules"), list) else []):
            versions = module.get("versions") if isinstance(module, dict) else None
            for j, version in enumerate(versions if isinstance(versions, list) else []):
                if isinstance(version, dict):
                    origins[(i, j)] = (version.pop("source", None), version.pop("line", None))
        problems: list[Problem] = []
        declared: dict[str, str] = {}
        doc = Document(body, where, 0, {})
        found = []
        for entry, parts in _entries_of(doc, problems, declared):
            origin, line = origins.get((parts[1], parts[3]), (None, None))
            origin = origin if isinstance(origin, str) else (written if written is not None else where)
            line = line if isinstance(line, int) and not isinstance(line, bool) else None
            found.append((replace(entry, source=origin, line=line), doc, parts))
        problems.extend(_cross_problems(found, declared))
        if problems:
            problems.sort(key=lambda p: p.line or 0)
            raise SpecError(problems, title=f"{where} is not a valid software catalog")
        return cls([entry for entry, *_where in found], written if written is not None else where, data.get("missing") is True)


def _too_large(data) -> str:
    """Why plain data is too big or deep to validate (the bounds of YAML documents), or ''."""
    count, stack = 0, [(data, 0)]
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            return f"more than {MAX_NODES} values"
        if depth > MAX_DEPTH:
            return f"nested deeper than {MAX_DEPTH} levels"
        if isinstance(node, dict):
            stack.extend((value, depth + 1) for value in node.values())
        elif isinstance(node, (list, tuple)):
            stack.extend((value, depth + 1) for value in node)
    return ""


# --------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------


def _image_problem(image: str) -> str | None:
    if "@" in image:
        return (
            f"{describe(image)} has a digest; put the digest (sha256:...) in 'digest' and keep the image as "
            "name:tag, such as 'ghcr.io/kuberos/pnp-planner:0.2.0'"
        )
    return image_reference_problem(image, digest_allowed=False)


def _version_problems(raw: dict, doc: Document, base: tuple, problems: list[Problem]) -> None:
    """Checks of one schema-valid version entry beyond what the schema says."""

    def add(parts, message):
        problems.append(problem(doc, base + parts, message))

    why = _image_problem(raw["image"])
    if why:
        add(("image",), why)
    problems.extend(launch_problems(raw["launch"], doc, base))
    requirements = raw.get("requirements") or {}
    resources = raw.get("resources") or {}
    for section, name, key, parser in (
        (requirements, "requirements", "max_latency", quantities.parse_latency_ms),
        (resources, "resources", "cpu", quantities.parse_cpu),
        (resources, "resources", "memory", quantities.parse_memory),
    ):
        if key in section:
            try:
                amount = parser(section[key])
            except ValueError as exc:
                add((name, key), f"{describe(section[key])} is not valid; {exc}")
                continue
            if key == "memory" and amount == 0:
                add((name, key), "must be more than zero; expected e.g. '128Mi'")
            if key == "max_latency" and amount <= 0:
                add((name, key), f"{describe(section[key])} is not more than zero; expected a latency such as '200 ms'")
    problems.extend(ros_parameter_problems(raw.get("rosParameters") or {}, doc, (*base, "rosParameters")))
    for key in raw.get("env") or {}:
        why = env_name_problem(key)
        if why:
            add(("env", str(key)), why)
    preference = raw.get("preference")
    if requirements.get("onboard") and preference is not None and as_tuple(preference)[:1] != ("onboard",):
        add(
            ("preference",),
            f"{describe(preference)} contradicts requirements.onboard: true; expected preference onboard (or leave it out)",
        )
    architectures = raw.get("architectures") or []
    arch = as_tuple(requirements.get("arch"))
    if architectures and arch and not set(arch) & set(architectures):
        add(
            ("requirements", "arch"),
            f"{describe(requirements['arch'])} shares no architecture with architectures ({', '.join(architectures)}); "
            "expected some of them",
        )
    for name, text in (raw.get("dependencies") or {}).items():
        try:
            parse_range(text)
        except ValueError as exc:
            add(("dependencies", name), f"{describe(text)} is not a valid version range: {exc}")


def _entry(raw: dict, name: str, description: str, doc: Document, parts: tuple) -> CatalogEntry:
    preference = raw.get("preference")
    requirements = dict(raw.get("requirements") or {})
    architectures = tuple(raw.get("architectures") or ())
    return CatalogEntry(
        name=name,
        version=raw["version"],
        image=raw["image"],
        digest=raw.get("digest", ""),
        launch=as_tuple(raw["launch"]),
        ros_distro=raw.get("rosDistro", ""),
        architectures=architectures,
        preference=tuple(preference) if isinstance(preference, list) else preference,
        requirements=requirements,
        resources=dict(raw.get("resources") or {}),
        ros_parameters=dict(raw.get("rosParameters") or {}),
        env=dict(raw.get("env") or {}),
        dependencies=tuple(sorted((raw.get("dependencies") or {}).items())),
        # JSON Schema counts 2.0 as an integer; keep real ints.
        interfaces=tuple(sorted((k, int(v)) for k, v in (raw.get("interfaces") or {}).items())),
        topics=copy.deepcopy(raw.get("topics") or {}),
        upgrade=raw.get("upgrade", ""),
        source=doc.source,
        line=doc.line_of(parts),
        description=description,
    )


def _entries_of(doc: Document, problems: list[Problem], declared: dict[str, str]) -> list[tuple[CatalogEntry, tuple]]:
    """The valid entries of one catalog document with their paths; its problems go to ``problems``.

    ``declared`` maps the module names of the documents read so far (valid or not) to where they are
    written; a module written twice is a problem (each module is written once, with all its versions).
    """
    found_problems = schema_problems(_validator(), doc)
    broken = {p.path for p in found_problems}
    mine: list[Problem] = list(found_problems)
    entries: list[tuple[CatalogEntry, tuple]] = []
    modules = doc.data.get("modules") if isinstance(doc.data, dict) else None
    for i, module in enumerate(modules if isinstance(modules, list) else []):
        prefix = format_path(("modules", i))
        if isinstance(module, dict) and isinstance(module.get("name"), str):
            line = doc.line_of(("modules", i, "name"))
            where = f"{doc.source}:{line}" if line else f"{doc.source} ({prefix})"
            if module["name"] in declared:
                mine.append(
                    problem(
                        doc,
                        ("modules", i, "name"),
                        f"'{module['name']}' is already a module of the catalog (at {declared[module['name']]}); "
                        "expected each module once, with all of its versions",
                    )
                )
            declared.setdefault(module["name"], where)
        if not isinstance(module, dict) or any(_under(path, prefix) and not _is_version_path(path, prefix) for path in broken):
            continue
        versions = module["versions"]
        seen: dict = {}
        for j, raw in enumerate(versions):
            parts = ("modules", i, "versions", j)
            if any(_under(path, format_path(parts)) for path in broken):
                continue
            try:
                version = parse_version(raw["version"])
            except ValueError as exc:
                mine.append(problem(doc, (*parts, "version"), str(exc)))
                continue
            if version in seen:
                first, first_line = seen[version]
                at = f"line {first_line}" if first_line else format_path(("modules", i, "versions", first))
                first_text = versions[first]["version"]
                same = (
                    "is listed twice"
                    if first_text == raw["version"]
                    else f"has the same precedence as {first_text} (build metadata does not count)"
                )
                mine.append(
                    problem(doc, (*parts, "version"), f"{raw['version']} {same}, first at {at}; expected each version once")
                )
                continue
            seen[version] = (j, doc.line_of((*parts, "version")))
            before = len(mine)
            _version_problems(raw, doc, parts, mine)
            if len(mine) == before:
                entries.append((_entry(raw, module["name"], module.get("description", ""), doc, parts), parts))
    problems.extend(sorted(mine, key=lambda p: (p.line or 0, p.path)))
    return entries


def _under(path: str, prefix: str) -> bool:
    return path == prefix or path.startswith(prefix + ".") or path.startswith(prefix + "[")


def _is_version_path(path: str, prefix: str) -> bool:
    """A problem inside one version of a module (the module's other versions are still checked)."""
    return path.startswith(prefix + ".versions[")


def _cross_problems(found: list[tuple[CatalogEntry, Document, tuple]], declared: dict[str, str]) -> list[Problem]:
    """Dependencies across the whole catalog: known, not the module itself, satisfiable.

    ``declared`` holds every module name written in the catalog, valid or not, so that a dependency
    on a module whose versions are all broken is not also reported as unknown.
    """
    problems: list[Problem] = []
    versions: dict[str, list[Version]] = {}
    for entry, _doc, _parts in found:
        versions.setdefault(entry.name, []).append(entry.semver)
    names = sorted(set(declared) | set(versions))
    for entry, doc, parts in found:
        for name, text in entry.dependencies:
            path = (*parts, "dependencies", name)
            if name == entry.name:
                problems.append(problem(doc, path, f"{entry.name} cannot depend on itself"))
            elif name not in names:
                problems.append(problem(doc, path, f"'{name}' is not a module of the catalog{did_you_mean(name, names)}"))
            elif name in versions and parse_range(text).best(versions[name]) is None:
                listed = ", ".join(str(v) for v in sorted(versions[name]))
                problems.append(problem(doc, path, f"no version of {name} satisfies {text} (versions: {listed})"))
    return problems


def _read(path: str, display: str, problems: list[Problem]) -> str | None:
    try:
        return read_text(path, display)
    except SpecError as exc:
        problems.extend(exc.problems)
        return None


def load_catalog(path, display: str | None = None) -> Catalog:
    """The catalog at ``path`` (a directory of YAML files, or one file); errors name ``display``.

    A missing path is an empty catalog whose ``missing`` is true, so that a spec naming a catalog
    module can say "no catalog at <path>". Every problem of every file is raised as one ``SpecError``.
    """
    path = os.fspath(path)
    display = display or path
    if not os.path.exists(path):
        return Catalog((), display, missing=True)
    problems: list[Problem] = []
    found: list[tuple[CatalogEntry, Document, tuple]] = []
    declared: dict[str, str] = {}
    for file_path, file_display in yaml_files(path, display, problems, MAX_FILES, "catalog files"):
        text = _read(file_path, file_display, problems)
        if text is None:
            continue
        try:
            documents = [doc for doc in load_documents(text, file_display) if doc.data is not None]
        except SpecError as exc:
            problems.extend(exc.problems)
            continue
        for doc in documents:
            if len(documents) > 1:
                doc.source = f"{file_display} (document {doc.index + 1})"
            found.extend((entry, doc, parts) for entry, parts in _entries_of(doc, problems, declared))
    problems.extend(_cross_problems(found, declared))
    if problems:
        problems.sort(key=lambda p: (p.source, p.line or 0))  # files in the order read, each by line
        raise SpecError(problems, title=f"{display} is not a valid software catalog")
    return Catalog([entry for entry, *_where in found], display)


# --------------------------------------------------------------------------------------------
# Against the inventory
# --------------------------------------------------------------------------------------------


def catalog_problems_against_inventory(deployments, inventory) -> list[Problem]:
    """Catalog modules whose architectures match no node they may use.

    A module resolved from the catalog carries the catalog's ``architectures`` (intersected with its
    own ``requirements.arch``) in ``requirements.arch``. It may use the nodes of its tiers: the fleet's
    edge and cloud nodes (``inventory.tier_nodes``) and the onboard computers of the deployment's
    robots. When none of those has one of its architectures, the module can never be placed.
    Modules that run in a third-party cluster are not checked (that cluster picks the node).
    """
    problems = []
    for dep in deployments:
        if dep.fleet not in inventory.fleets:
            continue  # the scheduler reports the unknown fleet
        robots = [r for r in (dep.robots or inventory.fleets[dep.fleet]) if r in inventory.robots]
        for module in dep.modules:
            arch = module.requirements.arch
            if not module.catalog_module or module.cluster or not arch:
                continue
            nodes = []
            for tier in module.tiers:
                if tier == "onboard":
                    nodes.extend(inventory.nodes[inventory.robots[r].node] for r in robots)
                else:
                    nodes.extend(inventory.tier_nodes(tier, dep.fleet))
            if any(node.arch in arch for node in nodes):
                continue
            have = ", ".join(
                f"{a} ({', '.join(sorted({n.name for n in nodes if n.arch == a}))})" for a in sorted({n.arch for n in nodes})
            )
            path = f"{module.path}.module"
            problems.append(
                Problem(
                    dep.source,
                    path,
                    f"{module.catalog_module} {module.version} runs on {', '.join(arch)}, but no {'/'.join(module.tiers)} "
                    f"node of fleet {dep.fleet} has that architecture (nodes: {have or 'none'})",
                    dep.line_of(path),
                )
            )
    return problems


__all__ = [
    "CATALOG_KIND",
    "CATALOG_SCHEMA",
    "DEFAULT_DIRECTORY",
    "Catalog",
    "CatalogEntry",
    "catalog_problems_against_inventory",
    "load_catalog",
]
