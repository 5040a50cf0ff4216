"""Modules in a third-party cluster: validation, placement and the objects rendered on both sides of the bridge."""

from __future__ import annotations

import copy

import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_deployment, render_remote
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import parse_rosdeployment

SPEC = "examples/partner-cloud.yml"
PARTNER = {
    "kuberos_latency_ms": 30,
    "kuberos_fleets": ["test-fleet"],
    "kuberos_bridge_endpoint": "203.0.113.10",
    "kuberos_bridge_node_port": 30722,
    "kuberos_cluster_domain": "partner.local",
}


@pytest.fixture
def raw(local_raw):
    raw = copy.deepcopy(local_raw)
    raw["hosts"]["partner-cloud"] = dict(PARTNER)
    raw["groups"]["clusters"] = ["partner-cloud"]
    return raw


@pytest.fixture
def spec_data(root):
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def test_a_module_in_a_third_party_cluster_is_placed_there_with_a_bridge_at_the_edge(raw, root, tmp_path):
    deployments, placement = load_and_place(f"{root}/{SPEC}", raw)
    planners = [i for i in placement.instances if i.module == "motion-planner"]
    assert {(i.node, i.cluster, i.robots) for i in planners} == {
        ("partner-cloud", "partner-cloud", ("fetch-1",)),
        ("partner-cloud", "partner-cloud", ("fetch-2",)),
    }
    assert all("third-party cluster partner-cloud" in i.reason and "30 ms <= 200 ms" in i.reason for i in planners)
    (bridge,) = placement.bridges["test-fleet"]
    assert bridge.name == "kuberos-bridge-partner-cloud" and bridge.tier == "edge" and bridge.node in {"edge-1", "edge-2"}

    inventory = load_inventory(raw)
    main = render_deployment(deployments, placement)
    kinds = {(o["kind"], o["metadata"]["name"]) for o in main}
    assert ("Deployment", "kuberos-bridge-partner-cloud") in kinds and ("Service", "kuberos-bridge-partner-cloud") in kinds
    assert not any(o["metadata"]["name"].startswith("partner-planning-motion-planner") for o in main), "planners run remotely"
    server = next(o for o in main if o["kind"] == "Deployment" and o["metadata"]["name"] == bridge.name)
    pod = server["spec"]["template"]["spec"]
    assert pod["nodeSelector"] == {"device.kuberos.io/hostname": bridge.node}
    env = {e["name"]: e["value"] for e in pod["containers"][0]["env"]}
    assert env["ROS_DISCOVERY_SERVER"].startswith("$(KUBEROS_DISCOVERY_0_SERVICE_HOST):11811;")  # the kubelet expands it
    assert pod["containers"][0]["args"][3:6] == ["server", "--listen", "0.0.0.0:50051"]
    service = next(o for o in main if o["kind"] == "Service" and o["metadata"]["name"] == bridge.name)
    assert service["spec"]["ports"][0]["nodePort"] == 30722, "the port the partner's client connects to"

    remote = render_remote(deployments, placement, inventory.clusters)
    objects = remote["partner-cloud"]
    names = [(o["kind"], o["metadata"]["name"]) for o in objects]
    assert names[0] == ("Namespace", "kuberos-test-fleet")
    assert ("Deployment", "kuberos-bridge-client") in names and ("Deployment", "kuberos-discovery-0") in names
    assert ("Deployment", "partner-planning-motion-planner-fetch-1") in names
    assert ("Deployment", "partner-planning-perception-fetch-1") not in names, "only the cluster's modules go there"
    for obj in objects:
        assert obj["metadata"]["annotations"]["kuberos.io/cluster"] == "partner-cloud"
        if obj["kind"] == "Deployment":
            spec = obj["spec"]["template"]["spec"]
            assert "nodeSelector" not in spec and "tolerations" not in spec, "the partner's scheduler picks the node"
    planner = next(o for o in objects if o["metadata"]["name"] == "partner-planning-motion-planner-fetch-1")
    env = {e["name"]: e.get("value") for e in planner["spec"]["template"]["spec"]["containers"][0]["env"]}
    assert env["ROS_DISCOVERY_SERVER"] == "$(KUBEROS_DISCOVERY_0_SERVICE_HOST):11811"  # the partner's own server's Service
    assert planner["metadata"]["namespace"] == "kuberos-test-fleet" and ("Service", "kuberos-discovery-0") in names
    client = next(o for o in objects if o["metadata"]["name"] == "kuberos-bridge-client")
    args = client["spec"]["template"]["spec"]["containers"][0]["args"]
    assert args[3:8] == ["client", "--connect", "203.0.113.10:30722", "--server-name", "kuberos-bridge-partner-cloud"]
    topics = yaml.safe_load(
        next(o for o in objects if o["metadata"]["name"] == "kuberos-bridge-client-topics")["data"]["topics.yaml"]
    )
    # {robot} is the robot's ROS name (fetch-1 is fetch_1): a hyphen in a topic name is refused by ROS and the bridge.
    assert topics["topics"] == [
        {"name": "/fetch_1/planning/request", "type": "std_msgs/msg/String", "direction": "to_client"},
        {"name": "/fetch_1/planning/response", "type": "std_msgs/msg/String", "direction": "to_server"},
        {"name": "/fetch_2/planning/request", "type": "std_msgs/msg/String", "direction": "to_client"},
        {"name": "/fetch_2/planning/response", "type": "std_msgs/msg/String", "direction": "to_server"},
    ]
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import load_topics

    rendered = tmp_path / "topics.yaml"
    rendered.write_text(yaml.safe_dump(topics))
    assert [t.name for t in load_topics(str(rendered))] == [t["name"] for t in topics["topics"]], "the bridge reads it"


def test_both_sides_are_valid_kubernetes_objects(raw, root):
    import kubernetes_validate

    deployments, placement = load_and_place(f"{root}/{SPEC}", raw)
    remote = render_remote(deployments, placement, load_inventory(raw).clusters)
    for obj in render_deployment(deployments, placement) + remote["partner-cloud"]:
        kubernetes_validate.validate(obj, "1.34", strict=True)


@pytest.mark.parametrize(
    "change, expected",
    [
        (lambda s: s["rosModules"][1].pop("bridge"), "rosModules[1].cluster: needs bridge.topics"),
        (lambda s: s["rosModules"][0].update(bridge=copy.deepcopy(s["rosModules"][1]["bridge"])),
         "rosModules[0].bridge: only applies with cluster"),
        (lambda s: s["rosModules"][1].update(requirements={"onboard": True}), "contradicts requirements.onboard"),
        (lambda s: s["rosModules"][1].update(strategy="shared"), "needs strategy dedicated"),
        (lambda s: s["rosModules"][1]["bridge"]["topics"][0].update(type="String"), "such as 'std_msgs/msg/String'"),
        (lambda s: s["rosModules"][1]["bridge"]["topics"][0].update(direction="both"), "to_module or from_module"),
        (lambda s: s["rosModules"][1]["bridge"]["topics"][1].update(name="/{robot}/planning/request"), "is already bridged"),
    ],
)  # fmt: skip
def test_bad_bridge_specs_are_refused_with_the_field_and_the_reason(spec_data, change, expected):
    change(spec_data)
    with pytest.raises(KuberosError) as raised:
        parse_rosdeployment(spec_data, "partner.yml")
    assert expected in str(raised.value)


@pytest.mark.parametrize(
    "change, expected",
    [
        (lambda r: r["groups"].pop("clusters"), "'partner-cloud' is not a cluster of the inventory's group clusters"),
        (lambda r: r["hosts"]["partner-cloud"].update(kuberos_fleets=["warehouse-fleet"]), "does not serve fleet test-fleet"),
        (lambda r: r["hosts"]["partner-cloud"].update(kuberos_latency_ms=250), "latency 250 ms to fetch-1 > max_latency 200 ms"),
        (lambda r: r["hosts"]["partner-cloud"].pop("kuberos_bridge_endpoint"), "hosts.partner-cloud.kuberos_bridge_endpoint"),
        (lambda r: r["hosts"]["partner-cloud"].update(kuberos_bridge_node_port=80), "expected a NodePort from 30000 to 32767"),
    ],
)
def test_a_cluster_the_inventory_does_not_offer_is_a_clear_error(raw, spec_data, change, expected):
    change(raw)
    with pytest.raises(KuberosError) as raised:
        load_and_place(spec_data, raw)
    assert expected in str(raised.value)


def test_the_controller_leaves_modules_of_a_third_party_cluster_to_that_cluster(raw, root):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.replacement import replace_modules

    deployments, placement = load_and_place(f"{root}/{SPEC}", raw)
    result = replace_modules(deployments, load_inventory(raw), placement, unavailable={"edge-1": "down", "edge-2": "down"})
    remote = {i.name: i.node for i in placement.instances if i.cluster}
    assert {i.name: i.node for i in result.placement.instances if i.cluster} == remote
    assert not any(m.instance in remote for m in result.moves)
    assert result.placement.bridges == placement.bridges
