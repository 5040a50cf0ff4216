"""playbooks/deploy.yml and undeploy.yml against the real local control plane.

Proves: every pod is bound by the real kube-scheduler to the node KubeROS placed it on; the discovery
Services exist with endpoints; the environment carries the server list; re-running changes nothing;
editing the spec changes only what differs; removing a module prunes its objects; undeploy removes one
deployment and nothing else; a rejected object in the server-side dry run of any batch means nothing is
applied; the role's main.yml from a user's own single play deploys the same way.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess

import pytest
from helpers import ROOT, deployments_denied, venv_tool, without_module

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests

pytestmark = pytest.mark.cluster

RECAP = re.compile(r"^(\S+)\s+: ok=\d+\s+changed=(\d+)\s+unreachable=\d+\s+failed=(\d+)", re.M)


def changed_by_host(result) -> dict[str, int]:
    """Changed tasks per host of the recap: deploy.yml applies on in-memory batch hosts besides localhost."""
    return {host: int(changed) for host, changed, _failed in RECAP.findall(result.stdout)}


def pods_by_instance(core, namespace):
    pods = core.list_namespaced_pod(namespace, label_selector="app.kubernetes.io/managed-by=kuberos").items
    return {p.metadata.labels["kuberos.io/instance"]: p for p in pods if not p.metadata.deletion_timestamp}


def resource_versions(apps, core, namespace):
    versions = {}
    for d in apps.list_namespaced_deployment(namespace).items:
        versions[("Deployment", d.metadata.name)] = d.metadata.resource_version
    for c in core.list_namespaced_config_map(namespace, label_selector="app.kubernetes.io/managed-by=kuberos").items:
        versions[("ConfigMap", c.metadata.name)] = c.metadata.resource_version
    for s in core.list_namespaced_service(namespace).items:
        versions[("Service", s.metadata.name)] = s.metadata.resource_version
    return versions


@pytest.fixture
def spec(tmp_path):
    path = tmp_path / "pick-and-place.yml"
    shutil.copy(os.path.join(ROOT, "examples", "pick-and-place.yml"), path)
    return path


def test_deploy_binds_every_pod_where_kuberos_placed_it(cluster, spec, tmp_path):
    core, apps, discovery = cluster.clients()
    out = tmp_path / "render"
    first = cluster.deploy(spec, out)
    assert first.returncode == 0, first.stdout[-6000:] + first.stderr[-2000:]
    assert first.changed >= 1
    assert list(changed_by_host(first)) == ["localhost"], changed_by_host(first)  # one pass, one host, no batch hosts
    placement = json.loads((out / "placement.json").read_text())
    namespace = "kuberos-test-fleet"
    pods = pods_by_instance(core, namespace)
    for inst in placement["instances"]:
        pod = pods[inst["name"]]
        assert pod.spec.node_name == inst["node"], inst["name"]  # bound by kube-scheduler, pinned by nodeSelector
        assert pod.status.phase == "Running"
        env = {e.name: e.value for e in pod.spec.containers[0].env}
        # the Services' cluster IPs, which the kubelet expands (the fleet's namespace holds both Services); an onboard
        # module lists its robot's own server last (its deployment's node-local Service)
        own = ";$(KUBEROS_ROBOT_DISCOVERY_PICK_AND_PLACE_SERVICE_HOST):11811" if inst["tier"] == "onboard" else ""
        assert (
            env["ROS_DISCOVERY_SERVER"]
            == "$(KUBEROS_DISCOVERY_0_SERVICE_HOST):11811;$(KUBEROS_DISCOVERY_1_SERVICE_HOST):11811" + own
        )
        services = {s.metadata.name for s in core.list_namespaced_service(namespace).items}
        assert {"kuberos-discovery-0", "kuberos-discovery-1"} <= services, services
        assert env["ROS_DOMAIN_ID"] == "7" and env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert placement["robot_discovery"], "each robot with an onboard module runs a discovery server of its own"
    for server in placement["robot_discovery"]:
        assert pods[server["name"]].spec.node_name == server["node"] and pods[server["name"]].status.phase == "Running"
    for server in placement["discovery"][0]["servers"]:
        assert pods[server["name"]].spec.node_name == server["node"]
        service = core.read_namespaced_service(server["name"], namespace)
        assert [(p.port, p.protocol) for p in service.spec.ports] == [(11811, "UDP")]
        slices = discovery.list_namespaced_endpoint_slice(
            namespace, label_selector=f"kubernetes.io/service-name={server['name']}"
        )
        addresses = [a for s in slices.items for e in (s.endpoints or []) for a in e.addresses]
        assert addresses == [pods[server["name"]].status.pod_ip], server["name"]
    # The table printed at the end is read back from the cluster.
    assert "NODE (CLUSTER)" in first.stdout and "Missing" not in first.stdout

    before = resource_versions(apps, core, namespace)
    again = cluster.deploy(spec, out)
    assert again.returncode == 0 and again.changed == 0, again.stdout[-6000:]
    assert set(changed_by_host(again).values()) == {0}, changed_by_host(again)
    assert resource_versions(apps, core, namespace) == before

    # Edit one parameter: only its ConfigMap changes.
    spec.write_text(spec.read_text().replace("planning_time: 2.0", "planning_time: 5.0"))
    edited = cluster.deploy(spec, out)
    assert edited.returncode == 0 and edited.changed >= 1, edited.stdout[-6000:]
    after = resource_versions(apps, core, namespace)
    changed = sorted(k for k in before if before[k] != after.get(k))
    # The deployment record (the spec, inventory and placement the controller reads) holds the spec too.
    assert changed == [("ConfigMap", "kuberos-record-pick-and-place"), ("ConfigMap", "pick-and-place-motion-planner-params")]
    # The edit is the deployment's revision 2, kept beside revision 1.
    assert sorted(set(after) - set(before)) == [("ConfigMap", "kuberos-rev-pick-and-place-2")]

    # Remove the perception module: its Deployments and ConfigMap are pruned, nothing else.
    text = spec.read_text()
    spec.write_text(without_module(text, "perception"))
    pruned = cluster.deploy(spec, out)
    assert pruned.returncode == 0, pruned.stdout[-6000:]
    remaining = resource_versions(apps, core, namespace)
    gone = sorted(set(after) - set(remaining))
    assert gone == [
        ("ConfigMap", "pick-and-place-perception-params"),
        ("Deployment", "pick-and-place-perception-fetch-1"),
        ("Deployment", "pick-and-place-perception-fetch-2"),
    ]
    assert sorted(set(remaining) - set(after)) == [("ConfigMap", "kuberos-rev-pick-and-place-3")]
    assert all(remaining[k] == after[k] for k in after if k in remaining and k != ("ConfigMap", "kuberos-record-pick-and-place"))


def test_two_fleets_side_by_side_and_undeploy_removes_one(cluster, tmp_path):
    core, apps, _discovery = cluster.clients()
    both = cluster.deploy(os.path.join(ROOT, "examples", "two-fleets.yml"), tmp_path / "two")
    assert both.returncode == 0, both.stdout[-6000:]
    test_fleet = {p.spec.node_name for p in pods_by_instance(core, "kuberos-test-fleet").values()}
    warehouse = pods_by_instance(core, "kuberos-warehouse-fleet")
    assert {
        p.metadata.labels["kuberos.io/deployment"] for p in warehouse.values() if "kuberos.io/deployment" in p.metadata.labels
    } == {"inventory-scan"}
    assert len([n for n in warehouse if n.startswith("kuberos-discovery-")]) == 3
    assert "tiago-1" not in test_fleet and "fetch-1" not in {p.spec.node_name for p in warehouse.values()}
    for pod in warehouse.values():
        if pod.metadata.labels.get("kuberos.io/component") == "ros-module":
            env = {e.name: e.value for e in pod.spec.containers[0].env}
            assert (
                manifests.fleet_discovery_part(env["ROS_DISCOVERY_SERVER"]).count("_SERVICE_HOST):11811") == 3
                and pod.metadata.namespace == "kuberos-warehouse-fleet"
            )

    # Undeploy the two-fleet file: its deployments go; pick-and-place (same test-fleet) stays.
    before = resource_versions(apps, core, "kuberos-test-fleet")
    gone = cluster.undeploy(os.path.join(ROOT, "examples", "two-fleets.yml"))
    assert gone.returncode == 0, gone.stdout[-6000:]
    after = resource_versions(apps, core, "kuberos-test-fleet")
    assert sorted(set(before) - set(after)) == [
        ("ConfigMap", "kuberos-record-picking"),
        ("ConfigMap", "kuberos-rev-picking-1"),
        ("Deployment", "kuberos-robot-discovery-picking-fetch-1"),
        ("Deployment", "kuberos-robot-discovery-picking-fetch-2"),
        ("Deployment", "picking-controller-fetch-1"),
        ("Deployment", "picking-controller-fetch-2"),
        ("Deployment", "picking-planner-fetch-1"),
        ("Deployment", "picking-planner-fetch-2"),
        ("Service", "kuberos-robot-discovery-picking"),
    ]
    assert all(after[k] == before[k] for k in after), "undeploy touched another deployment"
    # The warehouse fleet has no other deployment: its discovery servers went too.
    assert resource_versions(apps, core, "kuberos-warehouse-fleet") == {}
    assert cluster.undeploy(os.path.join(ROOT, "examples", "two-fleets.yml")).changed == 0


def test_a_rejected_object_means_nothing_is_applied(cluster, tmp_path):
    """A cluster policy rejects one Deployment; the objects before it passed their dry run, yet none is written."""
    import time

    core, apps, _discovery = cluster.clients()
    expression = "object.metadata.?labels[?'kuberos.io/module'].orValue('') != 'zz-forbidden'"
    refusal = "module zz-forbidden is not allowed in this cluster"
    with deployments_denied(apps.api_client, "no-forbidden-modules", expression, refusal):
        spec = tmp_path / "guarded.yml"
        spec.write_text(
            "metadata: {name: guarded, targetFleet: warehouse-fleet}\nrosModules:\n"
            "- {name: allowed, image: ghcr.io/x/a:1, launch: run, requirements: {onboard: true}, rosParameters: {rate: 5}}\n"
            "- {name: zz-forbidden, image: ghcr.io/x/f:1, launch: run, requirements: {onboard: true}}\n"
        )
        deadline = time.monotonic() + 30
        while True:  # the policy takes a moment to be enforced
            result = cluster.deploy(spec, tmp_path / "render")
            if result.returncode != 0 or time.monotonic() > deadline:
                break
            cluster.undeploy(spec)
        assert result.returncode != 0, result.stdout[-4000:]
        assert "nothing was applied" in result.stdout, result.stdout[-4000:]
        assert "module zz-forbidden is not allowed in this cluster" in result.stdout
        # The refusal names the object; the other objects passed their dry run, and still none of them was written.
        assert "Deployment kuberos-warehouse-fleet/guarded-zz-forbidden-" in result.stdout, result.stdout[-4000:]
        assert resource_versions(apps, core, "kuberos-warehouse-fleet") == {}


def test_check_mode_applies_nothing(cluster, tmp_path):
    _core, apps, _discovery = cluster.clients()
    spec = tmp_path / "checked.yml"
    spec.write_text(
        "metadata: {name: checked, targetFleet: warehouse-fleet}\n"
        "rosModules:\n- {name: driver, image: ghcr.io/x/driver:1, launch: run, requirements: {onboard: true}}\n"
    )
    result = cluster.deploy(spec, tmp_path / "render", "--check")
    assert result.returncode == 0, result.stdout[-6000:]
    assert result.changed >= 1
    assert apps.list_namespaced_deployment("kuberos-warehouse-fleet", label_selector="kuberos.io/deployment=checked").items == []


def test_the_role_alone_in_a_users_play_deploys_the_same_way(cluster, tmp_path):
    """roles/rosdeployment/tasks/main.yml from a user's single-play playbook: same result, idempotent, undeployable."""
    core, _apps, _discovery = cluster.clients()
    spec = tmp_path / "solo.yml"
    spec.write_text(
        "metadata: {name: solo, targetFleet: warehouse-fleet}\n"
        "rosModules:\n- {name: driver, image: ghcr.io/x/driver:1, launch: run, requirements: {onboard: true}}\n"
    )
    play = tmp_path / "site.yml"
    play.write_text(
        "- name: Deploy with the role alone\n  hosts: localhost\n  gather_facts: false\n"
        "  roles:\n    - role: kuberos.platform.rosdeployment\n"
    )
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [
        venv_tool("ansible-playbook"), str(play), "-i", "inventories/local",
        "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={tmp_path / 'render'}",
        "-e", f"kuberos_kubeconfig={cluster.kubeconfig}",
    ]  # fmt: skip
    try:
        first = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert first.returncode == 0, first.stdout[-6000:] + first.stderr[-2000:]
        assert list(changed_by_host(first)) == ["localhost"] and changed_by_host(first)["localhost"] >= 1
        pods = pods_by_instance(core, "kuberos-warehouse-fleet")
        placement = json.loads((tmp_path / "render" / "placement.json").read_text())
        for inst in placement["instances"]:
            assert pods[inst["name"]].spec.node_name == inst["node"], inst["name"]
        again = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert again.returncode == 0 and changed_by_host(again) == {"localhost": 0}, again.stdout[-6000:]
    finally:
        assert cluster.undeploy(spec).returncode == 0
