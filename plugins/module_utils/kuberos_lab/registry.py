"""A real container registry for the lab, and a client of the registry API (an I/O module of the local lab).

`LocalRegistry` runs the CNCF distribution registry (Debian's ``docker-registry``, distribution 2.8) as a
background process: TLS with a certificate of the registry's own CA (``ca.crt``: what containerd and clients
trust), htpasswd authentication (bcrypt, one user, a password generated once and kept 0600 in the state
directory), storage on the filesystem. Everything is under its ``directory``; `stop` ends the process and,
with ``remove``, deletes the directory.

`RegistryClient` speaks the registry HTTP API v2 over TLS with basic authentication: it pushes an OCI image
archive (as ``local_images`` writes them) blob by blob and then its manifest, byte for byte, so the digest
the registry serves is the archive's own, and checks that an image exists. Every failure is a `RegistryError`
whose message names the registry and the image and says why (refused credentials, unknown image, no
connection, an untrusted certificate).

No Kubernetes client: the registry API client of deploy (``kuberos_deploy/registry_api.py``), ``cryptography`` (the one PKI)
and ``bcrypt``.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import secrets
import shutil
import tarfile
import time
import urllib.parse
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.registry_api import (
    DEADLINE_S,
    MANIFEST_TYPES,
    RegistryApi,
    RegistryError,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import background_process as bg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

PROGRAM = "docker-registry"
CERT_DAYS = 365
START_TIMEOUT = 30.0
CHUNK = 1 << 20
UPLOAD_BYTES_PER_S = 1 << 20  # the slowest upload a blob's deadline allows for (beyond the usual deadline)


def image_reference(address: str, repository: str, digest: str) -> str:
    """``<address>/<repository>@<digest>``: how pods name an image pulled by digest."""
    return f"{address}/{repository}@{digest}"


def lab_repository(reference: str) -> tuple[str, str]:
    """(repository, tag) under which the lab registry keeps a built image: ``kuberos.local/ros:<key>`` is
    ``kuberos/ros`` tagged ``<key>``."""
    name, _sep, tag = reference.split("/", 1)[-1].rpartition(":")
    return f"kuberos/{name}", tag


def docker_config_json(address: str, username: str, password: str) -> str:
    """The content of a ``kubernetes.io/dockerconfigjson`` Secret's ``.dockerconfigjson`` for one registry."""
    auth = base64.b64encode(f"{username}:{password}".encode()).decode()
    return json.dumps({"auths": {address: {"username": username, "password": password, "auth": auth}}}, sort_keys=True)


OCI_LAYER = "application/vnd.oci.image.layer.v1.tar+gzip"


def _random_layer(size: int) -> tuple[bytes, str]:
    """A gzipped tar layer holding one file of ``size`` random bytes, and its diff id (the uncompressed tar's digest)."""
    import gzip
    import io

    data = os.urandom(size)
    raw = io.BytesIO()
    with tarfile.open(fileobj=raw, mode="w", format=tarfile.PAX_FORMAT) as archive:
        info = tarfile.TarInfo("opt/kuberos-lab/payload.bin")
        info.size, info.mode, info.mtime = size, 0o644, 0
        archive.addfile(info, io.BytesIO(data))
    tar = raw.getvalue()
    return gzip.compress(tar, compresslevel=1, mtime=0), "sha256:" + hashlib.sha256(tar).hexdigest()


class RegistryClient(RegistryApi):
    """The lab's registry client: the API's reads (``RegistryApi``), and pushes of the lab's images."""

    def derive_image(self, repository: str, digest: str, tag: str, extra_bytes: int = 0, **config) -> str:
        """A new image in ``repository`` from the one at ``digest``: the same layers, its configuration's
        ``config`` fields replaced (``Entrypoint=[...]``, ``Cmd=[...]``, ``Env=[...]``); tagged ``tag``. Returns
        the new manifest's digest. (How the lab makes a second version of an image without building it again.)
        ``extra_bytes``: one more layer, a file of that many random bytes, which a node must download (its content is
        nowhere else), as a new version of an application brings."""
        image = f"{self.address}/{repository}@{digest}"
        manifest = json.loads(self._get(f"/v2/{repository}/manifests/{digest}", image, ", ".join(MANIFEST_TYPES)))
        configuration = json.loads(self._get(f"/v2/{repository}/blobs/{manifest['config']['digest']}", image))
        configuration.setdefault("config", {}).update(config)
        if extra_bytes:
            layer, diff_id = _random_layer(extra_bytes)
            blob = "sha256:" + hashlib.sha256(layer).hexdigest()
            if not self._has_blob(repository, blob, image):
                self._upload_blob(repository, blob, len(layer), layer, image)
            media_type = manifest["layers"][-1]["mediaType"] if manifest.get("layers") else OCI_LAYER
            manifest["layers"] = [*manifest.get("layers", []), {"mediaType": media_type, "digest": blob, "size": len(layer)}]
            configuration.setdefault("rootfs", {"type": "layers", "diff_ids": []})["diff_ids"].append(diff_id)
            configuration.setdefault("history", []).append({"created_by": f"kuberos lab: {extra_bytes} random bytes"})
        data = json.dumps(configuration, sort_keys=True).encode()
        blob = "sha256:" + hashlib.sha256(data).hexdigest()
        if not self._has_blob(repository, blob, image):
            self._upload_blob(repository, blob, len(data), data, image)
        manifest["config"] = {**manifest["config"], "digest": blob, "size": len(data)}
        body = json.dumps(manifest, sort_keys=True).encode()
        media_type = manifest.get("mediaType") or MANIFEST_TYPES[0]
        self._request(
            "PUT", f"/v2/{repository}/manifests/{tag}", image, body=body, ok=(201,), headers={"Content-Type": media_type}
        )
        return "sha256:" + hashlib.sha256(body).hexdigest()

    def _has_blob(self, repository: str, digest: str, image: str) -> bool:
        status, _headers, _body = self._request("HEAD", f"/v2/{repository}/blobs/{digest}", image, ok=(200, 404))
        return status == 200

    def _mount_blob(self, repository: str, digest: str, source: str, image: str) -> bool:
        """Link a blob the registry holds under ``source`` into ``repository`` without sending it again."""
        query = urllib.parse.urlencode({"mount": digest, "from": source})
        status, _headers, _body = self._request(
            "POST", f"/v2/{repository}/blobs/uploads/?{query}", image, body=b"", ok=(201, 202)
        )
        return status == 201

    def _upload_blob(self, repository: str, digest: str, size: int, stream, image: str) -> None:
        _status, headers, _body = self._request("POST", f"/v2/{repository}/blobs/uploads/", image, body=b"", ok=(202,))
        location = headers.get("Location", "")
        if not location:
            raise RegistryError(f"registry {self.address}: no upload location for image {image}")
        url = urllib.parse.urljoin(f"https://{self.address}/", location)
        url += ("&" if "?" in url else "?") + urllib.parse.urlencode({"digest": digest})
        self._request(
            "PUT", url, image, body=stream, ok=(201,),
            headers={"Content-Type": "application/octet-stream", "Content-Length": str(size)},
            deadline_s=DEADLINE_S + size / UPLOAD_BYTES_PER_S,
        )  # fmt: skip

    def push_archive(
        self, archive: str, repository: str, tag: str | None = None, mount_from: str | None = None
    ) -> tuple[str, dict]:
        """Push the one image of an OCI archive to ``repository`` (its blobs, then its manifest under ``tag``, or
        under its digest). Returns the manifest digest and what was done: blobs uploaded and skipped, bytes.
        ``mount_from``: a repository of this registry that may hold the blobs already (linked, not sent again)."""
        with tarfile.open(archive, "r:") as tar:
            members = {m.name.lstrip("./"): m for m in tar.getmembers()}

            def read(name: str) -> bytes:
                member = members.get(name)
                if member is None:
                    raise RegistryError(f"{archive}: no {name} (not an OCI archive written by local_images)")
                return tar.extractfile(member).read()

            (descriptor,) = json.loads(read("index.json"))["manifests"]
            digest = descriptor["digest"]
            image = f"{self.address}/{repository}@{digest}"
            manifest_bytes = read(f"blobs/{digest.replace(':', '/')}")
            if "sha256:" + hashlib.sha256(manifest_bytes).hexdigest() != digest:
                raise RegistryError(f"{archive}: the manifest does not match its digest {digest}")
            manifest = json.loads(manifest_bytes)
            done = {"uploaded": 0, "skipped": 0, "bytes": 0}
            for blob in [manifest["config"], *manifest["layers"]]:
                if self._has_blob(repository, blob["digest"], image) or (
                    mount_from and self._mount_blob(repository, blob["digest"], mount_from, image)
                ):
                    done["skipped"] += 1
                    continue
                member = members[f"blobs/{blob['digest'].replace(':', '/')}"]
                self._upload_blob(repository, blob["digest"], member.size, tar.extractfile(member), image)
                done["uploaded"] += 1
                done["bytes"] += member.size
            media_type = manifest.get("mediaType") or descriptor.get("mediaType") or MANIFEST_TYPES[0]
            _status, headers, _body = self._request(
                "PUT", f"/v2/{repository}/manifests/{tag or digest}", image, body=manifest_bytes, ok=(201,),
                headers={"Content-Type": media_type},
            )  # fmt: skip
        served = headers.get("Docker-Content-Digest", digest)
        if served != digest:
            raise RegistryError(f"registry {self.address}: stored {image} as {served}, not as its own digest")
        return digest, done


@dataclass
class LocalRegistry:
    """The lab's registry: state under ``directory``, listening on ``host:port`` (TLS, htpasswd)."""

    directory: str
    host: str
    port: int = 5443
    username: str = "kuberos"
    auth: bool = True  # False: pulls need no credentials, as from a site's internal mirror (pushes neither)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def path(self, *parts: str) -> str:
        return os.path.join(self.directory, *parts)

    @property
    def ca_file(self) -> str:
        return self.path("ca.crt")

    @property
    def password(self) -> str:
        with open(self.path("password"), encoding="utf-8") as handle:
            return handle.read().strip()

    def client(self, username: str | None = None, password: str | None = None) -> RegistryClient:
        """A client of this registry (its own credentials unless others are given)."""
        return RegistryClient(
            self.address,
            self.username if username is None else username,
            self.password if password is None else password,
            self.ca_file,
        )

    def _marker(self, argv: list[str]) -> bool:
        return any(self.path("config.yml") == part for part in argv)

    def pid(self) -> int | None:
        return bg.running_pid(self.path("registry.pid"), self._marker)

    @staticmethod
    def problems() -> list[str]:
        return [] if shutil.which(PROGRAM) else [f"`{PROGRAM}` is not installed (Debian package docker-registry)"]

    def _files(self) -> None:
        """CA, serving certificate, htpasswd and configuration; made once, kept across restarts."""
        os.makedirs(self.path("storage"), exist_ok=True)
        os.chmod(self.directory, 0o700)
        if not os.path.exists(self.path("ca.key")):
            ca_cert, ca_key = pki.new_ca("kuberos lab registry CA", days=CERT_DAYS)
            pki.write_pem(self.path("ca.key"), ca_key)
            pki.write_pem(self.ca_file, ca_cert)
        if not os.path.exists(self.path("registry.key")):
            ca_cert, ca_key = pki.load_ca(self.ca_file, self.path("ca.key"))
            cert, key = pki.issue(ca_cert, ca_key, self.host, usage=pki.SERVER, days=CERT_DAYS, alt_names=[self.host])
            pki.write_pem(self.path("registry.key"), key)
            pki.write_pem(self.path("registry.crt"), cert)
        if not os.path.exists(self.path("password")):
            _write_secret(self.path("password"), secrets.token_urlsafe(18) + "\n")
        if not os.path.exists(self.path("htpasswd")):
            import bcrypt

            hashed = bcrypt.hashpw(self.password.encode(), bcrypt.gensalt(rounds=10)).decode()
            _write_secret(self.path("htpasswd"), f"{self.username}:{hashed}\n")
        if not os.path.exists(self.path("http-secret")):
            _write_secret(self.path("http-secret"), secrets.token_hex(16) + "\n")
        with open(self.path("http-secret"), encoding="utf-8") as handle:
            http_secret = handle.read().strip()
        config = {
            "version": 0.1,
            "log": {"level": "info", "formatter": "text"},
            "storage": {
                "filesystem": {"rootdirectory": self.path("storage")},
                "delete": {"enabled": True},
                "maintenance": {"uploadpurging": {"enabled": False}},
            },
            "http": {
                "addr": self.address,
                "secret": http_secret,
                "tls": {"certificate": self.path("registry.crt"), "key": self.path("registry.key")},
                "headers": {"X-Content-Type-Options": ["nosniff"]},
            },
        }
        if self.auth:
            config["auth"] = {"htpasswd": {"realm": "kuberos-lab", "path": self.path("htpasswd")}}
        _write_secret(self.path("config.yml"), json.dumps(config, indent=1) + "\n")  # JSON is YAML

    def start(self) -> bool:
        """Run the registry (True when it was started); it answers with the credentials before this returns."""
        problems = self.problems()
        if problems:
            raise RegistryError("the lab registry cannot run here: " + "; ".join(problems))
        self._files()
        if self.pid() is not None:
            return False
        process = bg.start([PROGRAM, "serve", self.path("config.yml")], self.path("registry.pid"), self.path("registry.log"))
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            try:
                self.client().check()
                return True
            except RegistryError as error:
                # The child itself, not the pid file's check of its command line: until it has exec'd the registry,
                # its command line is still this program's, and a busy machine showed that as "not running".
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RegistryError(
                        f"the lab registry did not answer on {self.address} ({error}); {self.path('registry.log')}:\n"
                        + bg.tail(self.path("registry.log"))
                    ) from None
            time.sleep(0.2)

    def stop(self, remove: bool = False) -> bool:
        """Stop the registry; ``remove``: also its state (images, credentials, certificates)."""
        changed = bg.stop(self.path("registry.pid"), self._marker) is not None
        if remove and os.path.isdir(self.directory):
            shutil.rmtree(self.directory)
            changed = True
        return changed

    def containerd_hosts(self) -> str:
        """containerd's ``hosts.toml`` for this registry (under ``<config_path>/<address>/``): trust its CA, in the
        ``[host]`` section and for the default server at the top level: containerd asks the default server again
        when a host answers 404, and without the CA there a missing image would read as a TLS failure
        (containerd 1.6 refuses a file without a ``[host]`` section)."""
        return "\n".join(
            [
                f'server = "https://{self.address}"',
                f'ca = "{self.ca_file}"',
                "",
                f'[host."https://{self.address}"]',
                '  capabilities = ["pull", "resolve"]',
                f'  ca = "{self.ca_file}"',
                "",
            ]
        )


def _write_secret(path: str, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(text)
