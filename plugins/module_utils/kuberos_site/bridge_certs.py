"""Certificates for the bridge's mutual TLS: one CA, a server certificate and a client certificate.

``generate_certificates(out_dir, server_name)`` writes ca.crt/ca.key, server.crt/server.key and
client.crt/client.key (keys ECDSA P-256, PEM, mode 0600) and returns their paths. The server certificate
names ``server_name`` (a DNS name, or an IP address) and is for serverAuth only; the client certificate
is for clientAuth only. Both sides trust only this CA, so a peer with a certificate from another CA is
refused during the TLS handshake.
"""

from __future__ import annotations

import os

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

FILES = {
    "ca_cert": "ca.crt",
    "ca_key": "ca.key",
    "server_cert": "server.crt",
    "server_key": "server.key",
    "client_cert": "client.crt",
    "client_key": "client.key",
}
CLIENT_NAME = "kuberos-bridge-client"


def generate_certificates(
    out_dir: str, server_name: str, *, days: int = 825, extra_server_names: list[str] | tuple[str, ...] = ()
) -> dict[str, str]:
    """Write a new CA, server and client certificate with their keys into out_dir; return name -> path.

    Keys of the returned dict: ca_cert, ca_key, server_cert, server_key, client_cert, client_key.
    Existing files of those names are replaced.
    """
    if not isinstance(server_name, str) or not server_name.strip():
        raise ValueError("server_name must be a non-empty DNS name or IP address")
    if days < 1:
        raise ValueError("days must be at least 1")
    os.makedirs(out_dir, exist_ok=True)
    ca, ca_key = pki.new_ca("kuberos-bridge-ca", days=days, organization="KubeROS", path_length=0)
    server_names = [server_name, *[n for n in extra_server_names if n != server_name]]
    server, server_key = pki.issue(
        ca, ca_key, server_name, usage=pki.SERVER, days=days, organization="KubeROS", alt_names=server_names
    )
    client, client_key = pki.issue(
        ca, ca_key, CLIENT_NAME, usage=pki.CLIENT, days=days, organization="KubeROS", alt_names=[CLIENT_NAME]
    )
    contents = {
        "ca_cert": ca, "ca_key": ca_key, "server_cert": server, "server_key": server_key,
        "client_cert": client, "client_key": client_key,
    }  # fmt: skip
    paths = {}
    for what, obj in contents.items():
        paths[what] = os.path.join(out_dir, FILES[what])
        pki.write_pem(paths[what], obj)
    return paths
