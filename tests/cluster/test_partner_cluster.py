"""A module in a third-party cluster: a second real control plane stands for the partner's cluster.

Deploy places the motion planners of examples/partner-cloud.yml in the partner cluster through its API server
(a ServiceAccount token kept in ansible-vault, its CA certificate), the bridge server at this cluster's edge
and the bridge client beside the planners; undeploy removes both sides. What crosses the bridge at run time
is tested with real ROS 2 processes in tests/integration/test_bridge.py; here the wiring is checked: the
client connects to the endpoint and NodePort the server's Service opens, and both ends trust the same CA.
"""

from __future__ import annotations

import base64
import os

import pytest
from helpers import PARTNER_PORTS, Cluster, partner_site

pytestmark = pytest.mark.cluster

SPEC = "examples/partner-cloud.yml"
NAMESPACE = "kuberos-test-fleet"
BRIDGE = "kuberos-bridge-partner-cloud"


@pytest.fixture(scope="module")
def partner(tmp_path_factory):
    partner = Cluster(tmp_path_factory.mktemp("partner"), PARTNER_PORTS)
    try:
        started = partner.start()
        assert started.returncode == 0, started.stdout[-4000:]
        yield partner
    finally:
        partner.stop(state="absent")


@pytest.fixture(scope="module")
def site(partner, tmp_path_factory):
    """An inventory adding the partner cluster, its token encrypted with ansible-vault."""
    core, _, _ = partner.clients()
    api_server = f"https://127.0.0.1:{PARTNER_PORTS['apiserver']}"
    ca_cert = os.path.join(partner.state_dir, "pki", "ca.crt")
    return partner_site(core, tmp_path_factory.mktemp("site"), "partner-cloud", api_server, ca_cert, "127.0.0.1")


def _secret(core, name):
    return {k: base64.b64decode(v).decode() for k, v in core.read_namespaced_secret(name, NAMESPACE).data.items()}


def test_deploy_places_the_module_in_the_partner_cluster_with_the_bridge_on_both_sides(cluster, partner, site, tmp_path):
    extra = ("-i", site["inventory"], "--vault-password-file", site["password"])
    deployed = cluster.deploy(SPEC, tmp_path / "render", *extra)
    assert deployed.returncode == 0, deployed.stdout[-5000:]
    assert site["token"] not in deployed.stdout + deployed.stderr, "the token is never printed"
    try:
        core, apps, _ = cluster.clients()
        pcore, papps, _ = partner.clients()
        # This cluster: the bridge server pinned at the edge, its NodePort, its TLS Secret; no planner here.
        server = apps.read_namespaced_deployment(BRIDGE, NAMESPACE)
        assert server.spec.template.spec.node_selector["device.kuberos.io/hostname"] in {"edge-1", "edge-2"}
        service = core.read_namespaced_service(BRIDGE, NAMESPACE)
        assert service.spec.type == "NodePort" and service.spec.ports[0].node_port == 30711
        names = {d.metadata.name for d in apps.list_namespaced_deployment(NAMESPACE).items}
        assert not any(n.startswith("partner-planning-motion-planner") for n in names), "the planners run in the partner cluster"
        # The partner cluster: the planners (scheduled by its own kube-scheduler), a discovery server, the client.
        remote = {d.metadata.name: d for d in papps.list_namespaced_deployment(NAMESPACE).items}
        assert {"partner-planning-motion-planner-fetch-1", "partner-planning-motion-planner-fetch-2",
                "kuberos-bridge-client", "kuberos-discovery-0"} <= set(remote)  # fmt: skip
        pods = pcore.list_namespaced_pod(NAMESPACE).items
        planners = [p for p in pods if "motion-planner" in p.metadata.name]
        assert len(planners) == 2 and all(p.spec.node_name for p in planners), "bound by the partner's scheduler"
        args = remote["kuberos-bridge-client"].spec.template.spec.containers[0].args
        assert args[args.index("--connect") + 1] == f"127.0.0.1:{service.spec.ports[0].node_port}"
        assert args[args.index("--server-name") + 1] == BRIDGE
        # Both ends trust the same CA; the server's certificate is for the name the client checks.
        server_tls, client_tls = _secret(core, f"{BRIDGE}-tls"), _secret(pcore, "kuberos-bridge-client-tls")
        assert server_tls["ca.crt"] == client_tls["ca.crt"] and server_tls["tls.key"] != client_tls["tls.key"]
        from cryptography import x509

        cert = x509.load_pem_x509_certificate(server_tls["tls.crt"].encode())
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(x509.DNSName)
        assert BRIDGE in names

        again = cluster.deploy(SPEC, tmp_path / "render", *extra, "--diff")
        assert again.returncode == 0 and again.changed == 0, again.stdout[-4000:]
    finally:
        removed = cluster.undeploy(SPEC, *extra)
    assert removed.returncode == 0, removed.stdout[-4000:]
    left = [d.metadata.name for d in papps.list_namespaced_deployment(NAMESPACE).items]
    assert left == [], f"undeploy removes the partner side too: {left}"
    assert [s.metadata.name for s in pcore.list_namespaced_secret(NAMESPACE).items if s.metadata.name.startswith("kuberos")] == []
    here = [d.metadata.name for d in apps.list_namespaced_deployment(NAMESPACE).items]
    assert BRIDGE not in here and not any(n.startswith("partner-planning") for n in here)
    assert [s.metadata.name for s in core.list_namespaced_secret(NAMESPACE).items if s.metadata.name == f"{BRIDGE}-tls"] == []
