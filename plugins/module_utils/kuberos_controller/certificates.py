"""How long the API server's serving certificate has left: read from the TLS handshake the controller makes with the
API server it talks to (the address and CA of its kubeconfig, or in a cluster the ``kubernetes`` Service), exported
as ``kuberos_apiserver_certificate_expiry_seconds{endpoint}`` (docs/monitoring.md).

kubeadm's certificates last a year and only an upgrade or ``kubeadm certs renew`` renews them; the collection's rules
alert when the soonest seen in six hours has less than 30 days (warning) or 7 days (critical) left. Behind a Service or
a virtual IP each handshake may reach another control plane, so over successive scrapes every API server's
certificate is seen; ``min_over_time`` in the rules keeps the soonest.

One handshake a ``REFRESH_S`` at most, bounded by a deadline; a failure leaves the last figure (or none) and is
logged once a refresh.
"""

from __future__ import annotations

import logging
import socket
import ssl
import threading
import time
import urllib.parse

REFRESH_S = 300.0
TIMEOUT_S = 5.0
log = logging.getLogger("kuberos.controller")


def serving_certificate_expiry(host: str, port: int, ca_file: str | None, timeout: float = TIMEOUT_S) -> float:
    """Seconds until the certificate the TLS server at ``host:port`` presents expires (negative once expired),
    verified against ``ca_file`` (None: the system's CAs) and ``host``. OSError or ssl.SSLError on failure."""
    context = ssl.create_default_context(cafile=ca_file)
    with socket.create_connection((host, port), timeout=timeout) as raw, context.wrap_socket(raw, server_hostname=host) as tls:
        not_after = tls.getpeercert()["notAfter"]
    return ssl.cert_time_to_seconds(not_after) - time.time()


def endpoint_of(configuration) -> tuple[str, int, str | None]:
    """(host, port, CA file) of a ``kubernetes.client.Configuration``."""
    parts = urllib.parse.urlsplit(configuration.host)
    return parts.hostname or "", parts.port or 443, getattr(configuration, "ssl_ca_cert", None) or None


class ApiServerCertificate:
    """The remaining lifetime of the API server's certificate, refreshed at most every ``refresh_s`` seconds."""

    def __init__(self, api_client, refresh_s: float = REFRESH_S, clock=time.monotonic, read=serving_certificate_expiry):
        configuration = getattr(api_client, "configuration", None)
        self.endpoint = endpoint_of(configuration) if configuration is not None and configuration.host else None
        self.refresh_s = refresh_s
        self._clock = clock
        self._read = read
        self._lock = threading.Lock()
        self._checked = None
        self._remaining: float | None = None
        self._read_at = 0.0

    def remaining(self) -> tuple[str, float] | None:
        """(endpoint, seconds left) as of now, or None when it was never read."""
        if self.endpoint is None or not self.endpoint[0]:
            return None
        host, port, ca_file = self.endpoint
        with self._lock:
            now = self._clock()
            if self._checked is None or now - self._checked >= self.refresh_s:
                self._checked = now
                try:
                    self._remaining, self._read_at = self._read(host, port, ca_file), now
                except (OSError, ValueError, KeyError) as exc:  # ssl.SSLError is an OSError
                    log.warning("cannot read the API server's certificate at %s:%s: %s", host, port, exc)
            if self._remaining is None:
                return None
            return f"{host}:{port}", self._remaining - (now - self._read_at)
