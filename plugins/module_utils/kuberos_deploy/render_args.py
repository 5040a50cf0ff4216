"""The argument_spec of the render options (documented by the kuberos.platform.render fragment), shared by modules."""

from __future__ import annotations

import re

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.validation import image_reference_problem

DNS_LABEL_RE = re.compile(r"[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?")

RENDER_ARGS = {
    "cluster_domain": {"type": "str", "default": RenderOptions.cluster_domain},
    "discovery_image": {"type": "str", "default": RenderOptions.discovery_image},
    "bridge_image": {"type": "str", "default": RenderOptions.bridge_image},
    "metrics_namespaces": {"type": "list", "elements": "str", "default": list(RenderOptions.metrics_namespaces)},
    "pin_images": {"type": "bool", "default": True},
    "registry_mirrors": {"type": "dict", "default": {}},
    "registry_token_realms": {"type": "dict", "default": {}, "no_log": False},  # realm hosts, not tokens
}


def render_options(params: dict) -> RenderOptions:
    """The options, once the images given for discovery servers and bridges are valid image references."""
    problems = [
        Problem("render options", option, why)
        for option in ("discovery_image", "bridge_image")
        if (why := image_reference_problem(params[option])) is not None
    ]
    namespaces = params.get("metrics_namespaces", list(RenderOptions.metrics_namespaces))
    problems += [
        Problem(
            "render options", f"metrics_namespaces[{i}]", f"{name!r} is not a namespace name (lowercase letters, digits, '-')"
        )
        for i, name in enumerate(namespaces)
        if not isinstance(name, str) or not DNS_LABEL_RE.fullmatch(name)
    ]
    if problems:
        raise SpecError(
            problems,
            title="the render options are not valid "
            "(rosdeployment_discovery_image, rosdeployment_bridge_image, rosdeployment_metrics_namespaces)",
        )
    return RenderOptions(
        cluster_domain=params["cluster_domain"],
        discovery_image=params["discovery_image"],
        bridge_image=params["bridge_image"],
        metrics_namespaces=tuple(namespaces),
        image_digests=tuple(sorted((params.get("image_digests") or {}).items())),
    )
