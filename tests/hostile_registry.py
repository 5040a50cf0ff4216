"""A registry that behaves as an attacker's would, on loopback, for the registry client's bounds and credential
scope (tests/unit/test_registry_trust.py, bench/bench_trust.py).

One TLS server (a certificate of its own CA for both ``127.0.0.1`` and ``localhost``, which are two origins to a
client: two hosts) whose answers are chosen per path by ``HostileRegistry.routes``. It records every request with
its Authorization header, so a test counts the credentials that reached a host they were not given for. A plain-http
twin (``plain=True``) serves the same routes without TLS.
"""

from __future__ import annotations

import http.server
import socket
import ssl
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

DIGEST = "sha256:" + "ab" * 32


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):  # quiet
        pass

    def _answer(self):
        server = self.server.registry
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        server.requests.append((self.command, host, self.path.split("?")[0], self.headers.get("Authorization")))
        route = server.route(self.path.split("?")[0])
        route(self)

    do_GET = do_HEAD = do_POST = do_PUT = _answer


def send(handler, status: int, headers: dict | None = None, body: bytes = b""):
    handler.send_response(status)
    for name, value in (headers or {}).items():
        handler.send_header(name, value)
    if "Content-Length" not in (headers or {}):
        handler.send_header("Content-Length", str(len(body)))
    handler.end_headers()
    if handler.command != "HEAD" and body:
        handler.wfile.write(body)


def manifest(handler):
    """The manifest, for a bearer token only (any token: the test is where credentials go, not the token)."""
    if not (handler.headers.get("Authorization") or "").startswith("Bearer "):
        realm = handler.server.registry.realm
        send(handler, 401, {"WWW-Authenticate": f'Bearer realm="{realm}",service="hostile",scope="repository:app:pull"'})
        return
    send(handler, 200, {"Docker-Content-Digest": DIGEST, "Content-Type": "application/vnd.oci.image.manifest.v1+json"})


def manifest_basic(handler):
    """The manifest for anyone (a mirror that needs no login)."""
    send(handler, 200, {"Docker-Content-Digest": DIGEST})


def token(handler):
    send(handler, 200, {"Content-Type": "application/json"}, b'{"token": "t0ken"}')


def redirect_to(url: str):
    def answer(handler):
        send(handler, 302, {"Location": url})

    return answer


def huge(size: int):
    """An answer of ``size`` bytes with no Content-Length (close-delimited), sent as fast as the client reads."""

    def answer(handler):
        handler.send_response(200)
        handler.send_header("Content-Type", "application/json")
        handler.send_header("Connection", "close")
        handler.end_headers()
        block = b" " * 65536
        sent = 0
        try:
            while sent < size:
                handler.wfile.write(block)
                sent += len(block)
        except OSError:
            pass
        handler.close_connection = True

    return answer


def huge_declared(size: int):
    def answer(handler):
        handler.send_response(200)
        handler.send_header("Content-Length", str(size))
        handler.end_headers()
        handler.close_connection = True

    return answer


def trickle(every_s: float, total_s: float, headers_too: bool = False):
    """One byte every ``every_s`` for at most ``total_s`` (of the body, or of the status line and headers)."""

    def answer(handler):
        end = time.monotonic() + total_s
        try:
            if headers_too:
                for byte in b"HTTP/1.1 200 OK\r\nX-Slow: " + b"a" * 10000:
                    if time.monotonic() > end:
                        return
                    handler.wfile.write(bytes([byte]))
                    handler.wfile.flush()
                    time.sleep(every_s)
                return
            handler.send_response(200)
            handler.send_header("Content-Length", "100000")
            handler.end_headers()
            handler.wfile.flush()
            while time.monotonic() < end:
                handler.wfile.write(b" ")
                handler.wfile.flush()
                time.sleep(every_s)
        except OSError:
            pass
        handler.close_connection = True

    return answer


class HostileRegistry:
    """A loopback server: ``routes`` path -> answer; ``requests``: (method, host, path, Authorization)."""

    def __init__(self, directory: str, plain: bool = False):
        self.routes: dict = {}
        self.requests: list = []
        self.realm = ""
        self.ca_file = f"{directory}/ca.crt"
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        server.daemon_threads = True
        server.registry = self
        if not plain:
            ca_cert, ca_key = pki.new_ca("hostile registry CA", days=1)
            cert, key = pki.issue(ca_cert, ca_key, "127.0.0.1", usage=pki.SERVER, days=1, alt_names=["127.0.0.1", "localhost"])
            for name, obj in (("ca.crt", ca_cert), ("tls.crt", cert), ("tls.key", key)):
                pki.write_pem(f"{directory}/{name}", obj)
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(f"{directory}/tls.crt", f"{directory}/tls.key")
            server.socket = context.wrap_socket(server.socket, server_side=True)
        self.server = server
        self.port = server.server_address[1]
        self.scheme = "http" if plain else "https"
        self._thread = threading.Thread(target=server.serve_forever, daemon=True)

    def url(self, host: str = "127.0.0.1", path: str = "") -> str:
        return f"{self.scheme}://{host}:{self.port}{path}"

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def route(self, path: str):
        return self.routes.get(path) or (lambda handler: send(handler, 404))

    def credentials_sent(self, host: str) -> int:
        """Requests to ``host`` that carried credentials of basic auth (the user's password)."""
        return sum(1 for _m, h, _p, auth in self.requests if h == host and (auth or "").startswith("Basic "))

    def __enter__(self) -> HostileRegistry:
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


def closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
