"""The deploy path in one call: spec + inventory -> validated deployments and a placement.

Shared by the scheduler filter, the render module, the controller and the simulator so that
they all read specs and place modules the same way.
"""

from __future__ import annotations

import os

from .errors import Problem, SpecError
from .inventory import load_inventory
from .placement import Placement
from .scheduler import place_modules
from .spec import RosDeployment, load_rosdeployment_file, parse_rosdeployment


def load_specs(spec, catalog=None) -> list[RosDeployment]:
    """A path to a spec file, one spec as data, or a list of specs as data.

    ``catalog`` (a ``catalog.Catalog`` or None) resolves modules that name a catalog module.
    """
    if isinstance(spec, (str, os.PathLike)):
        return load_rosdeployment_file(os.fspath(spec), catalog=catalog)
    if isinstance(spec, dict):
        return [parse_rosdeployment(spec, "<spec>", catalog=catalog)]
    if isinstance(spec, (list, tuple)) and spec:
        deployments, problems = [], []
        for index, item in enumerate(spec):
            try:
                deployments.append(parse_rosdeployment(item, f"<spec {index + 1}>", catalog=catalog))
            except SpecError as exc:
                problems.extend(exc.problems)
        if problems:
            raise SpecError(problems, title="the RosDeployment is not valid")
        return deployments
    raise SpecError([Problem("<spec>", "", f"expected a spec file path or a RosDeployment mapping, got {type(spec).__name__}")])


def load_and_place(
    spec, inventory, allocated=None, unavailable=None, previous=None, catalog=None
) -> tuple[list[RosDeployment], Placement]:
    """``previous`` (a Placement or its dict form) is what runs now: sticky placement keeps what still fits there.
    ``catalog`` resolves modules that name a catalog module (``load_specs``)."""
    deployments = load_specs(spec, catalog)
    model = load_inventory(inventory)
    if isinstance(previous, dict):
        previous = Placement.from_dict(previous) if previous.get("instances") or previous.get("discovery") else None
    return deployments, place_modules(deployments, model, allocated, unavailable, previous)
