"""The registry client's trust (kuberos_deploy/registry_api.py, image_digests.py) against a hostile registry on
loopback (tests/hostile_registry.py): credentials go only to the origin they were given for, every answer has a size
cap and every request an overall deadline, plain http only where a registry is marked insecure, and a malformed pull
Secret is one sentence naming it. The Kubernetes layer's reads of clusters KubeROS does not run are bounded the
same way."""

from __future__ import annotations

import base64
import json
import time
import tracemalloc

import pytest
from hostile_registry import (
    DIGEST,
    HostileRegistry,
    huge,
    huge_declared,
    manifest,
    manifest_basic,
    redirect_to,
    send,
    token,
    trickle,
)

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import registry_api as api
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube import api as kube_api
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.bounded import ReadBoundExceeded

REPO = "/v2/app/manifests/1.0"


@pytest.fixture
def hostile(tmp_path):
    with HostileRegistry(str(tmp_path)) as server:
        yield server


def client(server, **extra) -> api.RegistryApi:
    return api.RegistryApi(server.address, "alice", "s3cret", server.ca_file, **extra)


def test_a_realm_on_another_host_is_asked_without_the_credentials(hostile):
    hostile.routes = {REPO: manifest, "/token": token}
    hostile.realm = hostile.url("localhost", "/token")  # another origin than 127.0.0.1
    assert client(hostile).manifest_digest("app", "1.0") == DIGEST
    assert hostile.credentials_sent("localhost") == 0
    assert [r for r in hostile.requests if r[1] == "localhost"], "the realm was asked (anonymously)"


def test_a_realm_the_site_names_is_sent_the_credentials(hostile):
    hostile.routes = {REPO: manifest, "/token": token}
    hostile.realm = hostile.url("localhost", "/token")
    assert client(hostile, realms=("localhost",)).manifest_digest("app", "1.0") == DIGEST
    assert hostile.credentials_sent("localhost") == 1


def test_the_registrys_own_realm_is_sent_the_credentials(hostile):
    hostile.routes = {REPO: manifest, "/token": token}
    hostile.realm = hostile.url("127.0.0.1", "/token")
    assert client(hostile).manifest_digest("app", "1.0") == DIGEST
    token_requests = [r for r in hostile.requests if r[2] == "/token"]
    assert token_requests and token_requests[0][3].startswith("Basic ")


def test_a_realm_redirecting_to_another_host_does_not_carry_the_credentials_there(hostile):
    hostile.routes = {REPO: manifest, "/token": redirect_to(hostile.url("localhost", "/stolen")), "/stolen": token}
    hostile.realm = hostile.url("127.0.0.1", "/token")
    assert client(hostile).manifest_digest("app", "1.0") == DIGEST
    assert [r for r in hostile.requests if r[2] == "/stolen"], "the redirect was followed"
    assert hostile.credentials_sent("localhost") == 0


def test_a_redirect_to_plain_http_is_refused(hostile):
    hostile.routes = {REPO: manifest, "/token": redirect_to(f"http://localhost:{hostile.port}/stolen")}
    hostile.realm = hostile.url("127.0.0.1", "/token")
    with pytest.raises(api.RegistryError, match=r"refused its redirect to 'http://localhost:\d+/stolen': not https"):
        client(hostile).manifest_digest("app", "1.0")
    assert not [r for r in hostile.requests if r[2] == "/stolen"]


def test_a_plain_http_realm_is_refused(hostile):
    hostile.routes = {REPO: manifest}
    hostile.realm = f"http://127.0.0.1:{hostile.port}/token"
    with pytest.raises(api.RegistryError, match=r"its token service 'http://127\.0\.0\.1:\d+/token' is not https"):
        client(hostile).manifest_digest("app", "1.0")


def test_a_mirror_without_a_login_of_its_own_is_not_sent_the_upstream_credentials(hostile):
    hostile.routes = {REPO: manifest_basic}
    mirrors = {"ghcr.io": [{"url": hostile.url(), "ca": hostile.ca_file}]}
    logins = {"ghcr.io": ("alice", "s3cret")}
    assert image_digests.resolve(["ghcr.io/app:1.0"], mirrors, logins) == {"ghcr.io/app:1.0": DIGEST}
    assert hostile.credentials_sent("127.0.0.1") == 0
    # its own login, given under its address, is sent
    image_digests.resolve(["ghcr.io/app:1.0"], mirrors, {hostile.address: ("mirror", "pw")})
    assert hostile.credentials_sent("127.0.0.1") == 1


def test_a_plain_http_mirror_is_refused_unless_marked_insecure(tmp_path):
    with HostileRegistry(str(tmp_path), plain=True) as plain:
        plain.routes = {REPO: manifest_basic}
        with pytest.raises(KuberosError, match=r"registry mirror 'http://127.0.0.1:\d+' of ghcr.io: not https"):
            image_digests.resolve(["ghcr.io/app:1.0"], {"ghcr.io": [{"url": plain.url()}]}, {})
        mirrors = {"ghcr.io": [{"url": plain.url(), "insecure": True}]}
        assert image_digests.resolve(["ghcr.io/app:1.0"], mirrors, {}) == {"ghcr.io/app:1.0": DIGEST}


def test_a_huge_token_answer_is_refused_at_its_cap_without_holding_it(hostile):
    hostile.routes = {REPO: manifest, "/token": huge(200 * 1024 * 1024)}
    hostile.realm = hostile.url("127.0.0.1", "/token")
    tracemalloc.start()
    try:
        with pytest.raises(api.RegistryError, match=r"answered with more than 256 KiB \(the size limit of one answer\)"):
            client(hostile).manifest_digest("app", "1.0")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 1024 * 1024, f"peak {peak} bytes"


def test_a_declared_length_over_the_cap_is_refused_before_reading(hostile):
    hostile.routes = {"/v2/": huge_declared(10**12)}
    with pytest.raises(api.RegistryError, match=r"answered with more than 4 MiB"):
        client(hostile).check()


def test_a_head_of_a_large_blob_is_no_answer_over_the_cap(hostile):
    """A HEAD's Content-Length is the size of the blob a GET would send: the lab pushes layers of hundreds of MiB."""

    def large_blob(handler):
        send(handler, 200, {"Content-Length": str(500 * 1024 * 1024), "Docker-Content-Digest": DIGEST})

    hostile.routes = {"/v2/app/blobs/" + DIGEST: large_blob}
    status, _headers, body = client(hostile)._request("HEAD", f"/v2/app/blobs/{DIGEST}", "app", ok=(200, 404))
    assert (status, body) == (200, b"")


@pytest.mark.parametrize("headers_too", [False, True], ids=["body", "headers"])
def test_an_answer_that_trickles_ends_at_the_deadline(hostile, headers_too):
    hostile.routes = {"/v2/": trickle(0.2, 20, headers_too)}
    started = time.monotonic()
    with pytest.raises(api.RegistryError, match=r"gave no complete answer within 1.5 s \(the deadline of one request\)"):
        client(hostile, deadline_s=1.5).check()
    assert time.monotonic() - started < 4


def _secret(config, name="pull", namespace="fleet-a") -> dict:
    raw = config if isinstance(config, bytes) else json.dumps(config).encode()
    return {"metadata": {"name": name, "namespace": namespace}, "data": {".dockerconfigjson": base64.b64encode(raw).decode()}}


@pytest.mark.parametrize(
    "config, why",
    [
        (b"not json", "is not base64-encoded JSON"),
        ([1, 2], "has no 'auths' object"),
        ({"auths": ["x"]}, "has no 'auths' object"),
        ({"auths": {"ghcr.io": "x"}}, "entry for 'ghcr.io' is not an object"),
        ({"auths": {"ghcr.io": {"auth": "%%%"}}}, "'auth' for 'ghcr.io' is not base64 of user:password"),
        ({"auths": {"ghcr.io": {"auth": base64.b64encode(b"nocolon").decode()}}}, "is not base64 of user:password"),
        ({"auths": {"ghcr.io": {"username": 5, "password": []}}}, "are not strings"),
    ],
)
def test_a_malformed_pull_secret_is_one_sentence_naming_it(config, why):
    with pytest.raises(KuberosError, match=rf"pull Secret fleet-a/pull: its \.dockerconfigjson.*{why}"):
        image_digests.credentials([_secret(config)])


def test_a_pull_secret_that_is_not_base64_is_named():
    bad = {"metadata": {"name": "pull", "namespace": "fleet-a"}, "data": {".dockerconfigjson": "not base64 json"}}
    with pytest.raises(KuberosError, match=r"pull Secret fleet-a/pull: its \.dockerconfigjson is not base64-encoded JSON"):
        image_digests.credentials([bad])


# The Kubernetes layer's bounds for clusters KubeROS does not run (kuberos_kube.api: a third-party cluster, the
# metrics API), against the same hostile server speaking as an API server.


def _far_cluster(server, bounds=None):
    from kubernetes import client as k8s

    configuration = k8s.Configuration()
    configuration.host = server.url()
    configuration.retries = 0
    return kube_api.Kube(kube_api.clients_of(k8s.ApiClient(configuration)), name="far", bounds=bounds)


def test_a_third_party_clusters_huge_answer_is_refused_at_its_cap(tmp_path):
    with HostileRegistry(str(tmp_path), plain=True) as server:
        server.routes = {"/api/v1/namespaces/fleet/configmaps": huge(200 * 1024 * 1024)}
        far = _far_cluster(server, kube_api.Bounds(30, 1024 * 1024))
        with pytest.raises(ReadBoundExceeded, match=r"cluster far answered with more than 1 MiB"):
            far.list("ConfigMap", "fleet")
        assert kube_api.Kube({}, name="far").bounds == kube_api.REMOTE_BOUNDS, "a named cluster is bounded by default"


@pytest.mark.parametrize("headers_too", [False, True], ids=["body", "headers"])
def test_a_third_party_cluster_that_trickles_ends_at_the_deadline(tmp_path, headers_too):
    with HostileRegistry(str(tmp_path), plain=True) as server:
        server.routes = {"/api/v1/namespaces/fleet/configmaps": trickle(0.2, 20, headers_too)}
        far = _far_cluster(server, kube_api.Bounds(1.5, 1024 * 1024))
        started = time.monotonic()
        with pytest.raises(ReadBoundExceeded, match=r"cluster far gave no complete answer within 1.5 s"):
            far.list("ConfigMap", "fleet")
        assert time.monotonic() - started < 4
        assert "within 1.5 s" in kube_api.message(ReadBoundExceeded("cluster far gave no complete answer within 1.5 s"))


def test_the_metrics_api_that_trickles_ends_at_its_timeout(tmp_path):
    with HostileRegistry(str(tmp_path), plain=True) as server:
        server.routes = {"/apis/metrics.k8s.io/v1beta1/namespaces/fleet/pods": trickle(0.2, 20)}
        own = _far_cluster(server)
        own.name, own.bounds = "", None  # the site's own API server: only the metrics API is bounded
        started = time.monotonic()
        with pytest.raises(ReadBoundExceeded, match=r"the API server gave no complete answer within 1 s"):
            own.pod_metrics("fleet", timeout=1)
        assert time.monotonic() - started < 3.5


def test_the_controllers_metrics_reads_have_a_deadline_and_a_cap(tmp_path):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import signals

    with HostileRegistry(str(tmp_path), plain=True) as server:
        server.routes = {"/slow": trickle(0.2, 20), "/big": huge(64 * 1024 * 1024)}
        started = time.monotonic()
        with pytest.raises(OSError, match=r"127.0.0.1:\d+ gave no complete answer within 1 s"):
            signals._get(server.url(path="/slow"), 1.0)
        assert time.monotonic() - started < 3
        with pytest.raises(OSError, match=r"answered with more than 4 MiB"):
            signals._get(server.url(path="/big"), 10.0)
