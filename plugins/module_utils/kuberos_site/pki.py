"""The one X.509 helper: a certificate authority, and certificates it signs (an I/O helper: it writes PEM files).

Used by the local control plane (its cluster CA, the API server's serving certificate, client certificates of users,
components and kubelets) and by the KubeROS-Bridge (its mutual-TLS CA, server and client certificates). Keys are ECDSA
P-256 in PKCS#8 PEM, written with mode 0600; certificates are signed with SHA-256 and valid from five minutes ago.
``cryptography`` is imported only when a certificate is made.
"""

from __future__ import annotations

import datetime
import ipaddress
import os

SERVER = "server"
CLIENT = "client"


def _subject(common_name: str, organization: str | None):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    attrs = [x509.NameAttribute(NameOID.ORGANIZATION_NAME, organization)] if organization else []
    return x509.Name([*attrs, x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _key_usage(ca: bool):
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False,
        key_agreement=not ca, key_cert_sign=ca, crl_sign=ca, encipher_only=False, decipher_only=False,
    )  # fmt: skip


def alt_name(name: str):
    """A subjectAltName entry: an IP address when ``name`` is one, else a DNS name."""
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _validity(days: int):
    if days < 1:
        raise ValueError("days must be at least 1")
    start = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    return start, start + datetime.timedelta(days=days)


def new_key():
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def new_ca(common_name: str, *, days: int, organization: str | None = None, path_length: int | None = None):
    """A self-signed CA: (certificate, key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes

    key = new_key()
    name = _subject(common_name, organization)
    start, end = _validity(days)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=path_length), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return cert, key


def issue(ca_cert, ca_key, common_name: str, *, usage: str, days: int, organization: str | None = None, alt_names=()):
    """A certificate signed by the CA for ``usage`` (SERVER: serverAuth, CLIENT: clientAuth): (certificate, key).
    For a client certificate of a Kubernetes cluster the common name is the user and the organization its group."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID

    if usage not in (SERVER, CLIENT):
        raise ValueError(f"usage must be {SERVER!r} or {CLIENT!r}")
    key = new_key()
    start, end = _validity(days)
    builder = (
        x509.CertificateBuilder()
        .subject_name(_subject(common_name, organization))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH if usage == SERVER else ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    if alt_names:
        builder = builder.add_extension(x509.SubjectAlternativeName([alt_name(n) for n in alt_names]), critical=False)
    return builder.sign(ca_key, hashes.SHA256()), key


def write_pem(path: str, obj) -> None:
    """A certificate (mode 0644) or a private key (PKCS#8, mode 0600) as PEM, replacing the file."""
    from cryptography.hazmat.primitives import serialization

    private = hasattr(obj, "private_bytes")
    if private:
        data = obj.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    elif hasattr(obj, "public_bytes") and not hasattr(obj, "subject"):  # a public key
        data = obj.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    else:
        data = obj.public_bytes(serialization.Encoding.PEM)
    mode = 0o600 if private else 0o644
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
    os.chmod(path, mode)


def load_ca(cert_path: str, key_path: str):
    """A CA written by ``write_pem``: (certificate, key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    with open(cert_path, "rb") as handle:
        cert = x509.load_pem_x509_certificate(handle.read())
    with open(key_path, "rb") as handle:
        key = serialization.load_pem_private_key(handle.read(), password=None)
    return cert, key
