"""Images pinned by digest (kuberos_deploy/image_digests.py) against a real registry: the CNCF distribution registry
(Debian's docker-registry) with TLS and htpasswd on loopback, and a token service as Docker Hub and GHCR run them.

Checks: a tag resolves to the digest the registry serves, through a mirror for another registry's name as the nodes'
containerd asks it, with the credentials of a pull secret; a tag that moves resolves to the new digest; an image no
endpoint resolves is one line naming the image, each endpoint and why; a registry that answers with a bearer
challenge admits the token its realm hands out for the pull secret's credentials, and refuses without them.
"""

from __future__ import annotations

import base64
import http.server
import json
import os
import shutil
import ssl
import threading

import pytest
from oci import free_port, write_archive

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import registry as lab_registry
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

pytestmark = pytest.mark.skipif(
    not shutil.which("docker-registry") and not os.environ.get("CI"),
    reason="docker-registry is not installed (scripts/setup.sh installs it)",
)


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    running = lab_registry.LocalRegistry(str(tmp_path_factory.mktemp("registry") / "state"), "127.0.0.1", free_port())
    try:
        assert running.start() is True
        yield running
    finally:
        running.stop(remove=True)


def pull_secret(address: str, username: str, password: str) -> dict:
    config = lab_registry.docker_config_json(address, username, password)
    return {"metadata": {"name": "lab"}, "data": {".dockerconfigjson": base64.b64encode(config.encode()).decode()}}


def test_a_tag_resolves_through_the_mirror_with_the_pull_secrets_credentials_and_follows_a_moved_tag(registry, tmp_path):
    client = registry.client()
    first = write_archive(str(tmp_path / "one.tar"), b"first build\n")
    second = write_archive(str(tmp_path / "two.tar"), b"second build\n")
    assert client.push_archive(str(tmp_path / "one.tar"), "kuberos/pinned", "1.0")[0] == first
    with open(registry.ca_file, encoding="utf-8") as handle:
        ca = handle.read()
    # ghcr.io is not reachable here: the mirror answers first, as the nodes' containerd asks it
    mirrors = {"ghcr.io": [{"url": f"https://{registry.address}", "ca": ca}]}
    logins = image_digests.credentials([pull_secret(registry.address, registry.username, registry.password)])
    assert image_digests.resolve(["ghcr.io/kuberos/pinned:1.0"], mirrors, logins) == {"ghcr.io/kuberos/pinned:1.0": first}
    # an image with a digest already is not asked for
    assert image_digests.resolve([f"ghcr.io/kuberos/pinned:1.0@{first}"], mirrors, logins) == {}
    client.push_archive(str(tmp_path / "two.tar"), "kuberos/pinned", "1.0")  # the tag moves
    assert image_digests.resolve(["ghcr.io/kuberos/pinned:1.0"], mirrors, logins) == {"ghcr.io/kuberos/pinned:1.0": second}


def test_an_image_nobody_resolves_names_every_endpoint_and_why(registry):
    with open(registry.ca_file, encoding="utf-8") as handle:
        mirrors = {"ghcr.io": [{"url": f"https://{registry.address}", "ca": handle.read()}]}
    # every registry named here is on loopback: the mirror, then the registry itself (a port nobody listens on)
    closed = f"127.0.0.1:{free_port()}"
    mirrors = {closed: mirrors["ghcr.io"]}
    with pytest.raises(KuberosError) as caught:
        image_digests.resolve([f"{closed}/kuberos/absent:9.9"], mirrors, {})
    text = str(caught.value)
    assert text.startswith("cannot pin every image to its digest, so nothing was applied")
    assert f"- {closed}/kuberos/absent:9.9: registry {registry.address}: refused the credentials (anonymous access" in text
    assert f"; registry {closed}: cannot connect" in text, text


class _TokenRegistry(http.server.BaseHTTPRequestHandler):
    """A registry that admits a bearer token only, and the token service that issues one for user:secret."""

    digest = "sha256:" + "ab" * 32

    def log_message(self, *args):
        pass

    def do_GET(self):
        if self.path.startswith("/token?"):
            if self.headers.get("Authorization") != "Basic " + base64.b64encode(b"user:secret").decode():
                self.send_response(401)
                self.end_headers()
                return
            body = json.dumps({"token": "issued-token"}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
            return
        self.send_response(404)
        self.end_headers()

    def do_HEAD(self):
        if self.headers.get("Authorization") == "Bearer issued-token" and self.path == "/v2/team/app/manifests/2.0":
            self.send_response(200)
            self.send_header("Docker-Content-Digest", self.digest)
            self.end_headers()
            return
        host, port = self.server.server_address[:2]
        self.send_response(401)
        self.send_header(
            "WWW-Authenticate",
            f'Bearer realm="https://{host}:{port}/token",service="lab",scope="repository:team/app:pull"',
        )
        self.end_headers()


@pytest.fixture
def token_registry(tmp_path):
    ca_cert, ca_key = pki.new_ca("token registry CA", days=1)
    cert, key = pki.issue(ca_cert, ca_key, "127.0.0.1", usage=pki.SERVER, days=1, alt_names=["127.0.0.1"])
    for name, obj in (("ca.crt", ca_cert), ("tls.crt", cert), ("tls.key", key)):
        pki.write_pem(str(tmp_path / name), obj)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _TokenRegistry)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(str(tmp_path / "tls.crt"), str(tmp_path / "tls.key"))
    server.socket = context.wrap_socket(server.socket, server_side=True)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"127.0.0.1:{server.server_address[1]}", str(tmp_path / "ca.crt")
    finally:
        server.shutdown()
        server.server_close()


def test_a_registry_that_asks_for_a_bearer_token_gets_one_for_the_pull_secrets_credentials(token_registry):
    address, ca_file = token_registry
    named = f"127.0.0.1:{free_port()}"  # the registry's own name: on loopback, nobody listening
    mirrors = {named: [{"url": f"https://{address}", "ca": ca_file}]}
    image = f"{named}/team/app:2.0"
    logins = {address: ("user", "secret")}
    assert image_digests.resolve([image], mirrors, logins) == {image: _TokenRegistry.digest}
    with pytest.raises(KuberosError, match=rf"registry {address}: refused the credentials"):
        image_digests.resolve([image], mirrors, {address: ("user", "wrong")})
