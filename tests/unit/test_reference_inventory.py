"""Importing a reference KubeROS site (ClusterInventory and Fleet files) as an inventory: the conversion, its notes,
and every problem of the input named by file, line and field."""

from __future__ import annotations

import os

import pytest
import yaml
from helpers import ROOT, yml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory, raw_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reference_inventory import (
    DEFAULT_CPU,
    DEFAULT_MEMORY,
    HEADER,
    import_files,
    import_site,
)

EXAMPLE = os.path.join(ROOT, "examples", "reference", "site")

# A small site, lines 1-29; hosts[3] starts on line 25. Extra hosts appended start on line 30.
CLUSTER = yml(
    """
    apiVersion: v1alpha
    kind: ClusterInventory
    metadata:
      clusterName: lab
    hosts:
      - hostname: cp-1
        accessIp: 10.0.0.1
        kuberosRole: control-plane
      - hostname: tb-1
        alias: turtle-one
        accessIp: 10.0.0.11
        kuberosRole: onboard
        locatedInRobot:
          name: tb-1
          robotId: 7
        peripheralDevices:
          - deviceName: camera
            parameter:
              fps: 30
              serial: "0042"
      - hostname: tb-2
        accessIp: 10.0.0.12
        kuberosRole: onboard
        locatedInRobot: {name: tb-2}
      - hostname: edge-1
        accessIp: 10.0.0.21
        kuberosRole: edge
        shared: true
        resourceGroup: lab-rack
    """
)
FLEET = yml(
    """
    apiVersion: v1alpha
    kind: Fleet
    metadata:
      name: lab-fleet
      description: The lab's turtles
      mainCluster: lab
    robot:
      - name: tb-1
      - name: tb-2
    """
)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


def import_texts(tmp_path, cluster=CLUSTER, fleets=(FLEET,), **options):
    """Import from files named cluster.yml and fleet.yml, fleet-2.yml...; messages name them so."""
    cluster_path = write(tmp_path, "cluster.yml", cluster)
    fleet_paths = [write(tmp_path, "fleet.yml" if i == 0 else f"fleet-{i + 1}.yml", text) for i, text in enumerate(fleets)]
    displays = {path: os.path.basename(path) for path in [cluster_path, *fleet_paths]}
    return import_files(cluster_path, fleet_paths, displays=displays, **options)


def problems_of(tmp_path, cluster=CLUSTER, fleets=(FLEET,), **options) -> list[str]:
    with pytest.raises(SpecError) as caught:
        import_texts(tmp_path, cluster, fleets, **options)
    return [str(problem) for problem in caught.value.problems]


def parsed(site) -> dict:
    """The written file as the parser sees it: Ansible's groups and host variables, then load_inventory."""
    data = yaml.safe_load(site.text())
    groups = {name: list(group["hosts"]) for name, group in data["all"]["children"].items()}
    hostvars: dict = {}
    for group in data["all"]["children"].values():
        for host, variables in group["hosts"].items():
            if variables:
                hostvars[host] = variables
            hostvars.setdefault(host, {})
    return {"groups": groups, "hostvars": hostvars, "model": load_inventory(raw_inventory(groups, hostvars))}


# --- the conversion ---------------------------------------------------------------------------------------------


def test_small_site_converts_field_by_field(tmp_path):
    site = import_texts(tmp_path)
    assert site.groups == {"robots": ["tb-1", "tb-2"], "edge": ["cp-1", "edge-1"], "control_plane": ["cp-1"]}
    hosts = site.hosts
    assert hosts["tb-1"] == {
        "ansible_host": "10.0.0.11",
        "kuberos_robot": "tb-1",
        "kuberos_fleet": "lab-fleet",
        "kuberos_cpu": DEFAULT_CPU["onboard"],
        "kuberos_memory": DEFAULT_MEMORY["onboard"],
        "kuberos_devices": ["camera"],
        "kuberos_device_parameters": {"camera": {"fps": 30, "serial": "0042"}},
    }
    assert "kuberos_devices" not in hosts["tb-2"] and "kuberos_device_parameters" not in hosts["tb-2"]
    assert hosts["edge-1"] == {
        "ansible_host": "10.0.0.21",
        "kuberos_cpu": DEFAULT_CPU["edge"],
        "kuberos_memory": DEFAULT_MEMORY["edge"],
        "kuberos_shared": True,
        "kuberos_resource_group": "lab-rack",
    }
    # The control plane is an edge host without `shared`: the reference's default, not shared.
    assert hosts["cp-1"]["kuberos_shared"] is False
    assert site.inventory["all"]["children"]["control_plane"]["hosts"] == {"cp-1": {}}


def test_written_file_round_trips_and_the_parser_accepts_it(tmp_path):
    site = import_texts(tmp_path)
    text = site.text()
    assert text.startswith("---\n" + HEADER + "\n")
    result = parsed(site)
    assert result["hostvars"]["tb-1"] == site.hosts["tb-1"]
    assert result["hostvars"]["tb-1"]["kuberos_device_parameters"]["camera"]["serial"] == "0042"  # stays a string
    model = result["model"]
    assert model.fleets == {"lab-fleet": ("tb-1", "tb-2")}
    assert model.nodes["tb-1"].devices == frozenset({"camera"})
    assert model.nodes["edge-1"].resource_group == "lab-rack"
    assert model.nodes["cp-1"].tier == "edge" and not model.nodes["cp-1"].shared


def test_file_marks_placeholders_and_keeps_reference_fields_as_comments(tmp_path):
    text = import_texts(tmp_path).text()
    assert "        tb-1:  # reference: alias turtle-one, robotId 7\n" in text
    assert "          kuberos_cpu: 2  # placeholder: write the machine's own\n" in text
    assert "          kuberos_memory: 16Gi  # placeholder: write the machine's own\n" in text
    assert "          kuberos_devices: [camera]\n" in text
    assert "# ClusterInventory: cluster.yml\n# Fleet file: fleet.yml\n# Cluster: lab\n" in text
    assert "# Fleet lab-fleet (fleet.yml): The lab's turtles\n" in text
    assert "# To check and fill in (the import's notes):\n#   - kuberos_cpu and kuberos_memory are placeholders" in text
    assert all(len(line) <= 140 for line in text.splitlines())


def test_notes_say_what_to_fill_in(tmp_path):
    notes = import_texts(tmp_path).notes
    assert notes[0].startswith("kuberos_cpu and kuberos_memory are placeholders")
    assert "control-plane 4 and 8Gi on cp-1; onboard 2 and 4Gi on tb-1, tb-2; edge 8 and 16Gi on edge-1" in notes[0]
    assert any(note.startswith("not shared: cp-1 ") for note in notes)
    assert len(notes) == 2


def test_example_site_imports(tmp_path):
    site = import_files(
        os.path.join(EXAMPLE, "cluster_inventory.yml"),
        [os.path.join(EXAMPLE, "fleet.yml")],
        displays={os.path.join(EXAMPLE, "cluster_inventory.yml"): "cluster_inventory.yml"},
    )
    model = parsed(site)["model"]
    assert model.fleets == {"mir-fleet": ("mir-1", "mir-2")}
    assert site.groups["control_plane"] == ["hall-b-master"]
    assert site.hosts["mir-1"]["kuberos_device_parameters"]["ur-arm"] == {
        "robot-ip": "10.20.1.111",
        "ur-type": "ur10e",
        "headless": True,
    }
    assert site.hosts["mir-2"]["kuberos_devices"] == ["ur-arm", "lidar"]
    assert set(site.hosts["mir-2"]["kuberos_device_parameters"]) == {"ur-arm"}  # lidar has no parameter


def test_options_set_placeholders_sharing_and_tuple_unpacking(tmp_path):
    site = import_texts(
        tmp_path, default_cpu={"onboard": "1500m", "control-plane": 16}, default_memory={"edge": "64Gi"}, default_shared=True
    )
    inventory, notes = site
    hosts = site.hosts
    assert (hosts["tb-1"]["kuberos_cpu"], hosts["cp-1"]["kuberos_cpu"], hosts["edge-1"]["kuberos_memory"]) == (
        "1500m",
        16,
        "64Gi",
    )
    assert hosts["cp-1"]["kuberos_shared"] is True
    assert not any(note.startswith("not shared") for note in notes)
    assert inventory is site.inventory


def test_plain_data_without_lines(tmp_path):
    inventory, _notes = import_site(yaml.safe_load(CLUSTER), [yaml.safe_load(FLEET)])
    assert set(inventory["all"]["children"]) == {"robots", "edge", "control_plane"}
    with pytest.raises(SpecError) as caught:
        import_site(yaml.safe_load(CLUSTER), [{**yaml.safe_load(FLEET), "robot": [{"name": "tb-9"}]}])
    assert str(caught.value.problems[0]).startswith("fleets[0]: robot[0].name: 'tb-9' is not a robot of the ClusterInventory")


def test_second_onboard_computer_is_left_out_with_a_note(tmp_path):
    extra = (
        "  - hostname: tb-1-arm\n"
        "    kuberosRole: onboard\n"
        "    onboardComputerGroup: arm-pc\n"
        "    locatedInRobot: {name: tb-1}\n"
        "    peripheralDevices: [{deviceName: arm}]\n"
    )
    site = import_texts(tmp_path, CLUSTER + extra)
    assert "tb-1-arm" not in site.hosts
    note = next(n for n in site.notes if n.startswith("hosts[4] (tb-1-arm)"))
    assert "second onboard computer of robot tb-1, whose computer is hosts[1] (tb-1)" in note
    assert "not imported (nor its devices arm)" in note
    parsed(site)


def test_robot_in_no_fleet_is_left_out_or_put_in_the_default_fleet(tmp_path):
    fleet = FLEET.replace("  - name: tb-2\n", "")
    site = import_texts(tmp_path, fleets=(fleet,))
    assert "tb-2" not in site.hosts
    assert any(n.startswith("robot tb-2 (hosts[2] (tb-2)) is in no Fleet: not imported") for n in site.notes)
    second = "  - {hostname: tb-2-arm, kuberosRole: onboard, locatedInRobot: {name: tb-2}}\n"
    assert len([n for n in import_texts(tmp_path, CLUSTER + second, fleets=(fleet,)).notes if "tb-2" in n]) == 1
    site = import_texts(tmp_path, fleets=(fleet,), default_fleet="spare")
    assert site.hosts["tb-2"]["kuberos_fleet"] == "spare"
    assert "robots tb-2 are in no Fleet: put in fleet spare (default_fleet)." in site.notes
    assert parsed(site)["model"].fleets == {"lab-fleet": ("tb-1",), "spare": ("tb-2",)}


def test_several_fleets_in_files_and_documents(tmp_path):
    two = FLEET.replace("  - name: tb-2\n", "") + "---\n" + FLEET.replace("lab-fleet", "second").replace("  - name: tb-1\n", "")
    site = import_texts(tmp_path, fleets=(two,))
    assert parsed(site)["model"].fleets == {"lab-fleet": ("tb-1",), "second": ("tb-2",)}
    assert [source for *_rest, source in site.fleets] == ["fleet.yml (document 1)", "fleet.yml (document 2)"]
    empty = yml(
        """
        apiVersion: v1alpha
        kind: Fleet
        metadata: {name: empty, mainCluster: other}
        """
    )
    site = import_texts(tmp_path, fleets=(FLEET, empty))
    assert "Fleet empty (fleet-2.yml) has no robots: the inventory knows a fleet by its robots." in site.notes
    assert "Fleet empty (fleet-2.yml) names mainCluster other, but the ClusterInventory describes cluster lab" in " ".join(
        site.notes
    )


def test_onboard_sharing_and_computer_groups_are_noted(tmp_path):
    cluster = CLUSTER.replace("    locatedInRobot: {name: tb-2}\n", "    locatedInRobot: {name: tb-2}\n    shared: true\n")
    cluster += "  - {hostname: cloud-1, kuberosRole: cloud, onboardComputerGroup: x, resourceGroup: eu}\n"
    site = import_texts(tmp_path, cluster)
    notes = " | ".join(site.notes)
    assert "shared of the onboard hosts tb-2 was ignored" in notes
    assert "onboardComputerGroup of cloud-1 was ignored: they are not onboard computers." in notes
    assert "cloud hosts cloud-1 need kuberos_vpn_address" in notes
    assert "kuberos_shared" not in site.hosts["tb-2"]


def test_site_without_control_plane_is_noted(tmp_path):
    cluster = CLUSTER.replace("kuberosRole: control-plane", "kuberosRole: edge")
    site = import_texts(tmp_path, cluster)
    assert "control_plane" not in site.groups
    assert "no host has kuberosRole control-plane: playbooks/site.yml needs the group control_plane." in site.notes


def test_names_yaml_would_read_as_other_types_are_quoted(tmp_path):
    cluster = CLUSTER.replace("hostname: edge-1", "hostname: 'null'").replace("hostname: tb-2", "hostname: '1234'")
    site = import_texts(tmp_path, cluster)
    text = site.text()
    assert "        'null':\n" in text and "        '1234':\n" in text
    assert set(parsed(site)["model"].nodes) == {"cp-1", "tb-1", "1234", "null"}


def test_import_is_deterministic(tmp_path):
    assert import_texts(tmp_path).text() == import_texts(tmp_path).text()


# --- problems ---------------------------------------------------------------------------------------------------


BAD = {
    "invalid device name": (
        ("      - deviceName: camera", "      - deviceName: Front_Camera"),
        "cluster.yml:17: hosts[1].peripheralDevices[0].deviceName: 'Front_Camera' is not a valid device name; "
        "expected lowercase letters",
    ),
    "invalid hostname": (
        ("  - hostname: edge-1", "  - hostname: Edge_1"),
        "cluster.yml:25: hosts[3].hostname: 'Edge_1' is not a valid hostname",
    ),
    "unknown role": (
        ("kuberosRole: edge", "kuberosRole: egde"),
        "cluster.yml:27: hosts[3].kuberosRole: 'egde' is not valid; did you mean 'edge'?; expected onboard | control-plane",
    ),
    "role of the wrong type": (
        ("kuberosRole: edge", "kuberosRole: [edge]"),
        "cluster.yml:27: hosts[3].kuberosRole: ['edge'] (list) is not valid; expected onboard",
    ),
    "unknown field": (
        ("    accessIp: 10.0.0.21", "    acessIp: 10.0.0.21"),
        "cluster.yml:26: hosts[3].acessIp: unknown field; did you mean 'accessIp'?",
    ),
    "missing hostname": (
        ("  - hostname: edge-1\n", "  - alias: edge-1\n"),
        "cluster.yml:25: hosts[3]: hostname is required",
    ),
    "hostname without value": (
        ("  - hostname: edge-1\n", "  - hostname:\n"),
        "cluster.yml:25: hosts[3].hostname: is required; it has no value",
    ),
    "shared not a bool": (
        ("shared: true", "shared: 'yes'"),
        "cluster.yml:28: hosts[3].shared: 'yes' is not valid; expected true or false",
    ),
    "bad address": (
        ("accessIp: 10.0.0.21", "accessIp: 10.0.0.21 and more"),
        "cluster.yml:26: hosts[3].accessIp: '10.0.0.21 and more' is not valid; expected the machine's IP address or DNS name",
    ),
    "bad resource group": (
        ("resourceGroup: lab-rack", "resourceGroup: lab rack"),
        "cluster.yml:29: hosts[3].resourceGroup: 'lab rack' is not valid",
    ),
    "onboard without robot": (
        ("    locatedInRobot: {name: tb-2}\n", ""),
        "cluster.yml:21: hosts[2]: locatedInRobot is required for an onboard computer",
    ),
    "robot on an edge host": (
        ("    resourceGroup: lab-rack\n", "    resourceGroup: lab-rack\n    locatedInRobot: {name: tb-3}\n"),
        "cluster.yml:30: hosts[3].locatedInRobot: is only for an onboard computer, but kuberosRole is edge",
    ),
    "parameters not a mapping": (
        ('        parameter:\n          fps: 30\n          serial: "0042"\n', "        parameter: [fps]\n"),
        "cluster.yml:18: hosts[1].peripheralDevices[0].parameter: ['fps'] (list) is not valid; expected a mapping",
    ),
    "parameter value a list": (
        ("fps: 30", "fps: [30, 60]"),
        "cluster.yml:19: hosts[1].peripheralDevices[0].parameter.fps: [30, 60] (list) is not valid; expected a string, "
        "a number or true/false",
    ),
    "parameter without value": (
        ("fps: 30", "fps:"),
        "cluster.yml:19: hosts[1].peripheralDevices[0].parameter.fps: has no value",
    ),
    "parameter date": (
        ("fps: 30", "fps: 2024-01-01"),
        "cluster.yml:19: hosts[1].peripheralDevices[0].parameter.fps: datetime.date(2024, 1, 1) (date) is not valid",
    ),
    "parameter name a bool": (
        ("fps: 30", "yes: 30"),
        "cluster.yml:19: hosts[1].peripheralDevices[0].parameter.True: True (bool) is not a valid parameter name",
    ),
    "device twice": (
        ('          serial: "0042"\n', '          serial: "0042"\n      - deviceName: camera\n'),
        "cluster.yml:21: hosts[1].peripheralDevices[1].deviceName: 'camera' is already the device hosts[1].peripheralDevices[0]",
    ),
    "duplicate hostname": (
        ("  - hostname: tb-2", "  - hostname: tb-1"),
        "cluster.yml:21: hosts[2].hostname: 'tb-1' is already the hostname of hosts[1] (line 9); expected unique hostnames",
    ),
    "robot id a list": (
        ("robotId: 7", "robotId: [7]"),
        "cluster.yml:15: hosts[1].locatedInRobot.robotId: [7] (list) is not valid; expected a number or a name",
    ),
    "alias on two lines": (
        ("alias: turtle-one", 'alias: "turtle\\none"'),
        "cluster.yml:10: hosts[1].alias: 'turtle\\none' is not valid; expected another name of the machine (one line of text)",
    ),
    "wrong kind": (
        ("kind: ClusterInventory", "kind: Cluster"),
        "cluster.yml:2: kind: 'Cluster' is not valid; expected ClusterInventory",
    ),
    "fleet given as cluster inventory": (
        ("kind: ClusterInventory", "kind: Fleet"),
        "cluster.yml:2: kind: 'Fleet' is not valid (a Fleet file belongs in fleets); expected ClusterInventory",
    ),
    "other api version": (
        ("apiVersion: v1alpha", "apiVersion: v2"),
        "cluster.yml:1: apiVersion: 'v2' is not supported; expected v1alpha",
    ),
    "no cluster name": (("  clusterName: lab\n", "  name: lab\n"), "cluster.yml:4: metadata.name: unknown field"),
    "hosts not a list": (
        ("hosts:\n", "hosts: {}\nx:\n"),
        "cluster.yml:5: hosts: {} (dict) is not valid; expected a list of hosts",
    ),
}


@pytest.mark.parametrize(("change", "expected"), BAD.values(), ids=BAD.keys())
def test_bad_cluster_inventory(tmp_path, change, expected):
    old, new = change
    assert old in CLUSTER
    problems = problems_of(tmp_path, CLUSTER.replace(old, new, 1))
    assert any(p.startswith(expected) for p in problems), problems


def test_cluster_inventory_not_a_mapping(tmp_path):
    assert problems_of(tmp_path, "- hostname: a\n") == [
        "cluster.yml:1: [{'hostname': 'a'}] (list) is not valid; expected a ClusterInventory (a mapping with apiVersion, kind, "
        "metadata, hosts)"
    ]


def test_empty_and_unreadable_files(tmp_path):
    assert problems_of(tmp_path, "# nothing\n") == ["cluster.yml: no ClusterInventory found; the file is empty"]
    assert problems_of(tmp_path, CLUSTER + "---\n" + CLUSTER) == [
        "cluster.yml (document 2):31: a second document; expected one ClusterInventory per file"
    ]
    assert problems_of(tmp_path, "hosts: [\n")[0].startswith("cluster.yml:2: not valid YAML: ")
    with pytest.raises(SpecError, match=r"missing\.yml: cannot read the file: No such file or directory"):
        import_files(str(tmp_path / "missing.yml"), [])


BAD_FLEETS = {
    "robot not in the inventory": (
        ("  - name: tb-2", "  - name: tb-3"),
        "fleet.yml:9: robot[1].name: 'tb-3' is not a robot of the ClusterInventory cluster.yml (no host is locatedInRobot "
        "with that name); did you mean 'tb-2'?",
    ),
    "robot twice": (("  - name: tb-2", "  - name: tb-1"), "fleet.yml:9: robot[1].name: 'tb-1' is already robot[0] of this fleet"),
    "robot not a mapping": (("  - name: tb-2", "  - tb-2"), "fleet.yml:9: robot[1]: 'tb-2' is not valid; expected a robot"),
    "invalid fleet name": (
        ("name: lab-fleet", "name: Lab Fleet"),
        "fleet.yml:4: metadata.name: 'Lab Fleet' is not a valid fleet name",
    ),
    "no fleet name": (("  name: lab-fleet\n", ""), "fleet.yml:3: metadata: name is required"),
    "robots not a list": (
        ("robot:\n  - name: tb-1\n  - name: tb-2\n", "robot: tb-1\n"),
        "fleet.yml:7: robot: 'tb-1' is not valid",
    ),
    "wrong kind": (
        ("kind: Fleet", "kind: ClusterInventory"),
        "fleet.yml:2: kind: 'ClusterInventory' is not valid (a ClusterInventory file belongs in cluster_inventory)",
    ),
    "no kind": (("kind: Fleet\n", ""), "fleet.yml:1: kind is required; expected Fleet"),
    "no metadata": (
        ("metadata:\n  name: lab-fleet\n  description: The lab's turtles\n  mainCluster: lab\n", ""),
        "fleet.yml:1: metadata is required",
    ),
    "description a mapping": (
        ("description: The lab's turtles", "description: {a: b}"),
        "fleet.yml:5: metadata.description: {'a': 'b'} (dict)",
    ),
}


@pytest.mark.parametrize(("change", "expected"), BAD_FLEETS.values(), ids=BAD_FLEETS.keys())
def test_bad_fleet(tmp_path, change, expected):
    old, new = change
    assert old in FLEET
    problems = problems_of(tmp_path, fleets=(FLEET.replace(old, new, 1),))
    assert any(p.startswith(expected) for p in problems), problems


def test_robot_in_two_fleets_and_fleet_names_twice(tmp_path):
    other = FLEET.replace("lab-fleet", "other-fleet").replace("  - name: tb-2\n", "")
    assert problems_of(tmp_path, fleets=(FLEET, other)) == [
        "fleet-2.yml:8: robot[0].name: 'tb-1' is already in fleet lab-fleet (fleet.yml:8); expected each robot in one fleet"
    ]
    assert problems_of(tmp_path, fleets=(FLEET, FLEET.replace("  - name: tb-1\n  - name: tb-2\n", ""))) == [
        "fleet-2.yml:4: metadata.name: 'lab-fleet' is already the name of the fleet in fleet.yml:4; expected unique fleet names"
    ]


def test_every_problem_of_every_file_at_once(tmp_path):
    cluster = CLUSTER.replace("deviceName: camera", "deviceName: Camera").replace("kuberosRole: edge", "kuberosRole: edg")
    fleet = FLEET.replace("name: lab-fleet", "name: Lab")
    with pytest.raises(SpecError) as caught:
        import_texts(tmp_path, cluster, (fleet,))
    message = str(caught.value)
    assert message.startswith("cannot import the reference KubeROS site (3 problems):\n")
    assert "cluster.yml:17: hosts[1].peripheralDevices[0].deviceName" in message
    assert "cluster.yml:27: hosts[3].kuberosRole" in message
    assert "fleet.yml:4: metadata.name" in message


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({"default_cpu": {"onbaord": 2}}, "options: default_cpu.onbaord: unknown role; did you mean 'onboard'?"),
        ({"default_cpu": {"edge": "lots"}}, "options: default_cpu.edge: 'lots' is not valid; expected a CPU quantity"),
        ({"default_memory": {"edge": 0}}, "options: default_memory.edge: 0 (int) is not valid; expected more than zero"),
        ({"default_memory": "8Gi"}, "options: default_memory: '8Gi' is not valid; expected a mapping of kuberosRole to value"),
        ({"default_shared": "no"}, "options: default_shared: 'no' is not valid; expected true or false"),
        ({"default_fleet": "Spare"}, "options: default_fleet: 'Spare' is not a valid fleet name"),
    ],
)
def test_bad_options(tmp_path, options, expected):
    problems = problems_of(tmp_path, **options)
    assert any(p.startswith(expected) for p in problems), problems


HEAD = {"apiVersion": "v1alpha", "kind": "ClusterInventory"}


@pytest.mark.parametrize(
    "data",
    [None, 3, "text", [], {"kind": ["x"]}, {**HEAD, "metadata": [1]},
     {**HEAD, "metadata": {"clusterName": "c"}, "hosts": [None, 1, {"hostname": []}]},
     {**HEAD, "metadata": {"clusterName": ["c"]},
      "hosts": [{"hostname": "a", "kuberosRole": {"x": 1}, "locatedInRobot": "r", "peripheralDevices": {"a": 1}}]},
     {**HEAD, "metadata": {"clusterName": "c"},
      "hosts": [{"hostname": "a", "kuberosRole": "onboard", "locatedInRobot": {"name": 5, "robotId": 1.5},
                 "peripheralDevices": [None, {"deviceName": None}, {"deviceName": "x", "parameter": {(1, 2): 3}}]}]}],
)  # fmt: skip
def test_odd_input_is_a_problem_never_a_traceback(data):
    with pytest.raises(SpecError) as caught:
        import_site(data, [None, {"kind": "Fleet", "apiVersion": "v1alpha", "metadata": {"name": 1}, "robot": [[]]}])
    assert caught.value.problems
