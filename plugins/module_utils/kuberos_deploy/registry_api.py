"""The registry HTTP API v2, as deploy reads it (and the lab's registry client builds on): a manifest's digest for a
tag, over TLS with the registry's CA, with basic credentials or the bearer token the registry's challenge names.

Every failure is a `RegistryError` whose message names the registry and the image and says why (refused
credentials, unknown image, no connection, an untrusted certificate). Ansible's ``open_url`` is the one HTTP client.
"""

from __future__ import annotations

import base64
import contextlib
import json
import re
import ssl
import urllib.error
import urllib.parse

from ansible.module_utils.urls import open_url

MANIFEST_TYPES = (
    "application/vnd.oci.image.manifest.v1+json",
    "application/vnd.oci.image.index.v1+json",
    "application/vnd.docker.distribution.manifest.v2+json",
    "application/vnd.docker.distribution.manifest.list.v2+json",
)
REQUEST_TIMEOUT = 60.0


class RegistryError(RuntimeError):
    """A registry refused or failed a request; the message names the registry, the image and why."""


class RegistryApi:
    """The registry API v2 at ``https://<address>``, trusting ``ca_file`` (None: the system's CAs): reads, with basic
    credentials or the bearer token a registry's challenge asks for (Docker Hub, GHCR)."""

    def __init__(self, address: str, username: str = "", password: str = "", ca_file: str | None = None):
        self.address = address
        self._basic = "Basic " + base64.b64encode(f"{username}:{password}".encode()).decode() if username or password else None
        self._authorization = self._basic
        self._username = username
        self._ca_file = ca_file

    def _token(self, challenge: str, image: str) -> str:
        """The bearer token a 401's ``WWW-Authenticate: Bearer realm=...,service=...,scope=...`` names, from its
        realm (with the basic credentials, when given): how Docker Hub, GHCR and most public registries admit."""
        fields = dict(re.findall(r'(\w+)="([^"]*)"', challenge))
        realm = fields.pop("realm", "")
        if not realm.startswith("https://"):
            raise RegistryError(f"registry {self.address}: its token service {realm!r} is not https (image {image})")
        query = urllib.parse.urlencode({k: v for k, v in fields.items() if k in ("service", "scope")})
        headers = {"Authorization": self._basic} if self._basic else {}
        try:
            response = open_url(
                f"{realm}?{query}" if query else realm, headers=headers, timeout=REQUEST_TIMEOUT, ca_path=self._ca_file,
                use_proxy=False, use_netrc=False, follow_redirects="safe", http_agent="kuberos",
            )  # fmt: skip
            with response:
                answer = json.loads(response.read() or b"{}")
        except urllib.error.HTTPError as error:
            raise RegistryError(self._explain(error.code, error.read(), image, "token")) from None
        except (urllib.error.URLError, OSError, ValueError) as error:
            raise RegistryError(f"registry {self.address}: its token service {realm} failed ({error}) (image {image})") from None
        token = answer.get("token") or answer.get("access_token")
        if not token:
            raise RegistryError(f"registry {self.address}: its token service {realm} gave no token (image {image})")
        return token

    def _request(self, method: str, url: str, image: str, *, body=None, headers: dict | None = None, ok=(200,), retried=False):
        """One request; (status, headers, body bytes). Raises RegistryError naming the registry and the image. A 401
        whose challenge names a bearer token service is answered once with a token from it."""
        if not url.startswith("https://"):
            url = f"https://{self.address}{url}"
        headers = dict(headers or {})
        if self._authorization:
            headers["Authorization"] = self._authorization
        try:
            response = open_url(
                url, data=body, headers=headers, method=method, timeout=REQUEST_TIMEOUT, ca_path=self._ca_file,
                use_proxy=False, use_netrc=False, decompress=False, follow_redirects="none", http_agent="kuberos",
            )  # fmt: skip
            with response:
                return response.status, response.headers, response.read()
        except urllib.error.HTTPError as error:
            if error.code in ok:
                return error.code, error.headers, error.read()
            challenge = (error.headers or {}).get("WWW-Authenticate", "") if error.code == 401 else ""
            if challenge.lower().startswith("bearer ") and not retried:
                self._authorization = "Bearer " + self._token(challenge, image)
                return self._request(method, url, image, body=body, headers=headers, ok=ok, retried=True)
            raise RegistryError(self._explain(error.code, error.read(), image, method)) from None
        except urllib.error.URLError as error:
            reason = error.reason
            if isinstance(reason, ssl.SSLCertVerificationError) or "CERTIFICATE_VERIFY_FAILED" in str(reason):
                why = getattr(reason, "verify_message", "") or "certificate verify failed"
                raise RegistryError(
                    f"registry {self.address}: its certificate is not trusted ({why}); "
                    f"give the registry's CA certificate (image {image})"
                ) from None
            raise RegistryError(f"registry {self.address}: cannot connect ({reason}) (image {image})") from None
        except (OSError, TimeoutError, ValueError) as error:  # ansible's SSLValidationError is a ConnectionError
            if "certificate" in str(error).lower():
                raise RegistryError(
                    f"registry {self.address}: its certificate is not trusted ({error}); "
                    f"give the registry's CA certificate (image {image})"
                ) from None
            raise RegistryError(f"registry {self.address}: {error} (image {image})") from None

    def _explain(self, status: int, body: bytes, image: str, method: str) -> str:
        codes = []
        with contextlib.suppress(ValueError, AttributeError, TypeError):
            codes = [e.get("code", "") for e in json.loads(body or b"{}").get("errors", [])]
        if status == 401:
            who = f"user '{self._username}'" if self._username else "anonymous access"
            return f"registry {self.address}: refused the credentials ({who}: HTTP 401 Unauthorized) for image {image}"
        if status == 403:
            return f"registry {self.address}: access denied (HTTP 403) to image {image}"
        if status == 404 or "MANIFEST_UNKNOWN" in codes or "NAME_UNKNOWN" in codes:
            return f"registry {self.address}: image {image} not found ({', '.join(codes) or 'HTTP 404'})"
        text = body[:300].decode(errors="replace").strip()
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
