"""The registry HTTP API v2, as deploy reads it (and the lab's registry client builds on): a manifest's digest for a
tag, over TLS with the registry's CA, with basic credentials or the bearer token the registry's challenge names.

Credentials stay with the registry they were given for (its scheme, host and port): a redirect to anywhere else is
followed without them, a token service (realm) on another host gets them only when the site names that realm
(``realms``; Docker Hub's own, ``auth.docker.io`` for ``registry-1.docker.io``, is known), and plain ``http://`` is
refused unless the registry is marked ``insecure``. Every request has an overall deadline (``DEADLINE_S``, however
slowly an answer trickles) and every answer a size cap (``MAX_BODY``, ``MAX_TOKEN``), by ``kuberos_kube.bounded``.

Every failure is a `RegistryError` whose message names the registry and the image and says why (refused
credentials, unknown image, no connection, an untrusted certificate, a bound exceeded). The HTTP client is the
standard library's ``http.client``: the one place that opens the connection is the one that can bound it.
"""

from __future__ import annotations

import base64
import contextlib
import http.client
import json
import re
import ssl
import urllib.parse

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.bounded import (
    Deadline,
    ReadBoundExceeded,
    exchange,
)

MANIFEST_TYPES = (
    "application/vnd.oci.image.manifest.v1+json",
    "application/vnd.oci.image.index.v1+json",
    "application/vnd.docker.distribution.manifest.v2+json",
    "application/vnd.docker.distribution.manifest.list.v2+json",
)
REQUEST_TIMEOUT = 60.0  # seconds a single socket read may wait
DEADLINE_S = 60.0  # seconds one request may take in all (redirects included)
MAX_BODY = 4 * 1024 * 1024  # a manifest or an error (registries refuse manifests over 4 MiB)
MAX_TOKEN = 256 * 1024  # a token service's answer
MAX_REDIRECTS = 5
# Token services that serve a registry from another host, known without the site naming them.
KNOWN_REALMS = {"registry-1.docker.io": ("auth.docker.io",)}


class RegistryError(RuntimeError):
    """A registry refused or failed a request; the message names the registry, the image and why."""


def shown(text, limit: int = 300) -> str:
    """``text`` as a message may show it: at most ``limit`` characters, control characters escaped."""
    text = str(text)[:limit]
    return text if text.isprintable() else ascii(text)[1:-1]


def origin(url: str) -> tuple[str, str, int]:
    """(scheme, host, port) of ``url``: what credentials are scoped to."""
    parts = urllib.parse.urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    return parts.scheme.lower(), (parts.hostname or "").lower(), port or (443 if parts.scheme == "https" else 80)


class RegistryApi:
    """The registry API v2 at ``https://<address>`` (``http://`` only when ``insecure``), trusting ``ca_file`` (None:
    the system's CAs): reads, with basic credentials or the bearer token a registry's challenge asks for (Docker Hub,
    GHCR). ``realms``: hosts of token services on another host that may receive the credentials."""

    def __init__(self, address: str, username: str = "", password: str = "", ca_file: str | None = None,
                 insecure: bool = False, realms=(), deadline_s: float = DEADLINE_S):  # fmt: skip
        self.address = address
        self.scheme = "http" if insecure else "https"
        self._origin = origin(f"{self.scheme}://{address}")
        self._basic = "Basic " + base64.b64encode(f"{username}:{password}".encode()).decode() if username or password else None
        self._bearer: str | None = None
        self._username = username
        self._ca_file = ca_file
        self._insecure = insecure
        self._realms = {r.lower() for r in (*realms, *KNOWN_REALMS.get(self._origin[1], ()))}
        self._deadline_s = deadline_s

    # the connection, bounded

    def _send(self, method: str, url: str, headers: dict, body, image: str, cap: int, deadline: Deadline):
        """One HTTP exchange at ``url``: (status, headers, body bytes at most ``cap``)."""
        scheme, host, port = origin(url)
        if scheme == "https":
            context = ssl.create_default_context(cafile=self._ca_file)
            connection = http.client.HTTPSConnection(host, port, timeout=min(REQUEST_TIMEOUT, deadline.remaining()),
                                                     context=context)  # fmt: skip
        elif scheme == "http" and self._insecure:
            connection = http.client.HTTPConnection(host, port, timeout=min(REQUEST_TIMEOUT, deadline.remaining()))
        else:
            raise RegistryError(
                f"registry {self.address}: refused to send a request to {url!r}: not https, and the registry is not "
                f"marked insecure (image {image})"
            )
        parts = urllib.parse.urlsplit(url)
        target = urllib.parse.urlunsplit(("", "", parts.path or "/", parts.query, ""))
        try:
            return exchange(connection, deadline, method, target, f"registry {self.address} ({host})", cap, body,
                            {"User-Agent": "kuberos", **headers})  # fmt: skip
        except (OSError, http.client.HTTPException) as error:
            deadline.check()
            raise self._connection_error(error, image) from None
        except (UnicodeError, ValueError) as error:  # a host or path no request can name (from a redirect)
            raise RegistryError(f"registry {self.address}: cannot ask {shown(url)!r} ({shown(error)}) (image {image})") from None
        finally:
            connection.close()

    def _connection_error(self, error: BaseException, image: str) -> RegistryError:
        if isinstance(error, ssl.SSLCertVerificationError) or "CERTIFICATE_VERIFY_FAILED" in str(error):
            why = getattr(error, "verify_message", "") or "certificate verify failed"
            return RegistryError(
                f"registry {self.address}: its certificate is not trusted ({why}); "
                f"give the registry's CA certificate (image {image})"
            )
        return RegistryError(f"registry {self.address}: cannot connect ({error}) (image {image})")

    def _exchange(self, method: str, url: str, image: str, headers: dict, body, cap: int, authorization: str | None,
                  scope: set, deadline_s: float | None = None) -> tuple:  # fmt: skip
        """``_send`` following redirects (at most ``MAX_REDIRECTS``): ``authorization`` goes only to an origin in
        ``scope``, never across a redirect to another origin; a redirect to plain http is refused unless insecure."""
        with Deadline(f"registry {self.address}", deadline_s or self._deadline_s) as deadline:
            for _hop in range(MAX_REDIRECTS + 1):
                sent = dict(headers)
                if authorization and origin(url) in scope:
                    sent["Authorization"] = authorization
                try:
                    status, answer, data = self._send(method, url, sent, body, image, cap, deadline)
                except ReadBoundExceeded as exceeded:
                    raise RegistryError(f"{exceeded} (image {image})") from None
                location = answer.get("Location", "") if status in (301, 302, 303, 307, 308) else ""
                if not location:
                    return status, answer, data
                try:
                    url = urllib.parse.urljoin(url, location)
                    scheme = origin(url)[0]
                except ValueError:
                    raise RegistryError(
                        f"registry {self.address}: refused its redirect to {shown(location)!r}: not a URL (image {image})"
                    ) from None
                if scheme != "https" and not self._insecure:
                    raise RegistryError(
                        f"registry {self.address}: refused its redirect to {shown(url)!r}: not https (image {image})"
                    )
                if status == 303:
                    method, body = "GET", None
            raise RegistryError(f"registry {self.address}: more than {MAX_REDIRECTS} redirects (image {image})")

    def _token(self, challenge: str, image: str) -> str:
        """The bearer token a 401's ``WWW-Authenticate: Bearer realm=...,service=...,scope=...`` names, from its
        realm: with the basic credentials only when the realm is this registry's own origin or a named realm."""
        fields = dict(re.findall(r'(\w+)="([^"]*)"', challenge))
        realm = fields.pop("realm", "")
        if not realm.startswith("https://") and not (self._insecure and realm.startswith("http://")):
            raise RegistryError(f"registry {self.address}: its token service {shown(realm)!r} is not https (image {image})")
        query = urllib.parse.urlencode({k: v for k, v in fields.items() if k in ("service", "scope")})
        scope = {self._origin}
        if origin(realm)[1] in self._realms:
            scope.add(origin(realm))
        status, _headers, data = self._exchange(
            "GET", f"{realm}{'&' if '?' in realm else '?'}{query}" if query else realm, image, {}, None, MAX_TOKEN,
            self._basic, scope,
        )  # fmt: skip
        if status != 200:
            raise RegistryError(self._explain(status, data, image, "token"))
        try:
            answer = json.loads(data or b"{}")
            token = answer.get("token") or answer.get("access_token")
        except (ValueError, AttributeError):
            token = None
        if not token or not isinstance(token, str):
            raise RegistryError(f"registry {self.address}: its token service {shown(realm)} gave no token (image {image})")
        return token

    def _request(self, method: str, url: str, image: str, *, body=None, headers: dict | None = None, ok=(200,),
                 retried=False, deadline_s: float | None = None):  # fmt: skip
        """One request; (status, headers, body bytes). Raises RegistryError naming the registry and the image. A 401
        whose challenge names a bearer token service is answered once with a token from it."""
        if not url.startswith(("https://", "http://")):
            url = f"{self.scheme}://{self.address}{url}"
        status, answer, data = self._exchange(
            method, url, image, dict(headers or {}), body, MAX_BODY, self._bearer or self._basic, {self._origin}, deadline_s
        )
        if status in ok:
            return status, answer, data
        challenge = (answer.get("WWW-Authenticate") or "") if status == 401 else ""
        if challenge.lower().startswith("bearer ") and not retried:
            self._bearer = "Bearer " + self._token(challenge, image)
            return self._request(method, url, image, body=body, headers=headers, ok=ok, retried=True, deadline_s=deadline_s)
        raise RegistryError(self._explain(status, data, image, method))

    def _explain(self, status: int, body: bytes, image: str, method: str) -> str:
        codes = []
        with contextlib.suppress(ValueError, AttributeError, TypeError):
            codes = [e.get("code", "") for e in json.loads(body or b"{}").get("errors", [])]
        if status == 401:
            who = f"user '{shown(self._username, 100)}'" if self._username else "anonymous access"
            return f"registry {self.address}: refused the credentials ({who}: HTTP 401 Unauthorized) for image {image}"
        if status == 403:
            return f"registry {self.address}: access denied (HTTP 403) to image {image}"
        if status == 404 or "MANIFEST_UNKNOWN" in codes or "NAME_UNKNOWN" in codes:
            return f"registry {self.address}: image {image} not found ({shown(', '.join(map(str, codes)), 100) or 'HTTP 404'})"
        text = shown(body[:300].decode(errors="replace").strip())
        return f"registry {self.address}: {method} for image {image} failed: HTTP {status} {text}"

    def check(self) -> None:
        """The API answers and accepts the credentials (GET /v2/)."""
        self._request("GET", "/v2/", f"{self.address}/v2/")

    def manifest_digest(self, repository: str, reference: str) -> str:
        """The digest the registry serves for ``repository`` at a tag or digest (HEAD of the manifest)."""
        image = f"{self.address}/{repository}{'@' if ':' in reference else ':'}{reference}"
        _status, headers, _body = self._request(
            "HEAD", f"/v2/{repository}/manifests/{reference}", image, headers={"Accept": ", ".join(MANIFEST_TYPES)}
        )
        digest = headers.get("Docker-Content-Digest", "")
        if not digest:
            raise RegistryError(f"registry {self.address}: no digest for image {image}")
        return digest

    def _get(self, path: str, image: str, accept: str = "") -> bytes:
        _status, _headers, body = self._request("GET", path, image, headers={"Accept": accept} if accept else None)
        return body
