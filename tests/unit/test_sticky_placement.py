"""Sticky placement: a deploy keeps what runs where it runs, and a fleet's discovery servers are the fleet's."""

from __future__ import annotations

import dataclasses

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    discovery_from_deployments,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs

PNP = "examples/pick-and-place.yml"
LISTING1 = "examples/listing1.yml"


def _allocated(placement: Placement) -> dict:
    used: dict[str, dict] = {}
    for inst in placement.instances:
        entry = used.setdefault(inst.node, {"cpu": 0, "memory": 0, "gpu": 0, "pods": 0})
        entry["cpu"] += inst.cpu_millis
        entry["memory"] += inst.memory_bytes
        entry["gpu"] += inst.gpu
        entry["pods"] += 1
    return {node: {**e, "cpu": f"{e['cpu']}m"} for node, e in used.items()}


@pytest.fixture
def first(root, local_inventory):
    deployments = load_specs(f"{root}/{PNP}")
    return deployments, place_modules(deployments, local_inventory)


def _servers(placement):
    return [(s.name, s.node) for servers in placement.discovery.values() for s in servers]


def test_a_second_deployment_keeps_the_fleets_discovery_servers_where_they_run(root, local_inventory, first):
    _deps, placement = first
    second = load_specs(f"{root}/{LISTING1}")
    fresh = place_modules(second, local_inventory, _allocated(placement))
    assert _servers(fresh) != _servers(placement), "without what runs now the servers land elsewhere (the defect)"
    kept = place_modules(second, local_inventory, _allocated(placement), previous=Placement([], dict(placement.discovery)))
    assert _servers(kept) == _servers(placement)


def test_the_servers_read_back_from_their_live_deployments_are_the_placed_ones(first):
    deployments, placement = first
    objects = render_deployment(deployments, placement)
    assert discovery_from_deployments(objects) == placement.discovery


def test_deploying_the_same_spec_again_with_what_runs_changes_nothing(local_inventory, first):
    deployments, placement = first
    again = place_modules(deployments, local_inventory, previous=placement)
    assert again.to_dict() == placement.to_dict()


def test_what_runs_on_a_node_that_went_away_is_placed_again_and_only_that(local_inventory, first):
    deployments, placement = first
    node = next(i.node for i in placement.instances if i.tier == "edge")
    unavailable = {node: f"node {node} is NotReady"}
    again = place_modules(deployments, local_inventory, unavailable=unavailable, previous=placement)
    before = {i.name: i.node for i in placement.instances}
    after = {i.name: i.node for i in again.instances}
    moved = {name for name in before if before[name] != after[name]}
    assert moved == {name for name, n in before.items() if n == node}
    assert node not in after.values()


def test_a_changed_preference_moves_the_module_the_developer_moved(root, local_inventory, first):
    deployments, placement = first
    (dep,) = deployments
    modules = tuple(
        dataclasses.replace(m, tiers=("edge", "cloud", "onboard")) if m.name == "motion-planner" else m for m in dep.modules
    )
    changed = dataclasses.replace(dep, modules=modules)
    again = place_modules([changed], local_inventory, previous=placement)
    tiers = {i.name: i.tier for i in again.instances if i.module == "motion-planner"}
    assert set(tiers.values()) == {"edge"}
    others = {i.name: i.node for i in again.instances if i.module != "motion-planner"}
    assert others == {i.name: i.node for i in placement.instances if i.module != "motion-planner"}


def test_bigger_resources_that_still_fit_keep_the_node(local_inventory, first):
    deployments, placement = first
    (dep,) = deployments
    modules = tuple(
        dataclasses.replace(m, resources=dataclasses.replace(m.resources, cpu_millis=m.resources.cpu_millis + 100))
        for m in dep.modules
    )
    again = place_modules([dataclasses.replace(dep, modules=modules)], local_inventory, previous=placement)
    assert {i.name: i.node for i in again.instances} == {i.name: i.node for i in placement.instances}
    assert all(a.cpu_millis == b.cpu_millis + 100 for a, b in zip(again.instances, placement.instances, strict=True))


def test_a_new_robot_joins_a_shared_instance_with_room_and_the_others_stay(local_raw):
    raw = {**local_raw, "hosts": dict(local_raw["hosts"]), "groups": {k: list(v) for k, v in local_raw["groups"].items()}}
    inventory = load_inventory(raw)
    spec = {
        "metadata": {"name": "shared-demo", "targetFleet": "test-fleet", "robotSelector": {"robot": ["fetch-1"]}},
        "rosModules": [{"name": "coordinator", "image": "r/c:1", "launch": "c", "strategy": "shared", "robotsPerInstance": 2}],
    }
    (one,) = load_specs(spec)
    placed = place_modules([one], inventory)
    (two,) = load_specs({**spec, "metadata": {**spec["metadata"], "robotSelector": {"robot": ["fetch-1", "fetch-2"]}}})
    grown = place_modules([two], inventory, previous=placed)
    (inst,) = grown.instances
    assert inst.name == placed.instances[0].name and inst.node == placed.instances[0].node
    assert inst.robots == ("fetch-1", "fetch-2") and "shared by 2/2 robots" in inst.reason


def test_a_spec_cannot_move_the_fleets_discovery_servers_to_another_port(root, local_inventory, first):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError

    _deps, placement = first
    second = load_specs({**_listing1_data(root), "discovery": {"port": 11999}})
    with pytest.raises(SpecError) as raised:
        place_modules(second, local_inventory, previous=Placement([], dict(placement.discovery)))
    assert "discovery.port: 11999 differs from port 11811, which the discovery servers of fleet test-fleet run on" in str(
        raised.value
    )


def _listing1_data(root) -> dict:
    import yaml

    with open(f"{root}/{LISTING1}", encoding="utf-8") as handle:
        return yaml.safe_load(handle)
