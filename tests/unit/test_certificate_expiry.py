"""The API server certificate's remaining lifetime (kuberos_controller/certificates.py): read from a real TLS handshake
with a server on loopback whose certificate lasts 10 days, refreshed at most every REFRESH_S, exported as
kuberos_apiserver_certificate_expiry_seconds; a server that cannot be reached leaves no figure."""

from __future__ import annotations

import socket
import ssl
import threading
import time
from types import SimpleNamespace

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import certificates, metrics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

DAY = 86400


@pytest.fixture
def tls_server(tmp_path):
    ca_cert, ca_key = pki.new_ca("test CA", days=30)
    cert, key = pki.issue(ca_cert, ca_key, "127.0.0.1", usage=pki.SERVER, days=10, alt_names=["127.0.0.1"])
    for name, obj in (("ca.crt", ca_cert), ("tls.crt", cert), ("tls.key", key)):
        pki.write_pem(str(tmp_path / name), obj)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(str(tmp_path / "tls.crt"), str(tmp_path / "tls.key"))
    listener = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve():
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                raw, _ = listener.accept()
            except TimeoutError:
                continue
            try:
                with context.wrap_socket(raw, server_side=True):
                    pass
            except (OSError, ssl.SSLError):
                raw.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield listener.getsockname()[1], str(tmp_path / "ca.crt")
    stop.set()
    thread.join(2)
    listener.close()


def test_the_remaining_lifetime_is_read_from_the_handshake(tls_server):
    port, ca_file = tls_server
    left = certificates.serving_certificate_expiry("127.0.0.1", port, ca_file)
    assert 9.9 * DAY < left <= 10 * DAY, left
    with pytest.raises(ssl.SSLError):  # not trusted without its CA
        certificates.serving_certificate_expiry("127.0.0.1", port, None)


def test_the_controller_exports_it_and_reads_it_at_most_every_refresh(tls_server):
    port, ca_file = tls_server
    client = SimpleNamespace(configuration=SimpleNamespace(host=f"https://127.0.0.1:{port}", ssl_ca_cert=ca_file))
    reads = []

    def read(host, port, ca_file):
        reads.append(host)
        return certificates.serving_certificate_expiry(host, port, ca_file)

    now = [1000.0]
    certificate = certificates.ApiServerCertificate(client, refresh_s=300, clock=lambda: now[0], read=read)
    endpoint, left = certificate.remaining()
    assert endpoint == f"127.0.0.1:{port}" and 9.9 * DAY < left <= 10 * DAY
    now[0] += 100
    assert certificate.remaining()[1] == pytest.approx(left - 100) and len(reads) == 1  # counted down, not read again
    now[0] += 300
    certificate.remaining()
    assert len(reads) == 2
    collected = list(metrics.CertificateCollector(certificate).collect())
    (family,) = collected
    (sample,) = family.samples
    assert family.name == "kuberos_apiserver_certificate_expiry_seconds"
    assert sample.labels == {"endpoint": f"127.0.0.1:{port}"} and 9.9 * DAY < sample.value <= 10 * DAY


def test_an_api_server_that_cannot_be_reached_gives_no_figure():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # nobody listens once it is closed
    client = SimpleNamespace(configuration=SimpleNamespace(host=f"https://127.0.0.1:{port}", ssl_ca_cert=None))
    started = time.monotonic()
    certificate = certificates.ApiServerCertificate(client)
    assert certificate.remaining() is None and list(metrics.CertificateCollector(certificate).collect()) == []
    assert time.monotonic() - started < certificates.TIMEOUT_S + 1
    assert certificates.ApiServerCertificate(None).remaining() is None  # a controller without a cluster client
