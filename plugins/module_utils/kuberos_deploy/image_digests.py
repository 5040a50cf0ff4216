"""Each image's tag resolved to the digest its registry serves now (image_pins renders ``image@digest``).

A registry is asked through the site's mirrors first, as the nodes' container runtime asks it (``mirrors``: the
``node_prereqs_registry_mirrors`` form, ``{registry: [{url, ca}]}``), then at its own address (Docker Hub's is
``registry-1.docker.io``). Credentials come from the pull secrets the modules name (``.dockerconfigjson``, as the
kubelet reads them), each sent only to the registry it was given for: a mirror gets only its own; a registry that
asks for a bearer token gets one from its token service (sent the credentials only when it is the registry's own
host or a realm the site names, ``registry_token_realms``). An image no endpoint
can resolve stops the deploy before anything is applied, with one line per image naming every endpoint and why.
"""

from __future__ import annotations

import base64
import json
import os
import tempfile
import urllib.parse
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import image_pins
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.registry_api import RegistryApi, RegistryError

# Where a registry's API answers when it is not at the host its images name.
API_HOSTS = {"docker.io": "registry-1.docker.io"}
# The names a pull secret may give a registry's credentials under (as the kubelet matches them).
LOGIN_NAMES = {"docker.io": ("docker.io", "index.docker.io/v1", "index.docker.io", "registry-1.docker.io")}


@dataclass(frozen=True)
class Endpoint:
    """Where to ask for a registry's images: ``address`` (host[:port]), its CA file, plain http allowed
    (``insecure``), and the names under which a pull secret's credentials are this endpoint's own."""

    address: str
    ca_file: str | None = None
    insecure: bool = False
    login_names: tuple = ()


def _auths(secret: dict) -> tuple[str, dict]:
    meta = secret.get("metadata") or {}
    where = f"pull Secret {meta.get('namespace') or '?'}/{meta.get('name') or '?'}"
    encoded = (secret.get("data") or {}).get(".dockerconfigjson")
    try:
        config = json.loads(base64.b64decode(encoded, validate=True))
    except (ValueError, TypeError):
        raise KuberosError(f"{where}: its .dockerconfigjson is not base64-encoded JSON") from None
    auths = config.get("auths") if isinstance(config, dict) else None
    if not isinstance(auths, dict):
        raise KuberosError(f"{where}: its .dockerconfigjson has no 'auths' object (registry -> credentials)")
    return where, auths


def credentials(secrets: list[dict]) -> dict[str, tuple[str, str]]:
    """Registry host -> (username, password) from ``kubernetes.io/dockerconfigjson`` Secrets (raw JSON objects).
    A Secret whose ``.dockerconfigjson`` cannot be read is a KuberosError naming it and its namespace."""
    found = {}
    for secret in secrets:
        if not (secret.get("data") or {}).get(".dockerconfigjson"):
            continue
        where, auths = _auths(secret)
        for host, entry in auths.items():
            if not isinstance(entry, dict):
                raise KuberosError(f"{where}: its .dockerconfigjson's entry for {host!r} is not an object")
            user, password = entry.get("username", ""), entry.get("password", "")
            if not (user or password) and entry.get("auth"):
                try:
                    user, sep, password = base64.b64decode(str(entry["auth"]), validate=True).decode().partition(":")
                except (ValueError, UnicodeDecodeError):
                    sep = ""
                if not sep:
                    raise KuberosError(f"{where}: its .dockerconfigjson's 'auth' for {host!r} is not base64 of user:password")
            if not isinstance(user, str) or not isinstance(password, str):
                raise KuberosError(f"{where}: its .dockerconfigjson's username and password for {host!r} are not strings")
            found[str(host).removeprefix("https://").removeprefix("http://").rstrip("/")] = (user, password)
    return found


def endpoints(host: str, mirrors: dict) -> list[Endpoint]:
    """Where to ask for images of ``host``: its mirrors, then itself. A mirror's credentials are only those given
    under its own address; a plain-http mirror is refused unless it is marked ``insecure: true``."""
    found = []
    for mirror in mirrors.get(host) or []:
        entry = mirror if isinstance(mirror, dict) else {"url": str(mirror)}
        url = str(entry.get("url", ""))
        insecure = entry.get("insecure") is True
        if not url.startswith("https://") and not (insecure and url.startswith("http://")):
            raise KuberosError(
                f"registry mirror {url!r} of {host}: not https; a plain-http mirror must be marked insecure: true "
                "(its answers and any credentials travel unencrypted)"
            )
        address = url.split("://", 1)[1].rstrip("/")
        found.append(Endpoint(address, entry.get("ca") or None, insecure, (address,)))
    own = API_HOSTS.get(host, host)
    return [*found, Endpoint(own, None, False, LOGIN_NAMES.get(host, (own, host)))]


def resolve(images, mirrors: dict | None = None, logins: dict | None = None, realms: dict | None = None) -> dict[str, str]:
    """image -> digest for every image of ``images`` without one; KuberosError naming each that no endpoint resolves.
    A mirror's ``ca`` is a file, or the PEM text itself (as node_prereqs writes it to the nodes). ``realms``:
    registry address -> the hosts of token services elsewhere that may receive its credentials."""
    with tempfile.TemporaryDirectory(prefix="kuberos-registry-ca-") as folder:
        return _resolve(images, _ca_files(mirrors or {}, folder), logins or {}, realms or {})


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


def _login(endpoint: Endpoint, logins: dict) -> tuple[str, str]:
    """The credentials given for this endpoint itself, never another's (a mirror is not sent the upstream's)."""
    for name in endpoint.login_names:
        if name in logins:
            return logins[name]
    return "", ""


def _realms(realms: dict, address: str) -> tuple:
    named = realms.get(address) or ()
    return tuple(urllib.parse.urlsplit(r).hostname or r for r in ([named] if isinstance(named, str) else named))


def _resolve(images, mirrors: dict, logins: dict, realms: dict) -> dict[str, str]:
    digests, problems = {}, []
    for image in image_pins.unpinned(images):
        host, repository, tag = image_pins.registry_and_repository(image)
        tried = []
        for endpoint in endpoints(host, mirrors):
            user, password = _login(endpoint, logins)
            api = RegistryApi(endpoint.address, user, password, endpoint.ca_file, endpoint.insecure,
                              _realms(realms, endpoint.address))  # fmt: skip
            try:
                digests[image] = api.manifest_digest(repository, tag)
                break
            except RegistryError as exc:
                tried.append(str(exc))
        else:
            problems.append(f"{image}: " + "; ".join(tried))
            continue
        if not image_pins.DIGEST.match(digests[image]):
            problems.append(f"{image}: the registry answered {digests.pop(image)[:100]!r}, which is not a digest")
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
    return resolve(images, params.get("registry_mirrors") or {}, credentials(secrets), params.get("registry_token_realms") or {})
