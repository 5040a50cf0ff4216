"""Fleets isolated (kuberos/network_policy.py): every fleet namespace deploy renders, here and in a third-party
cluster, denies ingress by default and admits the fleet's own pods; each other opening is named (a bridge server's
gRPC port, metrics ports for the metrics namespaces). A CNI enforcing them (Cilium in the lab) is proven on the site
(tests/site)."""

from __future__ import annotations

import pytest
from admission import EXAMPLES, render_example

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests, naming, network_policy
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file


def policies(objects: list[dict]) -> dict[tuple[str, str], dict]:
    return {(o["metadata"]["namespace"], o["metadata"]["name"]): o["spec"] for o in objects if o["kind"] == "NetworkPolicy"}


@pytest.mark.parametrize("path", EXAMPLES)
def test_every_fleet_namespace_denies_by_default_and_admits_its_own_pods(path):
    objects = render_example(path)
    found = policies(objects)
    namespaces = {o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"}
    assert namespaces
    for namespace in namespaces:
        assert found[(namespace, network_policy.DEFAULT_DENY)] == {"podSelector": {}, "policyTypes": ["Ingress"], "ingress": []}
        assert found[(namespace, network_policy.SAME_FLEET)] == {
            "podSelector": {}, "policyTypes": ["Ingress"], "ingress": [{"from": [{"podSelector": {}}]}]
        }  # fmt: skip
    # nothing else opens a port to everyone but a bridge server's gRPC port
    for (namespace, name), spec in found.items():
        for rule in spec["ingress"]:
            if "from" not in rule:
                assert rule["ports"] == [{"protocol": "TCP", "port": naming.BRIDGE_PORT}], (namespace, name)
                assert spec["podSelector"] == {"matchLabels": {"kuberos.io/instance": name}}


def test_the_bridge_takes_its_partner_on_its_grpc_port_and_metrics_from_the_metrics_namespaces():
    objects = render_example("examples/partner-cloud.yml")
    bridges = {k: v for k, v in policies(objects).items() if k[1].startswith("kuberos-bridge")}
    assert len(bridges) == 1, sorted(policies(objects))
    [spec] = bridges.values()
    selector = {"matchExpressions": [{"key": "kubernetes.io/metadata.name", "operator": "In", "values": ["kuberos-system"]}]}
    assert spec["ingress"] == [
        {"ports": [{"protocol": "TCP", "port": naming.BRIDGE_PORT}]},
        {"from": [{"namespaceSelector": selector}], "ports": [{"protocol": "TCP", "port": manifests.BRIDGE_METRICS_PORT}]},
    ]


def test_a_scaled_modules_gauge_is_open_to_the_namespaces_that_read_it(root, local_inventory):
    deployments = load_rosdeployment_file(f"{root}/examples/scaling.yml")
    options = RenderOptions(metrics_namespaces=("kuberos-system", "monitoring"))
    objects = render_deployment(deployments, place_modules(deployments, local_inventory), options)
    gauges = [m for d in deployments for m in d.modules if m.scaling and not m.scaling.uses_cpu]
    assert gauges, "the example scales a module on a gauge of its own"
    found = policies(objects)
    for dep in deployments:
        for module in gauges:
            spec = found[(naming.fleet_namespace(dep.fleet), naming.metrics_policy_name(dep.name, module.name))]
            assert spec["podSelector"] == {"matchLabels": {"kuberos.io/deployment": dep.name, "kuberos.io/module": module.name}}
            [rule] = spec["ingress"]
            assert rule["ports"] == [{"protocol": "TCP", "port": module.scaling.metrics_port}]
            assert rule["from"][0]["namespaceSelector"]["matchExpressions"][0]["values"] == ["kuberos-system", "monitoring"]
