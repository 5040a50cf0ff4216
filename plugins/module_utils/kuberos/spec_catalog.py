"""Modules that name a catalog module (``module: name@range``): the entry resolved, its fields merged under the
spec's own, and what the catalog says about versions, architectures and devices checked."""

from __future__ import annotations

import copy

from .catalog import Catalog, CatalogEntry
from .errors import Problem, describe
from .semver import parse_range
from .spec_model import RosModule, _problem
from .validation import (
    as_tuple,
)
from .yaml_source import Document

NO_CATALOG = (
    "no catalog given; set kuberos_catalog to the software catalog (a directory of RosModuleCatalog files, "
    "by default the inventory's catalog/ directory), or give image and launch instead"
)


def _deep_merge(base: dict, over: dict) -> dict:
    """``over`` written over ``base``: mappings merge key by key, anything else replaces."""
    merged = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def _merged_module(module: dict, entry: CatalogEntry, index: int, doc: Document, problems: list[Problem]) -> dict | None:
    """The spec's module written over the catalog entry (docs/software.md, "Resolution and overrides")."""
    merged = {key: value for key, value in module.items() if key != "module"}
    merged["image"] = entry.image_ref
    merged.setdefault("launch", list(entry.launch))
    spec_requirements = module.get("requirements") or {}
    # A spec that pins the module onboard does not inherit the catalog's preference (it would contradict).
    if "preference" not in module and entry.preference is not None and not spec_requirements.get("onboard"):
        merged["preference"] = list(entry.preference) if isinstance(entry.preference, tuple) else entry.preference
    requirements = {**entry.requirements, **spec_requirements}
    # The images exist for the catalog's architectures only: the module may run on nodes of those.
    built = list(entry.architectures)
    if built and entry.requirements.get("arch"):
        built = [a for a in built if a in as_tuple(entry.requirements["arch"])]
    if built:
        wanted = as_tuple(spec_requirements.get("arch"))
        arch = [a for a in built if a in wanted] if wanted else built
        if not arch:
            problems.append(
                _problem(
                    doc,
                    ("rosModules", index, "requirements", "arch"),
                    f"{describe(spec_requirements['arch'])} shares no architecture with {entry.label}, "
                    f"whose image is built for {', '.join(built)}; expected some of them (or leave arch out)",
                )
            )
            return None
        requirements["arch"] = arch
    merged["requirements"] = requirements
    merged["resources"] = {**entry.resources, **(module.get("resources") or {})}
    merged["rosParameters"] = _deep_merge(entry.ros_parameters, module.get("rosParameters") or {})
    merged["env"] = {**entry.env, **(module.get("env") or {})}
    # The spec's publishes or subscribes replace the catalog's list of that direction.
    topics = {**entry.topics, **(module.get("topics") or {})}
    if topics:
        merged["topics"] = copy.deepcopy(topics)
    if "upgrade" not in module and entry.upgrade:
        merged["upgrade"] = entry.upgrade
    return merged


def _resolve(module: dict, index: int, doc: Document, catalog: Catalog | None, problems: list[Problem]):
    """The catalog entry ``module:`` names and the module merged over it, or None (a problem is added)."""
    path = ("rosModules", index, "module")
    reference = module["module"]
    if catalog is None:
        problems.append(_problem(doc, path, f"'{reference}' names a catalog module, but {NO_CATALOG}"))
        return None
    name, _sep, range_text = reference.partition("@")
    try:
        entry = catalog.resolve(name.strip(), range_text.strip() or None)
    except (LookupError, ValueError) as exc:
        problems.append(_problem(doc, path, str(exc)))
        return None
    merged = _merged_module(module, entry, index, doc, problems)
    return None if merged is None else (merged, entry)


def _catalog_problems(doc: Document, resolved: list[tuple[RosModule, CatalogEntry]], unresolved: set[str]) -> list[Problem]:
    """The catalog modules of one deployment agree: dependencies, rosDistro and interface versions.

    ``unresolved`` names the catalog modules of modules already reported (no second error for them).
    """
    problems = []

    def add(module: RosModule, message: str):
        problems.append(_problem(doc, ("rosModules", module.index, "module"), message))

    def named(module: RosModule, entry: CatalogEntry) -> str:
        return f"{module.path} ({module.name}: {entry.label})"

    by_catalog: dict[str, list[tuple[RosModule, CatalogEntry]]] = {}
    for module, entry in resolved:
        by_catalog.setdefault(entry.name, []).append((module, entry))
    distro = None
    interfaces: dict[str, tuple[int, RosModule, CatalogEntry]] = {}
    for module, entry in resolved:
        for name, text in entry.dependencies:
            users = by_catalog.get(name)
            if not users and name in unresolved:
                continue
            if not users:
                add(module, f"{entry.label} depends on {name} {text}; the deployment has no module from {name}")
                continue
            try:
                wanted = parse_range(text)
            except ValueError:  # the catalog checked its ranges; a hand-made Catalog may not have
                add(module, f"{entry.label} depends on {name} with an invalid range {text!r}")
                continue
            for other, other_entry in users:
                if not wanted.matches(other_entry.semver):
                    add(module, f"{entry.label} depends on {name} {text}; {other.path} ({other.name}) uses {other_entry.label}")
        if entry.ros_distro:
            if distro is None:
                distro = (module, entry)
            elif distro[1].ros_distro != entry.ros_distro:
                add(
                    module,
                    f"{entry.label} is built for ROS 2 {entry.ros_distro}, but {named(*distro)} is built for "
                    f"{distro[1].ros_distro}; expected one rosDistro in a deployment",
                )
        for name, number in entry.interfaces:
            first = interfaces.setdefault(name, (number, module, entry))
            if first[0] != number:
                add(
                    module,
                    f"{entry.label} speaks interface {name} version {number}, but {named(first[1], first[2])} speaks "
                    f"version {first[0]}; expected one version of each interface in a deployment",
                )
    return problems
