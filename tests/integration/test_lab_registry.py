"""The lab's registry (plugins/module_utils/kuberos_lab/registry.py): the real CNCF distribution registry
(Debian's docker-registry) with TLS and htpasswd, on loopback, and the client that pushes OCI archives by digest.

Checks: the registry answers only over TLS with its own CA and only with the password; an archive pushed is
served under the archive's own manifest digest, by tag and by digest; pushing again uploads nothing; a wrong
password, an unknown image, an unknown repository and an untrusted certificate are each one sentence naming the
registry and the image; stop ends the process and remove leaves nothing.
"""

from __future__ import annotations

import json
import os
import shutil

import pytest
from oci import free_port, write_archive

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import registry as lab_registry

pytestmark = [
    pytest.mark.skipif(
        not shutil.which("docker-registry") and not os.environ.get("CI"),
        reason="docker-registry is not installed (scripts/setup.sh installs it)",
    ),
    pytest.mark.host,  # a containerd of its own pulls from the registry
]


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


def test_pull_secrets():
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


@pytest.mark.skipif(not shutil.which("containerd") and not os.environ.get("CI"), reason="containerd is not installed")
def test_containerd_pulls_by_digest_trusting_the_ca_of_hosts_toml_and_a_missing_digest_reads_not_found(registry, tmp_path):
    """A containerd of the test's own with the registry's hosts.toml (as every real node has it): the image by
    digest with the password; a digest the registry lacks is 'not found', not a certificate error (containerd
    asks the default server again after a 404, which must trust the CA too)."""
    import signal
    import subprocess
    import time

    archive = str(tmp_path / "pulled.tar")
    digest = write_archive(archive, b"pulled by containerd\n")
    registry.client().push_archive(archive, "kuberos/pulled", "1")
    root = tmp_path / "ctd"
    hosts = root / "certs.d" / registry.address
    hosts.mkdir(parents=True)
    (hosts / "hosts.toml").write_text(registry.containerd_hosts(), encoding="utf-8")
    socket_path = f"/tmp/kuberos-ctd-{os.getpid()}.sock"  # sun_path is short
    (root / "config.toml").write_text(
        f'version = 2\nroot = "{root}/root"\nstate = "{root}/state"\n[grpc]\n  address = "{socket_path}"\n', encoding="utf-8"
    )
    with open(root / "log", "wb") as log:
        daemon = subprocess.Popen(["containerd", "--config", str(root / "config.toml")], stdout=log, stderr=subprocess.STDOUT,
                                  start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 30
        while subprocess.run(["ctr", "-a", socket_path, "version"], capture_output=True).returncode != 0:
            assert time.monotonic() < deadline and daemon.poll() is None, (root / "log").read_text()[-2000:]
            time.sleep(0.2)

        def pull(reference: str) -> subprocess.CompletedProcess:
            return subprocess.run(
                ["ctr", "-a", socket_path, "-n", "test", "images", "pull", "--hosts-dir", str(root / "certs.d"),
                 "--user", f"{registry.username}:{registry.password}", reference],
                capture_output=True, text=True, timeout=120,
            )  # fmt: skip

        good = pull(f"{registry.address}/kuberos/pulled@{digest}")
        assert good.returncode == 0, good.stderr[-2000:]
        missing = pull(f"{registry.address}/kuberos/pulled@sha256:{'0' * 64}")
        assert missing.returncode != 0 and missing.stderr.rstrip().endswith("not found"), missing.stderr[-2000:]
        assert "x509" not in missing.stderr and "certificate" not in missing.stderr
    finally:
        os.killpg(daemon.pid, signal.SIGTERM)
        daemon.wait(timeout=30)
        subprocess.run(["umount", "-R", str(root)], capture_output=True, check=False)


def test_a_derived_image_shares_the_layers_and_changes_only_its_configuration(registry, tmp_path):
    archive = str(tmp_path / "source.tar")
    digest = write_archive(archive, b"a program\n")
    client = registry.client()
    client.push_archive(archive, "kuberos/derived", "1")
    derived = client.derive_image("kuberos/derived", digest, "1-broken", Entrypoint=["/bin/false"])
    assert derived != digest
    assert client.manifest_digest("kuberos/derived", "1-broken") == derived
    assert client.manifest_digest("kuberos/derived", derived) == derived


def test_the_lab_keeps_a_built_image_under_kuberos_and_its_key():
    assert lab_registry.lab_repository("kuberos.local/ros:0123456789ab") == ("kuberos/ros", "0123456789ab")
    assert lab_registry.lab_repository("kuberos.local/ros-base:ba5e0123abcd") == ("kuberos/ros-base", "ba5e0123abcd")
    assert lab_registry.lab_repository("kuberos.local/pause:3.10") == ("kuberos/pause", "3.10")
