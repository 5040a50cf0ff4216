"""The argument_spec of the render options (documented by the kuberos.platform.render fragment), shared by modules."""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions

RENDER_ARGS = {
    "cluster_domain": {"type": "str", "default": RenderOptions.cluster_domain},
    "discovery_image": {"type": "str", "default": RenderOptions.discovery_image},
    "bridge_image": {"type": "str", "default": RenderOptions.bridge_image},
}


def render_options(params: dict) -> RenderOptions:
    return RenderOptions(
        cluster_domain=params["cluster_domain"], discovery_image=params["discovery_image"], bridge_image=params["bridge_image"]
    )
