"""The argument_spec of the render options (documented by the kuberos.platform.render fragment), shared by modules."""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.validation import image_reference_problem

RENDER_ARGS = {
    "cluster_domain": {"type": "str", "default": RenderOptions.cluster_domain},
    "discovery_image": {"type": "str", "default": RenderOptions.discovery_image},
    "bridge_image": {"type": "str", "default": RenderOptions.bridge_image},
}


def render_options(params: dict) -> RenderOptions:
    """The options, once the images given for discovery servers and bridges are valid image references."""
    problems = [
        Problem("render options", option, why)
        for option in ("discovery_image", "bridge_image")
        if (why := image_reference_problem(params[option])) is not None
    ]
    if problems:
        raise SpecError(
            problems, title="the render options are not valid (rosdeployment_discovery_image, rosdeployment_bridge_image)"
        )
    return RenderOptions(
        cluster_domain=params["cluster_domain"], discovery_image=params["discovery_image"], bridge_image=params["bridge_image"]
    )
