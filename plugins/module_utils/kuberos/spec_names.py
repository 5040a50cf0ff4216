"""Names that would clash: two modules of the deployments, or a module and an object already in the cluster."""

from __future__ import annotations

from . import naming
from .errors import Problem
from .spec_model import RosDeployment, RosModule


def _module_names(dep: RosDeployment, robots) -> list[tuple[naming.PlannedName, RosModule]]:
    return [
        (planned, module)
        for module in dep.modules
        for planned in naming.module_object_names(
            dep.fleet,
            dep.name,
            module.name,
            module.strategy == "shared",
            robots,
            bool(module.ros_parameters),
            module.scaling is not None,
        )
    ]


def name_clash_problems(deployments: list[RosDeployment], robots_of, live=()) -> list[Problem]:
    """Objects that would get the same name: two modules of the deployments (``robots_of(deployment)`` gives the
    robots each one serves, or None for all robots of its fleet when they are not known; see
    ``naming.module_object_names``), or a
    module and an object already in the cluster (``live``: mappings with kind, namespace, name and the deployment
    and module that own it, '' when none) that is not this deployment's own. Modules of third-party clusters are
    compared among themselves only.

    Names join deployment, module and robot with '-' (``naming.py``), so that deployment ``a-b`` with module ``c``
    and deployment ``a`` with module ``b-c`` name their instances alike; the problem is reported at the module
    named second, naming the first.
    """
    problems: list[Problem] = []
    first: dict[tuple, tuple[RosDeployment, RosModule, naming.PlannedName]] = {}
    reported = set()
    for dep in deployments:
        robots = robots_of(dep)
        for planned, module in _module_names(dep, robots):
            key = (module.cluster, planned.kind, planned.namespace, planned.name)
            other = first.setdefault(key, (dep, module, planned))
            if other[2] is planned or (dep.name, module.name) in reported:
                continue
            other_dep, other_module, _planned = other
            path = f"{module.path}.name"
            where = f"{other_dep.source}:{other_dep.line_of(other_module.path + '.name')}"
            problems.append(
                Problem(
                    dep.source,
                    path,
                    f"'{module.name}' of deployment {dep.name} would name a {planned.kind} {planned.name} ({planned.what}), "
                    f"the name {other_module.path}.name '{other_module.name}' of deployment {other_dep.name} ({where}) gets; "
                    "names join deployment, module and robot with '-'; expected module or deployment names that do not "
                    "join to the same name (rename one of the two)",
                    dep.line_of(path),
                )
            )
            reported.add((dep.name, module.name))
    mine = {(dep.name) for dep in deployments}
    owners = {(obj["kind"], obj["namespace"], obj["name"]): obj for obj in live}
    for (cluster, kind, namespace, name), (dep, module, planned) in first.items():
        obj = owners.get((kind, namespace, name))
        if cluster or obj is None or "<" in name or obj.get("deployment") in mine or (dep.name, module.name) in reported:
            continue
        owner = (
            f"deployment {obj['deployment']} (module {obj.get('module') or '?'})"
            if obj.get("deployment")
            else "no KubeROS deployment"
        )
        path = f"{module.path}.name"
        problems.append(
            Problem(
                dep.source,
                path,
                f"'{module.name}' of deployment {dep.name} would name a {kind} {name} ({planned.what}) in namespace "
                f"{namespace}, but a {kind} of that name is already there and belongs to {owner}; names join deployment, "
                "module and robot with '-'; expected module or deployment names that give other names",
                dep.line_of(path),
            )
        )
        reported.add((dep.name, module.name))
    return problems
