"""Fuzzing the registry client's answers: a hostile registry on loopback (tests/hostile_registry.py) answers the
manifest, the token service and two more paths with drawn statuses, headers (WWW-Authenticate challenges, Location,
Content-Length, Docker-Content-Digest) and bodies. Each case gives a digest or one ``RegistryError`` naming the
registry (through ``image_digests.resolve``: digests of the right shape, or one ``KuberosError`` naming the image),
within the tier's bounds; the user's password never reaches another origin.

Connections go to the loopback registry only: a drawn Location or realm naming any other host or port is refused at
connect (``socket.create_connection``, after the host name is encoded as the real resolver does, so a name it cannot
encode still fails as it would), so no case reaches a real network or another local service.
"""

from __future__ import annotations

import contextlib
import json
import socket

from fuzz_bounds import fuzz_settings, run_case
from hostile_registry import DIGEST, HostileRegistry, closed_port
from hypothesis import given
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import image_pins
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import registry_api as api

MANIFEST = "/v2/app/manifests/1.0"
PATHS = (MANIFEST, "/token", "/r1", "/r2")
UPSTREAM = "upstream.invalid"  # the image's own registry, which the mirror stands in for (never reached)
STATUSES = [200, 200, 200, 201, 204, 100, 101, 301, 302, 303, 307, 308, 400, 401, 401, 403, 404, 429, 500, 502, 599, 999]


@contextlib.contextmanager
def loopback_only(port: int):
    """``socket.create_connection`` reaching ``127.0.0.1``/``localhost`` at ``port`` only; other places refused."""
    real = socket.create_connection

    def connect(address, *args, **kwargs):
        host, wanted = address[0], address[1]
        if isinstance(host, str):
            host.encode("idna")  # what the resolver does first: UnicodeError for a name it cannot encode
        if host not in ("127.0.0.1", "localhost") or wanted != port:
            raise ConnectionRefusedError(f"[fuzz] {host}:{wanted} is not the loopback registry")
        return real(address, *args, **kwargs)

    socket.create_connection = connect
    try:
        yield
    finally:
        socket.create_connection = real


def _header_text(value: str) -> str:
    """What a server can put in a header: latin-1, no line break (the header would end there)."""
    return value.encode("latin-1", "replace").decode("latin-1").replace("\r", "").replace("\n", "")


def locations(port: int):
    return st.one_of(
        st.sampled_from([
            "/r1", "/r2", "/token", MANIFEST, "r1", "../r2", "?x=1", "#frag", "",
            f"https://127.0.0.1:{port}/r1", f"https://localhost:{port}/r1", f"http://127.0.0.1:{port}/r1",
            f"HTTPS://127.0.0.1:{port}/r2", f"https://127.0.0.1:{closed_port()}/x", "https://127.0.0.1:99999/x",
            "https://127.0.0.1:-1/x", "https://127.0.0.1:abc/x", "https://evil.invalid/steal", "//evil.invalid/x",
            "https://a..b/", "https://" + "a" * 64 + "/", "https://[::1/", "https:///x", "https://@/x",
            "https://user:pw@127.0.0.1/x", "mailto:x", "file:///etc/passwd", "javascript:x", "/\t/", "/%00",
            "/" + "a" * 70_000, "https://ä.invalid/", "https://\u2028/",
        ]),
        st.text(max_size=30),
    )  # fmt: skip


def challenges(port: int):
    realm = st.one_of(
        st.sampled_from([
            f"https://127.0.0.1:{port}/token", f"https://localhost:{port}/token", f"http://127.0.0.1:{port}/token",
            f"https://127.0.0.1:{port}/r1?a=b", "https://evil.invalid/token", "", "token", "ftp://x", "https://",
            f"https://127.0.0.1:{port}/token\x1b[2J", "https://" + "a" * 10_000,
        ]),
        st.text(max_size=20),
    )  # fmt: skip
    return st.one_of(
        st.builds(
            lambda r, service, scope: f'Bearer realm="{r}",service="{service}",scope="{scope}"',
            realm,
            st.sampled_from(["hostile", "", "a\x00b"]),
            st.sampled_from(["repository:app:pull", "", "x" * 5000]),
        ),
        st.sampled_from(['Basic realm="x"', "Bearer", "bearer realm=x", 'Bearer realm="', "Negotiate", "", "Bearer " * 1000]),
        st.text(max_size=40),
    )


bodies = st.one_of(
    st.just(b""),
    st.builds(lambda v: json.dumps({"token": v}).encode(), st.one_of(st.text(max_size=20), st.integers(), st.none())),
    st.builds(lambda v: json.dumps({"access_token": v}).encode(), st.text(max_size=20)),
    st.sampled_from([
        b'{"errors": [{"code": "MANIFEST_UNKNOWN"}]}', b'{"errors": [{"code": "NAME_UNKNOWN"}]}', b'{"errors": "x"}',
        b'{"errors": [1, null]}', b'{"errors": [{"code": [1]}]}', b"[]", b"null", b'"token"', b"{", b"\xff\xfe",
        b"\x1b[2J\x00 something broke", b"\x1b]0;owned\x07", b"<html>" + b"x" * 5000, b" " * (api.MAX_TOKEN + 1),
        b" " * (api.MAX_BODY + 1),
    ]),
    st.binary(max_size=300),
)  # fmt: skip


@st.composite
def answers(draw, port: int) -> dict:
    """path -> (status, headers, body) for each path of ``PATHS`` the case answers (the others: 404)."""
    routes = {}
    if draw(st.booleans()):  # the usual flow: the manifest asks for a token from the registry's own service
        challenge = f'Bearer realm="https://127.0.0.1:{port}/token",service="hostile",scope="repository:app:pull"'
        routes[MANIFEST] = (401, {"WWW-Authenticate": challenge}, b"")
    for path in PATHS:
        if path in routes or (path != MANIFEST and draw(st.integers(0, 3)) == 0):
            continue
        status = draw(st.sampled_from(STATUSES))
        headers = {}
        if draw(st.booleans()) or status in (301, 302, 303, 307, 308):
            headers["Location"] = draw(locations(port))
        if draw(st.booleans()) or status == 401:
            headers["WWW-Authenticate"] = draw(challenges(port))
        if draw(st.booleans()):
            headers["Docker-Content-Digest"] = draw(
                st.sampled_from([DIGEST, "", "sha256:xyz", "sha256:" + "AB" * 32, "x" * 10_000, "\x1b[31mred", DIGEST + " "])
            )
        body = draw(bodies)
        length = draw(st.sampled_from([None, None, None, "+10", "-1", "0", "-5", "9" * 20, "abc", "1e3"]))
        if length == "+10":
            headers["Content-Length"] = str(len(body) + 10)
        elif length is not None:
            headers["Content-Length"] = length
        routes[path] = (status, {k: _header_text(v) for k, v in headers.items()}, body)
    return routes


def answer(status: int, headers: dict, body: bytes):
    def respond(handler):
        try:
            handler.send_response(status)
            for name, value in headers.items():
                handler.send_header(name, value)
            if "Content-Length" not in headers:
                handler.send_header("Content-Length", str(len(body)))
            handler.send_header("Connection", "close")
            handler.end_headers()
            if handler.command != "HEAD" and body:
                handler.wfile.write(body)
        except OSError:  # the client went away (a cap reached)
            pass
        handler.close_connection = True

    return respond


def registry_located(address: str):
    def located(error) -> str:
        named = str(error).startswith((f"registry {address}: ", f"registry {address} ("))
        return "" if named else f"does not start with 'registry {address}'"

    return located


def resolve_located(error) -> str:
    message = str(error)
    if not message.startswith("cannot pin every image to its digest"):
        return "does not say which images could not be pinned"
    return "" if f"  - {UPSTREAM}/app:1.0: " in message else f"does not name the image {UPSTREAM}/app:1.0"


def test_hostile_registry_answers_are_a_digest_or_one_refusal_naming_the_registry(tmp_path_factory):
    with HostileRegistry(str(tmp_path_factory.mktemp("registry"))) as server, loopback_only(server.port):

        @fuzz_settings(300)
        @given(routes=answers(server.port), realms=st.sampled_from([(), ("localhost",)]))
        def case(routes, realms):
            server.routes = {path: answer(*drawn) for path, drawn in routes.items()}
            client = api.RegistryApi(server.address, "alice", "s3cret", server.ca_file, realms=realms, deadline_s=5.0)
            sent_before = server.credentials_sent("localhost")
            outcome = run_case(
                "registry", lambda: client.manifest_digest("app", "1.0"), api.RegistryError, registry_located(server.address),
                routes,
            )  # fmt: skip
            if outcome.error is None:
                assert isinstance(outcome.value, str) and outcome.value, outcome.value
            if not realms:
                assert server.credentials_sent("localhost") == sent_before, "the password went to another origin"

        case()


def test_hostile_mirror_answers_pin_digests_or_refuse_naming_the_image(tmp_path_factory):
    with HostileRegistry(str(tmp_path_factory.mktemp("mirror"))) as server, loopback_only(server.port):
        mirrors = {UPSTREAM: [{"url": server.url(), "ca": server.ca_file}]}

        @fuzz_settings(150)
        @given(routes=answers(server.port))
        def case(routes):
            server.routes = {path: answer(*drawn) for path, drawn in routes.items()}
            image = f"{UPSTREAM}/app:1.0"
            logins = {server.address: ("alice", "s3cret"), UPSTREAM: ("bob", "upstream-secret")}
            outcome = run_case(
                "registry-resolve", lambda: image_digests.resolve([image], mirrors, logins), KuberosError, resolve_located,
                routes,
            )  # fmt: skip
            if outcome.error is None:
                assert image_pins.DIGEST.match(outcome.value[image]), outcome.value
            assert not any((auth or "").startswith("Basic Ym9i") for *_rest, auth in server.requests), "upstream's login sent"

        case()
