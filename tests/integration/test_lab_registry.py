"""The lab's registry (plugins/module_utils/kuberos_lab/registry.py): the real CNCF distribution registry
(Debian's docker-registry) with TLS and htpasswd, on loopback, and the client that pushes OCI archives by digest.

Checks: the registry answers only over TLS with its own CA and only with the password; an archive pushed is
served under the archive's own manifest digest, by tag and by digest; pushing again uploads nothing; a wrong
password, an unknown image, an unknown repository and an untrusted certificate are each one sentence naming the
registry and the image; stop ends the process and remove leaves nothing.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import json
import os
import shutil
import socket
import tarfile

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import registry as lab_registry

pytestmark = pytest.mark.skipif(
    not shutil.which("docker-registry") and not os.environ.get("CI"),
    reason="docker-registry is not installed (scripts/setup.sh installs it)",
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def write_archive(path: str, content: bytes) -> str:
    """A one-layer OCI image archive as local_images writes them (index.json, blobs); its manifest digest."""
    blobs: dict[str, bytes] = {}

    def add(data: bytes) -> dict:
        digest = "sha256:" + hashlib.sha256(data).hexdigest()
        blobs[digest] = data
        return {"digest": digest, "size": len(data)}

    layer = io.BytesIO()
    with tarfile.open(fileobj=layer, mode="w") as tar:
        info = tarfile.TarInfo("hello.txt")
        info.size, info.mtime = len(content), 946684800
        tar.addfile(info, io.BytesIO(content))
    raw = layer.getvalue()
    compressed = gzip.compress(raw, mtime=0)
    diff_id = "sha256:" + hashlib.sha256(raw).hexdigest()
    config = {"architecture": "amd64", "os": "linux", "rootfs": {"type": "layers", "diff_ids": [diff_id]}, "config": {}}
    manifest = {
        "schemaVersion": 2,
        "mediaType": "application/vnd.oci.image.manifest.v1+json",
        "config": {"mediaType": "application/vnd.oci.image.config.v1+json", **add(json.dumps(config).encode())},
        "layers": [{"mediaType": "application/vnd.oci.image.layer.v1.tar+gzip", **add(compressed)}],
    }
    descriptor = {"mediaType": "application/vnd.oci.image.manifest.v1+json", **add(json.dumps(manifest).encode())}
    index = {"schemaVersion": 2, "manifests": [descriptor]}
    with tarfile.open(path, "w") as tar:
        for name, data in [("oci-layout", b'{"imageLayoutVersion":"1.0.0"}'), ("index.json", json.dumps(index).encode())] + [
            (f"blobs/{digest.replace(':', '/')}", data) for digest, data in blobs.items()
        ]:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return descriptor["digest"]


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    directory = tmp_path_factory.mktemp("registry")
    running = lab_registry.LocalRegistry(str(directory / "state"), "127.0.0.1", free_port())
    try:
        assert running.start() is True
        yield running
    finally:
        running.stop(remove=True)


def test_an_archive_is_served_by_its_own_digest_and_a_second_push_uploads_nothing(registry, tmp_path):
    archive = str(tmp_path / "hello.tar")
    digest = write_archive(archive, b"hello from the lab registry\n")
    client = registry.client()
    pushed, done = client.push_archive(archive, "kuberos/hello", "1.0")
    assert pushed == digest and done["uploaded"] == 2 and done["skipped"] == 0
    assert client.manifest_digest("kuberos/hello", "1.0") == digest
    assert client.manifest_digest("kuberos/hello", digest) == digest
    again, done = client.push_archive(archive, "kuberos/hello", "1.0")
    assert again == digest and done == {"uploaded": 0, "skipped": 2, "bytes": 0}
    assert registry.start() is False, "starting a running registry changes nothing"


def test_a_wrong_password_is_one_sentence_naming_the_registry_and_the_image(registry):
    with pytest.raises(lab_registry.RegistryError) as caught:
        registry.client(password="not-the-password").manifest_digest("kuberos/hello", "1.0")
    message = str(caught.value)
    assert message == (
        f"registry {registry.address}: refused the credentials (user 'kuberos': HTTP 401 Unauthorized) "
        f"for image {registry.address}/kuberos/hello:1.0"
    )
    with pytest.raises(lab_registry.RegistryError, match="anonymous access: HTTP 401"):
        registry.client(username="", password="").check()


@pytest.mark.parametrize("repository, reference", [("kuberos/hello", "9.9"), ("kuberos/nothing-here", "1.0")])
def test_an_unknown_image_is_one_sentence_naming_the_registry_and_the_image(registry, repository, reference):
    with pytest.raises(lab_registry.RegistryError) as caught:
        registry.client().manifest_digest(repository, reference)
    assert str(caught.value).startswith(
        f"registry {registry.address}: image {registry.address}/{repository}:{reference} not found"
    )


def test_a_registry_whose_ca_is_not_given_is_not_trusted(registry):
    client = lab_registry.RegistryClient(registry.address, registry.username, registry.password, ca_file=None)
    with pytest.raises(lab_registry.RegistryError, match=r"its certificate is not trusted .*give the registry's CA"):
        client.manifest_digest("kuberos/hello", "1.0")


def test_nothing_answers_on_a_closed_port():
    client = lab_registry.RegistryClient(f"127.0.0.1:{free_port()}", "kuberos", "x")
    with pytest.raises(lab_registry.RegistryError, match=r"cannot connect .*Connection refused"):
        client.check()


def test_references_and_pull_secrets():
    assert lab_registry.split_reference("10.1.0.1:5443/kuberos/ros@sha256:ab") == ("10.1.0.1:5443", "kuberos/ros", "sha256:ab")
    assert lab_registry.split_reference("registry.example.com/team/planner:2.1") == (
        "registry.example.com", "team/planner", "2.1",
    )  # fmt: skip
    assert lab_registry.split_reference("localhost/app") == ("localhost", "app", "latest")
    with pytest.raises(lab_registry.RegistryError, match="expected <registry host"):
        lab_registry.split_reference("ros:jazzy-ros-base")
    config = json.loads(lab_registry.docker_config_json("10.1.0.1:5443", "kuberos", "s3cret"))
    assert config == {"auths": {"10.1.0.1:5443": {"username": "kuberos", "password": "s3cret", "auth": "a3ViZXJvczpzM2NyZXQ="}}}


def test_stop_ends_the_process_and_remove_leaves_nothing(tmp_path):
    running = lab_registry.LocalRegistry(str(tmp_path / "state"), "127.0.0.1", free_port())
    running.start()
    pid = running.pid()
    assert pid is not None
    assert oct(os.stat(running.path("password")).st_mode & 0o777) == "0o600"
    assert running.stop(remove=True) is True
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
    assert not os.path.exists(running.directory)
    assert running.stop() is False
