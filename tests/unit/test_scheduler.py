"""Scheduler behaviour, as tables of small sites and specs with the placement expected."""

from __future__ import annotations

import dataclasses

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import PlacementError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement, robot_server_hosts
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import parse_rosdeployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import placement_table


def site(robots=2, edge=2, cloud=2, edge_cpu=8, cloud_cpu=16, cloud_gpu=1, fleet="f", **extra_hosts):
    hosts, groups = {}, {"robots": [], "edge": [], "cloud": []}
    for i in range(1, robots + 1):
        hosts[f"r{i}"] = {"kuberos_fleet": fleet, "kuberos_cpu": 2, "kuberos_memory": "4Gi", "kuberos_devices": ["camera"]}
        groups["robots"].append(f"r{i}")
    for i in range(1, edge + 1):
        hosts[f"e{i}"] = {"kuberos_cpu": edge_cpu, "kuberos_memory": "16Gi", "kuberos_latency_ms": 5}
        groups["edge"].append(f"e{i}")
    for i in range(1, cloud + 1):
        hosts[f"c{i}"] = {"kuberos_cpu": cloud_cpu, "kuberos_memory": "64Gi", "kuberos_gpu": cloud_gpu, "kuberos_latency_ms": 50}
        groups["cloud"].append(f"c{i}")
    for name, (group, host_vars) in extra_hosts.items():
        hosts[name] = host_vars
        groups[group].append(name)
    return {"hosts": hosts, "groups": groups}


def deployment(*modules, fleet="f", robots=None, name="app", servers=1):
    metadata = {"name": name, "targetFleet": fleet}
    if robots:
        metadata["robotSelector"] = {"robot": robots}
    mods = []
    for index, module in enumerate(modules):
        mods.append({"name": f"m{index}", "image": "img", "launch": ["ros2 run p n"], **module})
    return parse_rosdeployment({"metadata": metadata, "rosModules": mods, "discovery": {"servers": servers}}, "app.yml")


def where(placement: Placement) -> dict:
    return {(row["robot"], row["module"]): row["node"] for row in placement.rows()}


CASES = [
    # (id, site kwargs, module, expected {robot: node} for module m0)
    ("onboard-required-pins-to-own-robot", {}, {"requirements": {"onboard": True}}, {"r1": "r1", "r2": "r2"}),
    ("preference-cloud", {}, {"preference": "cloud"}, {"r1": "c1", "r2": "c2"}),
    # The discovery server takes a little of e1, so the first robot's module goes to e2.
    ("preference-edge-spreads", {}, {"preference": "edge", "resources": {"cpu": 2}}, {"r1": "e2", "r2": "e1"}),
    ("latency-excludes-cloud", {}, {"preference": "cloud", "requirements": {"max_latency": "20 ms"}}, {"r1": "e2", "r2": "e1"}),
    (
        "latency-excludes-everything-but-onboard",
        {},
        {"preference": "cloud", "requirements": {"max_latency": "1 ms"}},
        {"r1": "r1", "r2": "r2"},
    ),
    ("gpu-only-in-cloud", {}, {"preference": "edge", "resources": {"gpu": 1}}, {"r1": "c1", "r2": "c2"}),
    ("devices-only-onboard", {}, {"preference": "edge", "requirements": {"devices": ["camera"]}}, {"r1": "r1", "r2": "r2"}),
    ("explicit-list-order", {}, {"preference": ["cloud", "edge"]}, {"r1": "c1", "r2": "c2"}),
    ("no-cloud-falls-back-to-edge", {"cloud": 0}, {"preference": "cloud"}, {"r1": "e2", "r2": "e1"}),
    (
        "cpu-capacity-forces-fallback",
        {"edge": 1, "edge_cpu": 3},
        {"preference": "edge", "resources": {"cpu": 2}},
        {"r1": "e1", "r2": "c1"},
    ),
    (
        "arch-filters",
        {"arm": ("edge", {"kuberos_cpu": 64, "kuberos_memory": "64Gi", "kuberos_arch": "arm64"})},
        {"preference": "edge", "requirements": {"arch": "arm64"}},
        {"r1": "arm", "r2": "arm"},
    ),
]


@pytest.mark.parametrize(("site_kwargs", "module", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_placement_table(site_kwargs, module, expected):
    placement = place_modules([deployment(module)], load_inventory(site(**site_kwargs)))
    got = {robot: node for (robot, mod), node in where(placement).items() if mod == "m0"}
    assert got == expected


def test_capacity_is_accounted_across_modules_and_deployments():
    # Each edge node fits exactly two 3-CPU modules (8 CPUs, 100m taken by a discovery server on e1).
    inventory = load_inventory(site(robots=3, edge=2, cloud=1))
    first = deployment({"preference": ["edge", "cloud"], "resources": {"cpu": 3}}, name="one")
    second = deployment({"preference": ["edge", "cloud"], "resources": {"cpu": 3}}, name="two")
    placement = place_modules([first, second], inventory)
    per_node: dict[str, int] = {}
    for inst in placement.instances:
        per_node[inst.node] = per_node.get(inst.node, 0) + inst.cpu_millis
    for node, used in per_node.items():
        assert used + (100 if node == "e1" else 0) <= inventory.nodes[node].cpu_millis, (node, used)
    assert sorted(n for n in per_node if n.startswith("c")) == ["c1"]  # the overflow went to the cloud


def test_allocated_resources_are_respected():
    inventory = load_inventory(site(edge=1))
    spec = deployment({"preference": ["edge", "cloud"], "resources": {"cpu": 4}}, servers=1)
    free = place_modules([spec], inventory)
    assert where(free)[("r1", "m0")] == "e1"
    busy = place_modules([spec], inventory, allocated={"e1": {"cpu": "7", "memory": "1Gi"}})
    assert {where(busy)[("r1", "m0")], where(busy)[("r2", "m0")]} == {"c1", "c2"}


def test_same_inputs_same_placement():
    inventory = load_inventory(site(robots=6, edge=3, cloud=2))
    spec = deployment(
        {"preference": "edge", "resources": {"cpu": 1}},
        {"preference": "cloud", "requirements": {"max_latency": "100 ms"}},
        {"requirements": {"onboard": True}},
        {"strategy": "shared", "robotsPerInstance": 4},
    )
    assert place_modules([spec], inventory).to_dict() == place_modules([spec], inventory).to_dict()


def test_shared_packs_robots_up_to_the_limit():
    inventory = load_inventory(site(robots=5, edge=2, cloud=0))
    placement = place_modules([deployment({"strategy": "shared", "robotsPerInstance": 2, "preference": "edge"})], inventory)
    instances = [i for i in placement.instances if i.module == "m0"]
    assert [list(i.robots) for i in instances] == [["r1", "r2"], ["r3", "r4"], ["r5"]]
    assert all(i.shared for i in instances)
    rows = [r for r in placement.rows() if r["module"] == "m0"]
    assert len(rows) == 5  # one row per robot, each naming every robot its instance serves
    assert {tuple(r["robots"]) for r in rows} == {("r1", "r2"), ("r3", "r4"), ("r5",)}


def test_shared_instance_respects_latency_of_each_robot():
    raw = site(robots=3, edge=1, cloud=1)
    raw["hosts"]["r2"]["kuberos_link_latency_ms"] = {"e1": 80}
    placement = place_modules(
        [deployment({"strategy": "shared", "robotsPerInstance": 4, "requirements": {"max_latency": "60 ms"}})],
        load_inventory(raw),
    )
    instances = {i.node: list(i.robots) for i in placement.instances if i.module == "m0"}
    # r2 cannot join the instance on e1 (80 ms > 60 ms), so it gets one in the cloud (50 ms).
    assert instances == {"e1": ["r1", "r3"], "c1": ["r2"]}


def test_shared_instance_fails_when_a_robot_reaches_no_node():
    raw = site(robots=2, edge=1, cloud=0)
    raw["hosts"]["r2"]["kuberos_link_latency_ms"] = {"e1": 80}
    spec = deployment({"strategy": "shared", "requirements": {"max_latency": "50 ms"}})
    with pytest.raises(PlacementError, match=r"for robot r2 .*\n    e1 \(edge\): latency 80 ms to r2 > max_latency 50 ms"):
        place_modules([spec], load_inventory(raw))


def test_dedicated_gives_each_robot_its_own_instance():
    placement = place_modules([deployment({"preference": "edge"})], load_inventory(site(robots=3)))
    names = [i.name for i in placement.instances]
    assert len(names) == len(set(names)) == 3
    assert all(len(i.robots) == 1 for i in placement.instances)


def test_robot_selector_limits_robots():
    placement = place_modules([deployment({"preference": "edge"}, robots=["r2"])], load_inventory(site(robots=3)))
    assert {r["robot"] for r in placement.rows()} == {"r2"}


def test_edge_node_reserved_for_another_fleet_is_not_used():
    raw = site(edge=0, cloud=0, own=("edge", {"kuberos_cpu": 8, "kuberos_memory": "8Gi", "kuberos_fleets": ["g"]}))
    raw["hosts"]["g1"] = {"kuberos_fleet": "g", "kuberos_cpu": 1, "kuberos_memory": "1Gi"}
    raw["groups"]["robots"].append("g1")
    placement = place_modules([deployment({"preference": "edge"})], load_inventory(raw))
    assert {r["node"] for r in placement.rows()} == {"r1", "r2"}  # fell back onboard
    assert all("fallback to onboard" in r["reason"] for r in placement.rows())


def test_discovery_servers_on_distinct_edge_nodes_then_cloud():
    placement = place_modules([deployment({"preference": "edge"}, servers=3)], load_inventory(site(edge=2, cloud=2)))
    servers = placement.discovery["f"]
    assert [s.server_id for s in servers] == [0, 1, 2]
    assert len({s.node for s in servers}) == 3
    assert [s.tier for s in servers] == ["edge", "edge", "cloud"]


def test_discovery_servers_share_a_node_only_when_too_few():
    placement = place_modules(
        [deployment({"requirements": {"onboard": True}}, servers=3)], load_inventory(site(robots=1, edge=1, cloud=0))
    )
    nodes = [s.node for s in placement.discovery["f"]]
    assert sorted(nodes) == ["e1", "e1", "r1"] or len(set(nodes)) == 2
    assert any("shares it" in s.reason for s in placement.discovery["f"])


def test_every_placement_has_a_reason_and_the_table_shows_it():
    placement = place_modules([deployment({"preference": "cloud"}, {"requirements": {"onboard": True}})], load_inventory(site()))
    assert all(row["reason"] for row in placement.rows())
    table = placement_table(placement)
    assert "preferred tier cloud" in table and "onboard required" in table
    assert table.splitlines()[0].split() == ["DEPLOYMENT", "ROBOT", "MODULE", "TIER", "NODE", "REASON"]


def test_infeasible_module_explains_every_node():
    with pytest.raises(PlacementError) as caught:
        place_modules([deployment({"resources": {"gpu": 2}, "preference": "cloud"})], load_inventory(site()))
    message = str(caught.value)
    for node in ("c1", "c2", "e1", "e2", "r1"):
        assert f"{node} (" in message
    assert "gpu: needs 2, 1 free of 1" in message and "gpu: needs 2, node has none" in message
    assert "app.yml" in message and "rosModules[0]" in message


def test_unknown_fleet_and_robot_are_spec_errors():
    with pytest.raises(SpecError, match=r"'ff' is not a fleet in the inventory; did you mean 'f'\?"):
        place_modules([deployment({}, fleet="ff")], load_inventory(site()))
    with pytest.raises(SpecError, match=r"metadata.robotSelector.robot\[0\]: 'r9' is not a robot of fleet f"):
        place_modules([deployment({}, robots=["r9"])], load_inventory(site()))


def test_placement_round_trips_through_plain_data():
    placement = place_modules([deployment({"strategy": "shared"}, {"preference": "cloud"})], load_inventory(site()))
    data = placement.to_dict()
    assert Placement.from_dict(data).to_dict() == data
    for row in data["placements"]:
        assert {"robot", "module", "node", "tier", "reason", "robots", "instance"} <= set(row)
        assert row["tier"] in ("onboard", "edge", "cloud")


def test_names_that_clash_through_a_robots_name_are_refused_once_the_fleets_robots_are_known():
    """Module m0-x of robot r1 and module m0 of robot x-r1 would both name a Deployment app-m0-x-r1."""

    def spec(second: str):
        modules = [{"name": n, "image": "img", "launch": ["run"], "requirements": {"onboard": True}} for n in ("m0", second)]
        return parse_rosdeployment({"metadata": {"name": "app", "targetFleet": "f"}, "rosModules": modules}, "app.yml")

    inventory = load_inventory(
        site(robots=1, **{"x-r1": ("robots", {"kuberos_fleet": "f", "kuberos_cpu": 2, "kuberos_memory": "4Gi"})})
    )
    with pytest.raises(SpecError) as refused:
        place_modules([spec("m0-x")], inventory)
    assert "would name a Deployment app-m0-x-r1 (the instance of robot" in str(refused.value)
    assert place_modules([spec("m0-y")], inventory).rows(), "without the clash it places"


def test_a_robot_discovery_server_takes_room_on_each_robot_that_runs_an_onboard_module():
    """Each robot with an onboard instance holds its deployment's discovery server (100m, 64Mi), taken before the
    modules; robots whose modules all run elsewhere hold none; a robot with no room for it is refused, naming the
    field that goes without it."""
    inventory = load_inventory(site(robots=2))
    onboard = {"requirements": {"onboard": True}, "resources": {"cpu": 1}}
    placement = place_modules([deployment(onboard, {"preference": "edge"})], inventory)
    free = {n["name"]: n["free_cpu_millis"] for n in placement.nodes}
    assert free["r1"] == free["r2"] == 2000 - 1000 - 100
    hosts = robot_server_hosts({"app"}, placement.instances)
    assert hosts == {("app", "r1"): "r1", ("app", "r2"): "r2"}
    edge_only = place_modules([deployment({"preference": "edge"})], inventory)
    assert {n["name"]: n["free_cpu_millis"] for n in edge_only.nodes if n["tier"] == "onboard"} == {"r1": 2000, "r2": 2000}
    full = {"requirements": {"onboard": True}, "resources": {"cpu": 2}}  # the whole robot: no room for its server
    with pytest.raises(PlacementError) as refused:
        place_modules([deployment(full)], inventory)
    text = str(refused.value)
    assert "discovery server of deployment app on robot r1's computer" in text and "discovery.robotServers: false" in text
    assert "r1 (onboard): cpu: needs 0.1, 0 free of 2" in text, text
    without = deployment(full)
    without = dataclasses.replace(without, robot_servers=False)
    assert (
        robot_server_hosts({"app"} if without.uses_robot_servers else set(), place_modules([without], inventory).instances) == {}
    )


def test_a_robot_discovery_server_follows_an_onboard_fallback_and_is_rendered_for_it():
    """A module that prefers the edge but falls back onboard (no edge or cloud room) still gets its robot's server,
    with room taken after placing; its env lists the server after the fleet's."""
    inventory = load_inventory(site(robots=1, edge=1, cloud=0, edge_cpu=1))
    spec = deployment({"preference": ["edge", "onboard"], "resources": {"cpu": 1}})
    placement = place_modules([spec], inventory)
    assert where(placement) == {("r1", "m0"): "r1"}
    assert {n["name"]: n["free_cpu_millis"] for n in placement.nodes}["r1"] == 2000 - 1000 - 100
    objects = render_deployment([spec], placement)
    module = next(o for o in objects if o["metadata"]["name"] == "app-m0-r1")
    env = {e["name"]: e.get("value") for e in module["spec"]["template"]["spec"]["containers"][0]["env"]}
    assert env["ROS_DISCOVERY_SERVER"] == (
        "$(KUBEROS_DISCOVERY_0_SERVICE_HOST):11811;$(KUBEROS_ROBOT_DISCOVERY_APP_SERVICE_HOST):11811"
    )
    server = next(o for o in objects if o["metadata"]["name"] == "kuberos-robot-discovery-app-r1")
    container = server["spec"]["template"]["spec"]["containers"][0]
    assert container["args"][-4:] == ["-i", "1", "-p", "11811"]
    # it announces the node-local Service's address, which its robot's modules name
    assert {"name": "KUBEROS_DISCOVERY_ADDRESS", "value": "$(KUBEROS_ROBOT_DISCOVERY_APP_SERVICE_HOST)"} in container["env"]
    service = next(o for o in objects if o["kind"] == "Service" and o["metadata"]["name"] == "kuberos-robot-discovery-app")
    assert service["spec"]["internalTrafficPolicy"] == "Local"


@pytest.mark.parametrize("discovery", [{"robotServers": False}, "cyclonedds"])
def test_no_robot_discovery_servers_when_turned_off_or_for_cyclone_dds(discovery):
    inventory = load_inventory(site(robots=2))
    data = {
        "metadata": {"name": "app", "targetFleet": "f"},
        "rosModules": [{"name": "m0", "image": "img", "launch": ["ros2 run p n"], "requirements": {"onboard": True}}],
    }
    if discovery == "cyclonedds":
        data["rmw"] = "cyclonedds"
    else:
        data["discovery"] = discovery
    spec = parse_rosdeployment(data, "app.yml")
    placement = place_modules([spec], inventory)
    objects = render_deployment([spec], placement)
    assert not [o for o in objects if "robot-discovery" in o["metadata"]["name"]]
    # the module's default 100m only
    assert {n["name"]: n["free_cpu_millis"] for n in placement.nodes if n["tier"] == "onboard"} == {"r1": 1900, "r2": 1900}


def test_robot_servers_must_be_true_or_false():
    with pytest.raises(SpecError) as refused:
        parse_rosdeployment(
            {
                "metadata": {"name": "app", "targetFleet": "f"},
                "rosModules": [{"name": "m0", "image": "img", "launch": ["ros2 run p n"]}],
                "discovery": {"robotServers": "yes"},
            },
            "app.yml",
        )
    assert [(p.source, p.path) for p in refused.value.problems] == [("app.yml", "discovery.robotServers")]
    assert "true or false" in refused.value.problems[0].message
