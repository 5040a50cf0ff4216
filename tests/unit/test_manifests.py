"""Rendering: golden files for the examples, Kubernetes schema validation and wiring invariants.

Regenerate the golden files after an intended change with ``UPDATE_GOLDEN=1 make unit``.
"""

from __future__ import annotations

import os
import shutil
import subprocess

import kubernetes_validate
import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels, manifests, naming
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    RenderOptions,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement_map import render_placement_svg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file, parse_rosdeployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import placement_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_dir import apply_plan, plan_render_dir

KUBERNETES_VERSION = "1.34"
GOLDEN = os.path.join(os.path.dirname(__file__), "golden")
EXAMPLES = ["listing1", "pick-and-place", "two-fleets"]


def render_example(root, inventory, name):
    deployments = load_rosdeployment_file(os.path.join(root, "examples", f"{name}.yml"), f"examples/{name}.yml")
    placement = place_modules(deployments, inventory)
    return deployments, placement, render_deployment(deployments, placement, RenderOptions())


def tree(path):
    files = {}
    for dirpath, _dirs, names in os.walk(path):
        for name in names:
            full = os.path.join(dirpath, name)
            with open(full, encoding="utf-8") as handle:
                files[os.path.relpath(full, path)] = handle.read()
    return files


@pytest.mark.parametrize("name", EXAMPLES)
def test_golden_files(root, local_inventory, name, tmp_path):
    _deployments, placement, objects = render_example(root, local_inventory, name)
    picture = render_placement_svg(placement)
    plan = plan_render_dir(str(tmp_path / name), objects, placement.to_dict(), placement_table(placement), picture)
    apply_plan(plan)
    golden = os.path.join(GOLDEN, name)
    if os.environ.get("UPDATE_GOLDEN"):
        shutil.rmtree(golden, ignore_errors=True)
        shutil.copytree(tmp_path / name, golden)
    got, want = tree(tmp_path / name), tree(golden)
    assert sorted(got) == sorted(want)
    for rel in want:
        assert got[rel] == want[rel], f"{rel} differs from the golden file; UPDATE_GOLDEN=1 regenerates after review"


@pytest.mark.parametrize("name", EXAMPLES)
def test_manifests_pass_kubernetes_schema(root, local_inventory, name):
    _deployments, _placement, objects = render_example(root, local_inventory, name)
    for obj in objects:
        kubernetes_validate.validate(obj, KUBERNETES_VERSION, strict=True)


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_module_is_pinned_and_wired_to_its_fleets_discovery_servers(root, local_inventory, name):
    deployments, placement, objects = render_example(root, local_inventory, name)
    services = {(o["metadata"]["namespace"], o["metadata"]["name"]) for o in objects if o["kind"] == "Service"}
    by_instance = {inst.name: inst for inst in placement.instances}
    modules = [
        o for o in objects if o["kind"] == "Deployment" and o["metadata"]["labels"]["kuberos.io/component"] == "ros-module"
    ]
    assert len(modules) == len(placement.instances)
    for obj in modules:
        inst = by_instance[obj["metadata"]["name"]]
        pod = obj["spec"]["template"]["spec"]
        assert pod["nodeSelector"] == {labels.HOSTNAME: inst.node}
        assert obj["metadata"]["namespace"] == inst.namespace
        env = {e["name"]: e.get("value") for e in pod["containers"][0]["env"]}
        assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
        servers = env["ROS_DISCOVERY_SERVER"].split(";")
        expected = placement.discovery[inst.fleet]
        if inst.tier == "onboard":
            # the robot's own server comes last, at the first id after the fleet's: its deployment's node-local Service
            # and, on this robot, a server Deployment of that id pinned there
            host, port = servers.pop().rsplit(":", 1)
            service = f"kuberos-robot-discovery-{inst.deployment}"
            assert host == f"$({service.upper().replace('-', '_')}_SERVICE_HOST)", host
            assert (inst.namespace, service) in services
            assert int(port) == expected[0].port
            own = [
                o for o in objects
                if o["kind"] == "Deployment" and o["metadata"]["labels"]["kuberos.io/component"] == "robot-discovery-server"
                and o["metadata"]["labels"]["kuberos.io/deployment"] == inst.deployment
                and o["spec"]["template"]["spec"]["nodeSelector"] == {labels.HOSTNAME: inst.node}
            ]  # fmt: skip
            assert len(own) == 1
            assert own[0]["spec"]["template"]["spec"]["containers"][0]["args"] == manifests.discovery_server_args(
                len(expected), 11811
            )
        assert len(servers) == len(expected)
        for server_id, address in enumerate(servers):
            host, port = address.rsplit(":", 1)
            # the Service's cluster IP as the kubelet expands it: a Service of the module's own namespace
            service = f"kuberos-discovery-{server_id}"
            assert host == f"$({service.upper().replace('-', '_')}_SERVICE_HOST)", host
            assert (obj["metadata"]["namespace"], service) in services
            assert int(port) == expected[server_id].port
        assert env["KUBEROS_ROBOTS"] == ",".join(inst.robots)
        tolerations = pod.get("tolerations", [])
        assert (inst.tier == "onboard") == bool(tolerations)
        if inst.tier == "onboard":
            # an onboard pod stays on its robot however long the robot is offline: no tolerationSeconds
            offline = [t for t in tolerations if t["effect"] == "NoExecute"]
            assert offline == [
                {"key": "node.kubernetes.io/unreachable", "operator": "Exists", "effect": "NoExecute"},
                {"key": "node.kubernetes.io/not-ready", "operator": "Exists", "effect": "NoExecute"},
            ]
    for dep in deployments:
        for obj in modules:
            if obj["metadata"]["labels"]["kuberos.io/deployment"] == dep.name:
                env = {e["name"]: e.get("value") for e in obj["spec"]["template"]["spec"]["containers"][0]["env"]}
                assert env["ROS_DOMAIN_ID"] == str(dep.ros_domain_id)


def test_discovery_server_objects(local_inventory, root):
    _deployments, placement, objects = render_example(root, local_inventory, "two-fleets")
    for fleet, servers in placement.discovery.items():
        namespace = servers[0].namespace
        deploys = [
            o
            for o in objects
            if o["kind"] == "Deployment"
            and o["metadata"]["namespace"] == namespace
            and o["metadata"]["labels"].get("kuberos.io/component") == "discovery-server"
        ]
        assert len(deploys) == len(servers), fleet
        for obj, server in zip(sorted(deploys, key=lambda o: o["metadata"]["name"]), servers, strict=True):
            container = obj["spec"]["template"]["spec"]["containers"][0]
            assert "command" not in container  # the image's entrypoint stays (published ROS images source ROS there)
            assert container["args"] == manifests.discovery_server_args(server.server_id, 11811)
            assert container["args"][-4:] == ["-i", str(server.server_id), "-p", "11811"]
            env = {e["name"]: e["value"] for e in container["env"]}
            # it announces its Service's address: replaced at a new pod address, its clients still reach it
            assert env[manifests.DISCOVERY_ADDRESS_ENV] == f"$({naming.service_host_variable(obj['metadata']['name'])})"
            assert any(s["metadata"]["name"] == obj["metadata"]["name"] for s in objects if s["kind"] == "Service")
            peers = env.get("ROS_DISCOVERY_SERVER", "").split(";")
            # linked to the fleet's other servers (a replaced one copies what they know), never to itself
            assert sum(bool(p) for p in peers) == len(servers) - 1 and not peers[server.server_id], peers
            assert obj["spec"]["template"]["spec"]["nodeSelector"] == {labels.HOSTNAME: server.node}
        svcs = [o for o in objects if o["kind"] == "Service" and o["metadata"]["namespace"] == namespace]
        assert all(
            s["spec"]["ports"] == [{"name": "discovery", "port": 11811, "targetPort": 11811, "protocol": "UDP"}] for s in svcs
        )
    namespaces = [o["metadata"]["name"] for o in objects if o["kind"] == "Namespace"]
    assert namespaces == ["kuberos-test-fleet", "kuberos-warehouse-fleet"]


def _run_discovery_container(tmp_path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """The rendered server container's args run by sh, with a fast-discovery-server on PATH that prints its argv and
    the profile file it was given (the real program: tests/integration/test_discovery_netns.py)."""
    fake = tmp_path / "fast-discovery-server"
    fake.write_text('#!/bin/sh\nprintf "%s\\n" "$@"; cat "$2"\n')
    fake.chmod(0o755)
    args = manifests.discovery_server_args(3, 11811, delay_s=0)
    base = {"PATH": f"{tmp_path}:/usr/bin:/bin", "TMPDIR": str(tmp_path), manifests.DISCOVERY_PROFILE_ENV: "<dds/>"}
    return subprocess.run(args, env={**base, **env}, capture_output=True, text=True, timeout=30, check=False)


def test_the_discovery_container_announces_its_services_address_and_refuses_to_start_without_it(tmp_path):
    served = _run_discovery_container(tmp_path, {manifests.DISCOVERY_ADDRESS_ENV: "10.96.0.17"})
    assert served.returncode == 0, served.stderr
    argv = served.stdout.splitlines()
    assert argv[0] == "-x" and argv[2:8] == ["-l", "10.96.0.17", "-i", "3", "-p", "11811"], argv
    assert argv[-1] == "<dds/>"  # the profile from the environment, written to a file of its own
    # the Service did not exist when the container started: the kubelet left the reference as it was
    unresolved = f"$({naming.service_host_variable('kuberos-discovery-3')})"
    refused = _run_discovery_container(tmp_path, {manifests.DISCOVERY_ADDRESS_ENV: unresolved})
    assert refused.returncode == 1 and not refused.stdout, refused
    assert "its Service did not exist when the container started" in refused.stderr and unresolved in refused.stderr
    # without the variable (what a server rendered before announced): every address of its pod
    before = _run_discovery_container(tmp_path, {})
    assert before.stdout.splitlines()[2:4] == ["-l", "0.0.0.0"], before


def test_gpu_parameters_and_multi_command_launch(local_inventory, root):
    _deployments, _placement, objects = render_example(root, local_inventory, "two-fleets")
    detector = next(
        o for o in objects if o["kind"] == "Deployment" and o["metadata"]["name"].startswith("inventory-scan-detector")
    )
    resources = detector["spec"]["template"]["spec"]["containers"][0]["resources"]
    assert resources["limits"]["nvidia.com/gpu"] == "1" and resources["requests"]["nvidia.com/gpu"] == "1"
    lidar = next(
        o for o in objects if o["kind"] == "Deployment" and o["metadata"]["name"].startswith("inventory-scan-lidar-driver")
    )
    containers = lidar["spec"]["template"]["spec"]["containers"]
    assert [(c["name"], c["args"]) for c in containers] == [
        ("lidar-driver", ["ros2", "run", "lidar_driver", "driver_node"]),
        ("lidar-driver-1", ["ros2", "run", "lidar_driver", "filter_node"]),
    ]
    _deployments, _placement, objects = render_example(root, local_inventory, "pick-and-place")
    params = next(o for o in objects if o["kind"] == "ConfigMap" and o["metadata"]["name"] == "pick-and-place-perception-params")
    document = yaml.safe_load(params["data"]["params.yaml"])
    assert document == {"/**": {"ros__parameters": {"max_rate_hz": 2.0, "voxel_size": 0.01}}}


@pytest.mark.parametrize(
    ("launch", "argvs"),
    [
        (("ros2 launch pkg file.launch.py",), [["ros2", "launch", "pkg", "file.launch.py"]]),
        (("ros2 run pkg node --ros-args -p 'name:=a b'",), [["ros2", "run", "pkg", "node", "--ros-args", "-p", "name:=a b"]]),
        (("a", "b --x"), [["a"], ["b", "--x"]]),
        (
            ("a $(touch x) `id` $HOME; b && c | d > e # f",),
            [["a", "$(touch", "x)", "`id`", "$HOME;", "b", "&&", "c", "|", "d", ">", "e", "#", "f"]],
        ),
        (("a '#' \\$x *",), [["a", "#", "$x", "*"]]),
    ],
)
def test_container_argvs(local_inventory, launch, argvs):
    """Each launch line is one container of the rendered pod, started with its literal argv."""
    spec = {
        "metadata": {"name": "argv", "targetFleet": "test-fleet", "robotSelector": {"robot": ["fetch-1"]}},
        "rosModules": [{"name": "m", "image": "example/m:1", "launch": list(launch)}],
    }
    deployments = [parse_rosdeployment(spec)]
    objects = render_deployment(deployments, place_modules(deployments, local_inventory), RenderOptions())
    (deployment,) = [o for o in objects if o["kind"] == "Deployment" and o["metadata"]["name"] == "argv-m-fetch-1"]
    assert [c["args"] for c in deployment["spec"]["template"]["spec"]["containers"]] == argvs


@pytest.mark.parametrize("name", EXAMPLES)
def test_placement_picture_shows_every_node_and_instance(root, local_inventory, name):
    import xml.etree.ElementTree as ET

    _deployments, placement, _objects = render_example(root, local_inventory, name)
    svg = render_placement_svg(placement)
    texts = [el.text or "" for el in ET.fromstring(svg).iter("{http://www.w3.org/2000/svg}text")]
    for node in placement.nodes:
        assert any(t.startswith(node["name"]) for t in texts), node["name"]
    for inst in placement.instances:
        serves = inst.robots[0] if len(inst.robots) == 1 else f"{len(inst.robots)} robots"
        assert f"{inst.module} · {serves}" in texts
    for fleet, servers in placement.discovery.items():
        for server in servers:
            assert f"◆ discovery-{server.server_id} ({fleet})" in texts
    robot_links = sum(len(i.robots) for i in placement.instances if i.tier != "onboard")
    assert svg.count("<path ") == robot_links


def test_readme_picture_is_current(root):
    with open(os.path.join(GOLDEN, "pick-and-place", "placement.svg"), encoding="utf-8") as handle:
        golden = handle.read()
    with open(os.path.join(root, "docs", "images", "placement-pick-and-place.svg"), encoding="utf-8") as handle:
        assert handle.read() == golden, "copy tests/unit/golden/pick-and-place/placement.svg to docs/images/"


def test_libyaml_and_python_emitters_write_the_same_text():
    """Rendered files come from libyaml's emitter when PyYAML has it; they must read as the pure-Python one writes."""
    import glob

    import yaml

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifest_yaml

    assert yaml.__with_libyaml__ and manifest_yaml.DUMPER is not manifest_yaml.PURE_DUMPER
    objects = [
        doc
        for path in sorted(glob.glob(os.path.join(GOLDEN, "**", "*.yaml"), recursive=True))
        for doc in yaml.safe_load_all(open(path, encoding="utf-8"))
        if isinstance(doc, dict)
    ]
    objects.append(
        {"text": "multi\nline\n", "trailing": "a \nb", "long": " ".join(["word"] * 80), "unicode": "é 🤖", "bell": "\x07",
         "crlf": "a\r\nb", "quoted": "x: y", "special": ["yes", "~", "0x1f", "*a", "&b", "%c", "@d", "#e"], "empty": {},
         "none": None, "numbers": [1, 1.5, 10**20, True]}
    )  # fmt: skip
    assert len(objects) > 40
    for obj in objects:
        assert manifest_yaml.dump_object(obj) == manifest_yaml.dump_object(obj, manifest_yaml.PURE_DUMPER)


def test_references_expand_as_the_kubelet_expands_them():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests, naming

    links = {naming.service_host_variable("kuberos-discovery-0"): "10.96.0.12"}
    assert links == {"KUBEROS_DISCOVERY_0_SERVICE_HOST": "10.96.0.12"}
    assert manifests.expand_references("$(KUBEROS_DISCOVERY_0_SERVICE_HOST):11811", links) == "10.96.0.12:11811"
    # unknown references stay as they are, $$ escapes a reference (Kubernetes' EnvVar.value rules)
    assert manifests.expand_references("$(NOPE):1;$$(KUBEROS_DISCOVERY_0_SERVICE_HOST)", links) == (
        "$(NOPE):1;$(KUBEROS_DISCOVERY_0_SERVICE_HOST)"
    )


def test_a_discovery_server_is_ready_once_its_udp_port_is_bound():
    """The readiness probe runs as written: it finds a bound UDP port in the kernel's socket table, and not a free one."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as bound:
        bound.bind(("127.0.0.1", 0))
        port = bound.getsockname()[1]
        probe = manifests.discovery_readiness_probe(port)["exec"]["command"]
        assert subprocess.run(probe, check=False).returncode == 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe_free:
        probe_free.bind(("127.0.0.1", 0))
        free = probe_free.getsockname()[1]
    assert subprocess.run(manifests.discovery_readiness_probe(free)["exec"]["command"], check=False).returncode != 0
