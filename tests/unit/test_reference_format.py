"""The reference KubeROS format (kind ApplicationDeployment) and what RosDeployment gained to say the same things:
parameter maps, launch arguments with inventory device parameters, registries, privileged modules, workspaces,
shell launch lines, resource groups and Cyclone DDS.

The manifests here are this project's own, written in both formats; every rendered object is checked against the
Kubernetes 1.34 schema."""

from __future__ import annotations

import copy
import os
import subprocess
from dataclasses import replace

import kubernetes_validate
import pytest
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import manifests, naming
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    RenderOptions,
    device_options,
    launch_argument_problems,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import build_records, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import (
    file_reader,
    load_rosdeployment_file,
    load_rosdeployments,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.third_party import yaml

EXAMPLE = os.path.join(ROOT, "examples", "reference", "talker-listener.kuberos.yml")

# The example's meaning in our own format: the two must place and render alike.
OURS = """
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata:
  name: talker-listener
  targetFleet: test-fleet
  robotSelector: {robot: [fetch-1]}
parameterMaps:
- name: talker-launch
  type: key-value
  data: {topic: /chatter, LOG_LEVEL: info}
- name: talker_params.yaml
  type: yaml
  path: config/talker_params.yaml
imageRegistries:
- {name: private, pullSecret: registry-credentials, pullPolicy: IfNotPresent}
rosModules:
- name: talker
  image: registry.example.com/demo/talker:1.2
  launch: [ros2 launch demo_nodes talker.launch.py]
  shell: true
  workspace: /workspace/install
  preference: [onboard]
  privileged: true
  launchArguments:
    gripper_port: "{device:gripper.port}"
    topic: "{talker-launch.topic}"
  requirements: {max_latency: 20 ms, devices: [gripper]}
  envFrom: [talker-launch]
  parameterFiles: [{map: talker_params.yaml, mountPath: /workspace/config}]
- name: listener
  image: registry.example.com/demo/listener:1.2
  imageRegistry: private
  launch: ["ros2 run demo_nodes listener; echo listener stopped"]
  shell: true
  workspace: /workspace/install
  preference: [edge, cloud]
  requirements: {max_latency: 50 ms}
"""


def reference(text: str, name: str = "ref.yml"):
    return load_rosdeployments(text, name)


def problems_of(text: str, source: str = "ref.yml", read_file=None) -> list[str]:
    with pytest.raises(SpecError) as caught:
        load_rosdeployments(text, source, read_file=read_file)
    return [str(p) for p in caught.value.problems]


def rendered(deployments, inventory):
    placement = place_modules(deployments, inventory)
    options = replace(RenderOptions(), **device_options(inventory))
    return placement, render_deployment(deployments, placement, options), options


def by_name(objects, kind):
    return {o["metadata"]["name"]: o for o in objects if o["kind"] == kind}


MINIMAL = """
apiVersion: v1
kind: ApplicationDeployment
metadata:
  name: hello
  targetFleet: test-fleet
rosModules:
  - name: talker
    image: example/talker:1
    entrypoint: ["ros2 run demo talker"]
"""


def test_the_example_places_and_renders_as_its_translation_into_our_format(local_inventory):
    theirs = load_rosdeployment_file(EXAMPLE)
    ours = load_rosdeployments(OURS, EXAMPLE, read_file=file_reader(EXAMPLE))  # the same source: placement names it
    assert theirs[0].kind == "ApplicationDeployment" and ours[0].kind == "RosDeployment"
    placement_theirs, objects_theirs, _ = rendered(theirs, local_inventory)
    placement_ours, objects_ours, _ = rendered(ours, local_inventory)
    assert placement_theirs.to_dict() == placement_ours.to_dict()
    assert objects_theirs == objects_ours
    for obj in objects_theirs:
        kubernetes_validate.validate(obj, "1.34", strict=True)


def test_the_example_becomes_what_the_reference_means(local_inventory):
    (dep,) = load_rosdeployment_file(EXAMPLE)
    talker, listener = dep.modules
    assert dep.robots == ("fetch-1",) and dep.fleet == "test-fleet" and dep.rmw == "fastdds"
    assert talker.launch == ("ros2 launch demo_nodes talker.launch.py",) and talker.shell and listener.shell
    assert talker.workspace == "/workspace/install"  # sourceWs, its trailing '/' dropped
    assert talker.tiers == ("onboard",) and listener.tiers == ("edge", "cloud")
    assert talker.requirements.max_latency_ms == 20 and talker.requirements.devices == ("gripper",)
    assert talker.privileged and not listener.privileged
    assert talker.env_from == ("talker-launch",)
    assert talker.parameter_files == (("talker_params.yaml", "/workspace/config"),)
    assert [(a.name, a.value, a.device, a.parameter) for a in talker.launch_arguments] == [
        ("gripper_port", "", "gripper", "port"),
        ("topic", "/chatter", "", ""),
    ]
    assert listener.registry.pull_secret == "registry-credentials" and talker.registry is None
    notes = "\n".join(dep.notes)
    for field in ("rosVersion", "appVersion", "edgeResourceGroup", "dynamicRescheduling", "useBridge"):
        assert f".{field}:" in notes, field
    assert "talker-listener.kuberos.yml:27: rosModules[0].requirements.dynamicRescheduling" in notes

    _placement, objects, _ = rendered([dep], local_inventory)
    deployment = by_name(objects, "Deployment")["talker-listener-talker-fetch-1"]
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    # bash sources ROS and the workspace, then runs the line with the arguments appended, fetch-1's gripper port
    assert container["command"][:2] == ["/bin/bash", "-c"]
    assert container["command"][3:] == [
        "/workspace/install",
        "ros2 launch demo_nodes talker.launch.py gripper_port:=/dev/ttyUSB0 topic:=/chatter",
    ]
    assert container["securityContext"] == {"privileged": True, "runAsUser": 0}  # privileged: root, unless it names a user
    assert container["envFrom"] == [{"configMapRef": {"name": naming.parameter_map_name("talker-listener", "talker-launch")}}]
    assert container["volumeMounts"] == [{"name": "parameter-file-0", "mountPath": "/workspace/config", "readOnly": True}]
    maps = by_name(objects, "ConfigMap")
    params = maps[naming.parameter_map_name("talker-listener", "talker_params.yaml")]["data"]
    assert yaml.safe_load(params["talker_params.yaml"]) == {
        "talker": {"ros__parameters": {"publish_rate_hz": 10.0, "frame_id": "base_link"}}
    }
    listener_pod = by_name(objects, "Deployment")["talker-listener-listener-fetch-1"]["spec"]["template"]["spec"]
    assert listener_pod["imagePullSecrets"] == [{"name": "registry-credentials"}]


def test_launch_arguments_run_as_written_in_bash_and_literally_without_it(tmp_path, local_inventory):
    """The rendered commands run for real. With shell (the reference format) bash sources the workspace, the line's
    ';' works and the arguments are bash words as written: the reference's pre-quoted values lose their quotes as the
    reference's shell would. Without shell, a value is one argument, whatever it holds, and runs nothing."""
    workspace = tmp_path / "ws"
    workspace.mkdir()
    (workspace / "setup.bash").write_text("export FROM_WORKSPACE=sourced\n")
    text = f"""
apiVersion: v1
kind: ApplicationDeployment
metadata: {{name: hello, targetFleet: test-fleet, targetRobots: [fetch-1]}}
rosModules:
  - name: talker
    image: example/talker:1
    entrypoint: ["echo $FROM_WORKSPACE; printf '<%s>' "]
    sourceWs: {workspace}/
    launchParameters:
      goals: {{args.goals}}
    rosParameters: [{{name: args, type: key-value, valueFrom: args}}]
rosParamMap:
  - name: args
    type: key-value
    data: {{goals: "'2,-2,0;0,-3.5,0'"}}
"""
    _placement, objects, _ = rendered(reference(text), local_inventory)
    (container,) = by_name(objects, "Deployment")["hello-talker-fetch-1"]["spec"]["template"]["spec"]["containers"]
    out = subprocess.run(container["command"], capture_output=True, text=True, timeout=10, check=True)
    assert out.stdout.splitlines() == ["sourced", "<goals:=2,-2,0;0,-3.5,0>"]

    literal = f"""
metadata: {{name: plain, targetFleet: test-fleet, robotSelector: {{robot: [fetch-1]}}}}
parameterMaps: [{{name: args, type: key-value, data: {{evil: "$(touch {tmp_path}/pwned); x"}}}}]
rosModules:
  - name: talker
    image: example/talker:1
    launch: "printf '<%s>'"
    workspace: {workspace}
    launchArguments: {{evil: "{{args.evil}}"}}
"""
    _placement, objects, _ = rendered(load_rosdeployments(literal, "plain.yml"), local_inventory)
    (container,) = by_name(objects, "Deployment")["plain-talker-fetch-1"]["spec"]["template"]["spec"]["containers"]
    out = subprocess.run(container["command"], capture_output=True, text=True, timeout=10, check=True)
    assert out.stdout == f"<evil:=$(touch {tmp_path}/pwned); x>"
    assert not (tmp_path / "pwned").exists()


def test_device_references_in_flow_mapping_form_take_the_robots_device(local_inventory):
    """`robot_ip: {SIM_ARM.ROBOT_IP}` is a YAML flow mapping; it names the device sim-arm's parameter robot-ip, taken
    from the module's node when it carries the device, else from its robot's computer (an edge module driving the
    robot's gripper gets the robot's port); a node and robot without the parameter is reported before rendering."""
    text = MINIMAL + "    preference: [edge]\n    launchParameters:\n      port: {GRIPPER.PORT}\n      model: {GRIPPER.MODEL}\n"
    (dep,) = reference(text)
    (module,) = dep.modules
    assert module.requirements.devices == ()
    assert [(a.device, a.parameter) for a in module.launch_arguments] == [("gripper", "port"), ("gripper", "model")]
    assert any("takes parameter port of device gripper from the inventory" in n for n in dep.notes)
    placement, objects, options = rendered([dep], local_inventory)
    assert {i.node for i in placement.instances} <= {"edge-1", "edge-2"}
    commands = {
        name: d["spec"]["template"]["spec"]["containers"][0]["command"][-1]
        for name, d in by_name(objects, "Deployment").items()
        if name.startswith("hello-")
    }
    assert commands == {
        "hello-talker-fetch-1": "ros2 run demo talker port:=/dev/ttyUSB0 model:=robotiq-2f85",
        "hello-talker-fetch-2": "ros2 run demo talker port:=/dev/ttyUSB1 model:=robotiq-2f85",
    }
    missing = launch_argument_problems([dep], placement, replace(options, device_parameters=()))
    assert sorted((m[1], m[4], m[5]) for m in missing) == sorted(
        [("talker", "gripper", "model"), ("talker", "gripper", "port")] * 2
    )


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (
            lambda d: d["rosModules"][0].update(entrypoint=7),
            "ref.yml:9: rosModules[0].entrypoint: 7 (int) is not valid; expected a list whose first item is the command line",
        ),
        (
            lambda d: d["rosModules"][0].update(requirements={"latency": "fast"}),
            "ref.yml:12: rosModules[0].requirements.latency: 'fast' is not valid",
        ),
        (lambda d: d["metadata"].update(targetRobots=["Robot_1"]), "ref.yml:6: metadata.targetRobots[0]: 'Robot_1' is not valid"),
        (
            lambda d: d["rosModules"][0].update(rosParameters=[{"name": "a", "type": "key-value", "valueFrom": "nope"}]),
            "rosModules[0].rosParameters[0].valueFrom: 'nope' is not a parameter map",
        ),
        (lambda d: d["metadata"].update(rmwImplementation="zenoh"), "metadata.rmwImplementation: 'zenoh' is not valid"),
        (lambda d: d.update(rosModules="all"), "rosModules: 'all' is not valid; expected a non-empty list of modules"),
        (lambda d: d["rosModules"].append(["x"]), "rosModules[1]: ['x'] (list) is not valid"),
        (
            lambda d: d["rosModules"][0].update(launchParameters={"a": "{Mixed.key}"}),
            "rosModules[0].launchParameters.a: '{Mixed.key}' is neither a device (UPPERCASE) nor a parameter map",
        ),
        (
            lambda d: d["rosModules"][0].update(launchParameters={"a": "{missing.key}"}),
            "rosModules[0].launchParameters.a: '{missing.key}': missing is neither a rosParameters entry",
        ),
        (
            lambda d: d["rosModules"][0].update(preference=["moon"]),
            "rosModules[0].preference",
        ),
    ],
)
def test_bad_reference_manifests_name_the_reference_field(change, expected):
    data = yaml.safe_load(MINIMAL)
    change(data)
    found = problems_of(yaml.safe_dump(data, sort_keys=False))
    assert any(expected in p for p in found), found


def test_hostile_reference_manifests_are_refused_without_a_traceback():
    for text in (
        "kind: ApplicationDeployment\nmetadata: []\nrosModules: {}\n",
        "kind: ApplicationDeployment\nrosModules: [{name: a, launchParameters: [1, 2], requirements: 3}]\n",
        "kind: ApplicationDeployment\nrosParamMap: [{name: x, type: yaml, path: ../../../etc/shadow}]\n",
        "kind: ApplicationDeployment\ncontainerRegistry: [7]\nrosModules: [{name: a, rosParameters: [null]}]\n",
    ):
        assert problems_of(text)  # SpecError, nothing else


def test_rmw_from_a_key_value_map_and_its_conflict_with_metadata():
    text = (
        MINIMAL
        + """    rosParameters: [{name: env, type: key-value, valueFrom: env}]
rosParamMap:
  - {name: env, type: key-value, data: {RMW_IMPLEMENTATION: rmw_cyclonedds_cpp, WORLD: maze}}
"""
    )
    (dep,) = reference(text)
    assert dep.rmw == "cyclonedds"
    assert any("chooses cyclonedds for the whole deployment" in n for n in dep.notes)
    assert any(
        "RMW_IMPLEMENTATION' of parameter map env is not an environment variable (KubeROS sets it)" in n for n in dep.notes
    )
    conflicting = text.replace("targetFleet: test-fleet", "targetFleet: test-fleet\n  rmwImplementation: fastdds")
    assert any("chooses cyclonedds, but metadata.rmwImplementation is fastdds" in p for p in problems_of(conflicting))


def test_cyclonedds_gives_each_instance_the_peers_it_talks_with(local_inventory):
    """Each instance gets a headless Service and a configuration naming the instances that serve one of its robots:
    the lists are symmetric, and a moved instance keeps its name."""
    text = OURS.replace("kind: RosDeployment\n", "kind: RosDeployment\nrmw: cyclonedds\n").replace(
        "  robotSelector: {robot: [fetch-1]}\n", ""
    )
    deps = load_rosdeployments(text, EXAMPLE, read_file=file_reader(EXAMPLE))
    placement, objects, _ = rendered(deps, local_inventory)
    peers = manifests.cyclonedds_peers(deps[0], placement, "cluster.local")
    assert peers["talker-listener-talker-fetch-1"] == ["talker-listener-listener-fetch-1.kuberos-test-fleet.svc.cluster.local"]
    for name, names in peers.items():
        for other in names:
            assert f"{name}.kuberos-test-fleet.svc.cluster.local" in peers[other.split(".")[0]]
    services = by_name(objects, "Service")
    ports = services["talker-listener-talker-fetch-2"]["spec"]["ports"]
    assert [p["port"] for p in ports][:2] == [7410, 7412] and len(ports) == 32 and {p["protocol"] for p in ports} == {"UDP"}
    pod = by_name(objects, "Deployment")["talker-listener-talker-fetch-2"]["spec"]["template"]["spec"]
    env = {e["name"]: e.get("value") for e in pod["containers"][0]["env"]}
    assert env["RMW_IMPLEMENTATION"] == "rmw_cyclonedds_cpp" and "ROS_DISCOVERY_SERVER" not in env
    assert env["CYCLONEDDS_URI"] == "file:///etc/kuberos-cyclonedds/talker-listener-talker-fetch-2.xml"
    config = by_name(objects, "ConfigMap")["talker-listener-cyclonedds"]["data"]["talker-listener-talker-fetch-2.xml"]
    assert "<AllowMulticast>false</AllowMulticast>" in config
    assert '<Peer Address="talker-listener-listener-fetch-2.kuberos-test-fleet.svc.cluster.local"/>' in config
    for obj in objects:
        kubernetes_validate.validate(obj, "1.34", strict=True)


def test_a_changed_parameter_map_restarts_only_the_modules_that_read_it(local_inventory):
    deps = load_rosdeployments(OURS, EXAMPLE, read_file=file_reader(EXAMPLE))
    _p, before, _o = rendered(deps, local_inventory)
    changed = load_rosdeployments(OURS.replace("LOG_LEVEL: info", "LOG_LEVEL: debug"), EXAMPLE, read_file=file_reader(EXAMPLE))
    _p, after, _o = rendered(changed, local_inventory)
    old, new = by_name(before, "Deployment"), by_name(after, "Deployment")
    talker = "talker-listener-talker-fetch-1"
    assert old[talker]["spec"]["template"] != new[talker]["spec"]["template"]  # its maps' hash changed
    assert old["talker-listener-listener-fetch-1"] == new["talker-listener-listener-fetch-1"]


@pytest.mark.parametrize("rmw", ["fastdds", "cyclonedds"])
def test_the_record_keeps_the_files_and_renders_the_same_without_them(local_raw, local_inventory, rmw):
    """The controller re-renders from the record alone: the parameter file and the device parameters travel in it
    (and, with Cyclone DDS, the peer lists and Services come out the same)."""
    text = open(EXAMPLE, encoding="utf-8").read()
    if rmw == "cyclonedds":
        text = text.replace("  edgeResourceGroup: ['public']", "  edgeResourceGroup: ['public']\n  rmwImplementation: cyclonedds")
    deps = load_rosdeployments(text, EXAMPLE, read_file=file_reader(EXAMPLE))
    assert deps[0].rmw == rmw
    placement, objects, options = rendered(deps, local_inventory)
    _revision, record = build_records(text, EXAMPLE, deps, placement, local_raw, options, "kuberos")
    back = parse_record(copy.deepcopy(record))
    assert back.deployments[0].parameter_maps == deps[0].parameter_maps
    assert render_deployment(back.deployments, back.placement, back.options) == objects


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("parameterMaps: [{name: m, type: key-value}]", "parameterMaps[0]: needs data (the map inline) or path"),
        ("parameterMaps: [{name: m, type: key-value, data: {a: 1}, path: x.yaml}]", "parameterMaps[0]: needs data"),
        ("parameterMaps: [{name: m, type: key-value, data: {a: {b: 1}}}]", "key-value map has 'a' with a value"),
        ("parameterMaps: [{name: m, type: key-value, path: x.yaml}]", "parameterMaps[0].path: files cannot be read here"),
    ],
)
def test_bad_parameter_maps(spec, expected):
    text = f"""
metadata: {{name: demo, targetFleet: test-fleet}}
{spec}
rosModules: [{{name: a, image: example/a:1, launch: run}}]
"""
    assert any(expected in p for p in problems_of(text)), problems_of(text)


@pytest.mark.parametrize(
    ("module", "expected"),
    [
        ("envFrom: [nope]", "rosModules[0].envFrom[0]: 'nope' is not a parameter map; expected one of: bad, file, vars"),
        ("envFrom: [file]", "rosModules[0].envFrom[0]: parameter map file is yaml; expected a key-value map"),
        ("envFrom: [bad]", "rosModules[0].envFrom[0]: parameter map bad key 'not-a-name' is not an environment variable"),
        ("parameterFiles: [{map: vars, mountPath: /c}]", "parameter map vars is key-value; expected a yaml map"),
        ("launchArguments: {a: '{vars.missing}'}", "parameter map vars has no key 'missing'; its keys: WORLD"),
        (
            "launchArguments: {a: '{device:lidar.ip}'}\n  strategy: shared",
            "takes a device parameter, but a shared instance serves several robots",
        ),
        ("launchArguments: {a: 'x{vars.WORLD}'}", "is not valid; expected a value, '{map.key}'"),
        ("imageRegistry: other", "rosModules[0].imageRegistry: 'other' is not in imageRegistries; expected one of: default"),
        ("workspace: relative/dir", "rosModules[0].workspace"),
    ],
)
def test_bad_module_references(module, expected):
    text = f"""
metadata: {{name: demo, targetFleet: test-fleet}}
imageRegistries: [{{name: default, pullSecret: creds}}]
parameterMaps:
- {{name: vars, type: key-value, data: {{WORLD: maze}}}}
- {{name: bad, type: key-value, data: {{not-a-name: 1}}}}
- {{name: file, type: yaml, data: {{node: {{ros__parameters: {{a: 1}}}}}}}}
rosModules:
- name: a
  image: example/a:1
  launch: run
  {module}
"""
    found = problems_of(text)
    assert any(expected in p for p in found), found


def test_the_default_registry_serves_modules_that_name_none(local_inventory):
    text = """
metadata: {name: demo, targetFleet: test-fleet}
imageRegistries: [{name: default, pullSecret: creds, pullPolicy: Always}]
rosModules: [{name: a, image: example/a:1, launch: run}]
"""
    _p, objects, _o = rendered(load_rosdeployments(text, "s.yml"), local_inventory)
    pod = by_name(objects, "Deployment")["demo-a-fetch-1"]["spec"]["template"]["spec"]
    assert pod["imagePullSecrets"] == [{"name": "creds"}] and pod["containers"][0]["imagePullPolicy"] == "Always"


def test_resource_groups_keep_modules_on_the_named_groups(local_raw):
    raw = copy.deepcopy(local_raw)
    raw["hosts"]["edge-2"]["kuberos_resource_group"] = "lab"
    inventory = load_inventory(raw)
    text = """
metadata: {name: demo, targetFleet: test-fleet}
resourceGroups: [lab]
rosModules: [{name: a, image: example/a:1, launch: run, preference: edge}]
"""
    placement = place_modules(load_rosdeployments(text, "s.yml"), inventory)
    assert {i.node for i in placement.instances} == {"edge-2"}


def test_device_parameters_must_belong_to_the_hosts_devices(local_raw):
    raw = copy.deepcopy(local_raw)
    raw["hosts"]["fetch-1"]["kuberos_device_parameters"] = {"lidar": {"ip": "10.0.0.1"}, "gripper": [1]}
    with pytest.raises(SpecError) as caught:
        load_inventory(raw)
    text = str(caught.value)
    assert "hosts.fetch-1.kuberos_device_parameters.lidar: names a device the host does not carry" in text
    assert "hosts.fetch-1.kuberos_device_parameters.gripper: [1] (list) is not valid" in text


def test_reference_quirks_read_as_the_reference_reads_them(local_inventory):
    """latency 0 is no requirement; a launch key missing from the named map is read from another map the module
    attaches; no preference means onboard first. Each is noted."""
    text = MINIMAL.replace(
        'entrypoint: ["ros2 run demo talker"]', 'entrypoint: ["ros2 run demo talker"]\n    requirements: {latency: 0ms}'
    )
    text += """    launchParameters:
      world: {launch-parameters.world}
      headless: {launch-parameters.headless}
    rosParameters:
      - {name: launch-parameters, type: key-value, valueFrom: eval}
      - {name: environment, type: key-value, valueFrom: env}
rosParamMap:
  - {name: eval, type: key-value, data: {world: maze}}
  - {name: env, type: key-value, data: {headless: true}}
"""
    (dep,) = reference(text)
    (module,) = dep.modules
    assert module.requirements.max_latency_ms is None
    assert [(a.name, a.value, a.map) for a in module.launch_arguments] == [("world", "maze", "eval"), ("headless", "true", "env")]
    notes = "\n".join(dep.notes)
    assert "requirements.latency: '0ms': no latency requirement" in notes
    assert "key headless is not in eval but in env" in notes
    assert "rosModules[0].preference: not given: onboard (the reference's default) first" in notes


def test_reference_problems_say_what_is_missing_and_name_its_fields(local_inventory):
    no_type = MINIMAL + "    rosParameters: [{name: p, valueFrom: params}]\n"
    assert any(
        "rosParameters[0].valueFrom: 'params' names no rosParamMap (and type is not given)" in p for p in problems_of(no_type)
    )
    no_modules = "apiVersion: v1\nkind: ApplicationDeployment\nmetadata: {name: x, targetFleet: test-fleet}\n"
    assert any("rosModules" in p and "required" in p for p in problems_of(no_modules)), problems_of(no_modules)
    (dep,) = reference(MINIMAL.replace("targetFleet: test-fleet", "targetFleet: test-fleet\n  targetRobots: [simbot-1]"))
    with pytest.raises(SpecError) as caught:
        place_modules([dep], local_inventory)
    assert "ref.yml:7: metadata.targetRobots[0]: 'simbot-1' is not a robot of fleet test-fleet" in str(caught.value)
