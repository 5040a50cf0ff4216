"""Images pinned by digest: what a deploy resolves each image's tag to, and how it is rendered.

A module's image names a tag (``ghcr.io/kuberos/pnp-planner:0.1``); what a robot runs must not change when the tag
moves. Deploy and rollouts resolve every image that has no digest yet (the catalog records one per version; a spec
may write ``image@sha256:...`` itself) to the digest its registry serves now, and render ``name:tag@digest``: the
kubelet pulls the digest, people still read the tag, and the deployment record keeps both. The next deploy or rollout
resolves again; a tag that moved in between shows as an image change in its diff, and nothing changes before.

Pure: plain data in, plain data out (the registry is asked by ``kuberos_deploy.image_digests``).
"""

from __future__ import annotations

import re

from .validation import split_image

DIGEST = re.compile(r"^sha(256:[0-9a-f]{64}|512:[0-9a-f]{128})$")
DOCKER_HUB = "docker.io"


def has_digest(image: str) -> bool:
    return bool(split_image(image)[3])


def pinned(image: str, digests: dict[str, str]) -> str:
    """``image@digest`` when ``digests`` resolves ``image`` (and it has no digest of its own), else ``image``."""
    digest = digests.get(image)
    return f"{image}@{digest}" if digest and not has_digest(image) else image


def unpinned(images) -> list[str]:
    """The images of ``images`` that name no digest, each once, sorted."""
    return sorted({image for image in images if image and not has_digest(image)})


def registry_and_repository(image: str) -> tuple[str, str, str]:
    """(registry host, repository, tag) as a container runtime reads a reference: Docker Hub when it names no
    registry, ``library/`` before a one-part Docker Hub path, ``latest`` when it names no tag."""
    domain, path, tag, _digest = split_image(image)
    domain = domain or DOCKER_HUB
    if domain == DOCKER_HUB and "/" not in path:
        path = f"library/{path}"
    return domain, path, tag or "latest"


def deployment_images(deployments, discovery_image: str, bridge_image: str, with_bridge: bool) -> list[str]:
    """Every image a render of ``deployments`` names: the modules', the discovery servers', the bridges' (when a
    module runs in a third-party cluster)."""
    images = {m.image for d in deployments for m in d.modules} | {discovery_image}
    if with_bridge:
        images.add(bridge_image)
    return sorted(images)
