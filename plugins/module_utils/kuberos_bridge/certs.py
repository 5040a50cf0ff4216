"""Certificates for the bridge's mutual TLS: one CA, a server certificate and a client certificate.

``generate_certificates(out_dir, server_name)`` writes ca.crt/ca.key, server.crt/server.key and
client.crt/client.key (keys ECDSA P-256, PEM, mode 0600) and returns their paths. The server certificate
names ``server_name`` (a DNS name, or an IP address) and is for serverAuth only; the client certificate
is for clientAuth only. Both sides trust only this CA, so a peer with a certificate from another CA is
refused during the TLS handshake.
"""

from __future__ import annotations

import datetime
import ipaddress
import os

FILES = {
    "ca_cert": "ca.crt",
    "ca_key": "ca.key",
    "server_cert": "server.crt",
    "server_key": "server.key",
    "client_cert": "client.crt",
    "client_key": "client.key",
}
CLIENT_NAME = "kuberos-bridge-client"


def _write(path: str, data: bytes, private: bool) -> None:
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    fd = os.open(path, flags, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
    os.chmod(path, 0o600 if private else 0o644)


def _san(name: str):
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def generate_certificates(
    out_dir: str, server_name: str, *, days: int = 825, extra_server_names: list[str] | tuple[str, ...] = ()
) -> dict[str, str]:
    """Write a new CA, server and client certificate with their keys into out_dir; return name -> path.

    Keys of the returned dict: ca_cert, ca_key, server_cert, server_key, client_cert, client_key.
    Existing files of those names are replaced.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not isinstance(server_name, str) or not server_name.strip():
        raise ValueError("server_name must be a non-empty DNS name or IP address")
    if days < 1:
        raise ValueError("days must be at least 1")
    os.makedirs(out_dir, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    until = now + datetime.timedelta(days=days)

    def key():
        return ec.generate_private_key(ec.SECP256R1())

    def name(common: str):
        return x509.Name(
            [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "KubeROS"), x509.NameAttribute(NameOID.COMMON_NAME, common)]
        )

    ca_key = key()
    ca_name = name("kuberos-bridge-ca")
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False,
                key_agreement=False, key_cert_sign=True, crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip

    def leaf(common: str, sans: list, usage):
        leaf_key = key()
        builder = (
            x509.CertificateBuilder()
            .subject_name(name(common))
            .issuer_name(ca_name)
            .public_key(leaf_key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(until)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(
                    digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False,
                    key_agreement=True, key_cert_sign=False, crl_sign=False, encipher_only=False, decipher_only=False,
                ),
                critical=True,
            )
            .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(
                    ca.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
                ),
                critical=False,
            )
        )  # fmt: skip
        return builder.sign(ca_key, hashes.SHA256()), leaf_key

    server_names = [server_name, *[n for n in extra_server_names if n != server_name]]
    server, server_key = leaf(server_name, [_san(n) for n in server_names], ExtendedKeyUsageOID.SERVER_AUTH)
    client, client_key = leaf(CLIENT_NAME, [x509.DNSName(CLIENT_NAME)], ExtendedKeyUsageOID.CLIENT_AUTH)

    def key_pem(k) -> bytes:
        return k.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())

    contents = {
        "ca_cert": (ca.public_bytes(serialization.Encoding.PEM), False),
        "ca_key": (key_pem(ca_key), True),
        "server_cert": (server.public_bytes(serialization.Encoding.PEM), False),
        "server_key": (key_pem(server_key), True),
        "client_cert": (client.public_bytes(serialization.Encoding.PEM), False),
        "client_key": (key_pem(client_key), True),
    }
    paths = {}
    for what, (data, private) in contents.items():
        paths[what] = os.path.join(out_dir, FILES[what])
        _write(paths[what], data, private)
    return paths
