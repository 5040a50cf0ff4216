"""Each image's tag resolved to the digest its registry serves now (image_pins renders ``image@digest``).

A registry is asked through the site's mirrors first, as the nodes' container runtime asks it (``mirrors``: the
``node_prereqs_registry_mirrors`` form, ``{registry: [{url, ca}]}``), then at its own address (Docker Hub's is
``registry-1.docker.io``). Credentials come from the pull secrets the modules name (``.dockerconfigjson``, as the
kubelet reads them); a registry that asks for a bearer token gets one from its token service. An image no endpoint
can resolve stops the deploy before anything is applied, with one line per image naming every endpoint and why.
"""

from __future__ import annotations

import base64
import json
import os
import tempfile

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import image_pins
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.registry_api import RegistryApi, RegistryError

# Where a registry's API answers when it is not at the host its images name.
API_HOSTS = {"docker.io": "registry-1.docker.io"}


def credentials(secrets: list[dict]) -> dict[str, tuple[str, str]]:
    """Registry host -> (username, password) from ``kubernetes.io/dockerconfigjson`` Secrets (raw JSON objects)."""
    found = {}
    for secret in secrets:
        encoded = (secret.get("data") or {}).get(".dockerconfigjson")
        if not encoded:
            continue
        try:
            auths = json.loads(base64.b64decode(encoded)).get("auths") or {}
        except (ValueError, TypeError):
            continue
        for host, entry in auths.items():
            user, password = entry.get("username", ""), entry.get("password", "")
            if not (user or password) and entry.get("auth"):
                user, _sep, password = base64.b64decode(entry["auth"]).decode(errors="replace").partition(":")
            found[host.removeprefix("https://").removeprefix("http://").rstrip("/")] = (user, password)
    return found


def endpoints(host: str, mirrors: dict) -> list[tuple[str, str | None]]:
    """(address, CA file) to ask for images of ``host``: its mirrors, then itself."""
    found = []
    for mirror in mirrors.get(host) or []:
        url = mirror.get("url", "") if isinstance(mirror, dict) else str(mirror)
        if url.startswith("https://"):
            found.append(
                (url.removeprefix("https://").rstrip("/"), (mirror.get("ca") if isinstance(mirror, dict) else None) or None)
            )
    return [*found, (API_HOSTS.get(host, host), None)]


def resolve(images, mirrors: dict | None = None, logins: dict | None = None) -> dict[str, str]:
    """image -> digest for every image of ``images`` without one; KuberosError naming each that no endpoint resolves.
    A mirror's ``ca`` is a file, or the PEM text itself (as node_prereqs writes it to the nodes)."""
    with tempfile.TemporaryDirectory(prefix="kuberos-registry-ca-") as folder:
        return _resolve(images, _ca_files(mirrors or {}, folder), logins or {})


def _ca_files(mirrors: dict, folder: str) -> dict:
    """``mirrors`` with each CA given as PEM text written to a file of ``folder``."""
    out = {}
    for host, entries in mirrors.items():
        out[host] = []
        for number, entry in enumerate(entries or []):
            entry = dict(entry) if isinstance(entry, dict) else {"url": str(entry)}
            if str(entry.get("ca") or "").lstrip().startswith("-----BEGIN"):
                path = os.path.join(folder, f"{len(out)}-{number}.crt")
                with open(path, "w", encoding="utf-8") as handle:
                    handle.write(entry["ca"])
                entry["ca"] = path
            out[host].append(entry)
    return out


def _resolve(images, mirrors: dict, logins: dict) -> dict[str, str]:
    digests, problems = {}, []
    for image in image_pins.unpinned(images):
        host, repository, tag = image_pins.registry_and_repository(image)
        tried = []
        for address, ca_file in endpoints(host, mirrors):
            user, password = logins.get(address, logins.get(host, ("", "")))
            try:
                digests[image] = RegistryApi(address, user, password, ca_file).manifest_digest(repository, tag)
                break
            except RegistryError as exc:
                tried.append(str(exc))
        else:
            problems.append(f"{image}: " + "; ".join(tried))
            continue
        if not image_pins.DIGEST.match(digests[image]):
            problems.append(f"{image}: the registry answered {digests.pop(image)!r}, which is not a digest")
    if problems:
        raise KuberosError(
            "cannot pin every image to its digest, so nothing was applied (rosdeployment_pin_images; a site with a "
            "mirror names it in rosdeployment_registry_mirrors):\n" + "\n".join(f"  - {p}" for p in problems)
        )
    return digests


def pull_secrets(deployments) -> set[tuple[str, str]]:
    """(namespace, name) of every pull secret the deployments' modules name: where their registries' credentials are."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace

    return {(fleet_namespace(d.fleet), m.registry.pull_secret) for d in deployments for m in d.modules
            if m.registry and m.registry.pull_secret}  # fmt: skip


def for_render(deployments, params: dict, secrets: list[dict], bridges: bool) -> dict[str, str]:
    """image -> digest of every image a render of ``deployments`` names (the render options ``params``), asked with
    the credentials of ``secrets`` (the pull secrets of ``pull_secrets``): what deploy and rollouts pin."""
    images = image_pins.deployment_images(deployments, params["discovery_image"], params["bridge_image"], bridges)
    return resolve(images, params.get("registry_mirrors") or {}, credentials(secrets))
