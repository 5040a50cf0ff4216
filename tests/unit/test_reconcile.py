"""The controller's pure core: sticky re-placement, deployment records and fault decisions."""

from __future__ import annotations

import copy

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    Memory,
    NodeView,
    PodView,
    Settings,
    decide,
    status_rows,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import build_records, pack_text, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.replacement import replace_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import controller_table

SPEC = "examples/pick-and-place.yml"


@pytest.fixture
def placed(local_raw, root):
    deployments, placement = load_and_place(f"{root}/{SPEC}", local_raw)
    return deployments, placement


@pytest.fixture
def record(placed, local_raw, root):
    deployments, placement = placed
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        text = handle.read()
    _revision, configmap = build_records(text, SPEC, deployments, placement, local_raw, RenderOptions(), "kuberos")
    return parse_record(configmap)


def nodes_of(placement) -> dict[str, str]:
    where = {i.name: i.node for i in placement.instances}
    where.update({s.name: s.node for servers in placement.discovery.values() for s in servers})
    return where


def nodes_by_namespace(placement) -> dict[tuple[str, str], str]:
    where = {(i.namespace, i.name): i.node for i in placement.instances}
    where.update({(s.namespace, s.name): s.node for servers in placement.discovery.values() for s in servers})
    return where


def healthy(record, **down) -> ClusterView:
    nodes = {n: NodeView(n, True) for n in record.inventory.nodes}
    for name, since in down.items():
        nodes[name.replace("_", "-")] = NodeView(name.replace("_", "-"), False, "Ready=Unknown (NodeStatusUnknown)", since)
    return ClusterView(nodes=nodes)


# -- replace_modules -----------------------------------------------------------------------------
def test_nothing_unavailable_moves_nothing(placed, local_inventory):
    deployments, placement = placed
    result = replace_modules(deployments, local_inventory, placement)
    assert result.moves == [] and result.stranded == []
    assert nodes_of(result.placement) == nodes_of(placement)


def test_only_the_instances_of_an_unavailable_node_move_and_never_onto_it(placed, local_inventory):
    deployments, placement = placed
    before = nodes_of(placement)
    result = replace_modules(deployments, local_inventory, placement, unavailable={"edge-1": "node edge-1 is NotReady"})
    after = nodes_of(result.placement)
    assert {m.instance for m in result.moves} == {i for i, n in before.items() if n == "edge-1"}
    assert "edge-1" not in after.values()
    assert all(after[i] == n for i, n in before.items() if n != "edge-1")
    assert all(m.why == "node edge-1 is NotReady" for m in result.moves)
    servers = result.placement.discovery["test-fleet"]
    assert len({s.node for s in servers}) == len(servers), "discovery servers stay on distinct nodes"
    moved = next(i for i in result.placement.instances if i.name == "pick-and-place-perception-fetch-1")
    assert moved.reason.startswith("moved from edge-1 (node edge-1 is NotReady)")


def test_onboard_modules_of_a_dead_robot_stay_and_are_stranded(placed, local_inventory):
    deployments, placement = placed
    result = replace_modules(deployments, local_inventory, placement, unavailable={"fetch-1": "node fetch-1 is NotReady"})
    assert result.moves == []
    (stranded,) = result.stranded
    assert stranded.instance == "pick-and-place-controller-fetch-1" and stranded.node == "fetch-1"
    assert "onboard modules stay with their robot" in stranded.why
    assert nodes_of(result.placement) == nodes_of(placement)


def test_no_room_anywhere_strands_instead_of_failing(placed, local_inventory):
    deployments, placement = placed
    full = {n: {"cpu": 10_000, "memory": "1Ti", "pods": 1000} for n in local_inventory.nodes}
    result = replace_modules(deployments, local_inventory, placement, full, unavailable={"edge-1": "down"})
    assert result.moves == []
    assert {s.instance for s in result.stranded} == {i for i, n in nodes_of(placement).items() if n == "edge-1"}
    assert all("no other feasible node" in s.why or "no other node" in s.why for s in result.stranded)


def test_held_instances_stay_but_nothing_new_lands_on_their_node(placed, local_inventory):
    deployments, placement = placed
    unavailable = {"edge-1": "waiting", "edge-2": "down"}
    held = {i for i, n in nodes_of(placement).items() if n == "edge-1"}
    result = replace_modules(deployments, local_inventory, placement, unavailable=unavailable, hold=held)
    after = nodes_of(result.placement)
    assert all(after[i] == "edge-1" for i in held)
    leaving = {m.instance for m in result.moves} | {s.instance for s in result.stranded}
    assert leaving == {i for i, n in nodes_of(placement).items() if n == "edge-2"}
    # perception needs <= 20 ms: with edge-1 held and edge-2 down the cloud (40 ms) cannot take it.
    assert {s.instance for s in result.stranded} == {"pick-and-place-perception-fetch-2"}
    assert all(m.to_node not in unavailable for m in result.moves)


def test_a_measured_latency_moves_a_module_with_max_latency(placed, local_inventory):
    deployments, placement = placed
    node = nodes_of(placement)["pick-and-place-perception-fetch-2"]
    measured = local_inventory.with_measured_latency({"fetch-2": {node: 45.0}})
    assert measured.latency_ms("fetch-2", node) == 45.0 and local_inventory.latency_ms("fetch-2", node) == 5.0
    result = replace_modules(deployments, measured, placement)
    (move,) = result.moves
    assert move.instance == "pick-and-place-perception-fetch-2" and move.from_node == node
    assert "latency 45 ms to fetch-2 > max_latency 20 ms" in move.why


@settings(max_examples=60, deadline=None)
@given(down=st.sets(st.sampled_from(["edge-1", "edge-2", "edge-3", "cloud-1", "cloud-2", "fetch-1", "fetch-2"])))
def test_any_set_of_dead_nodes_keeps_every_instance_exactly_once(down, local_raw, root):
    deployments, placement = load_and_place(f"{root}/examples/two-fleets.yml", local_raw)
    inventory = load_inventory(local_raw)
    result = replace_modules(deployments, inventory, placement, unavailable={n: "down" for n in down})
    before, after = nodes_by_namespace(placement), nodes_by_namespace(result.placement)
    servers = sum(len(s) for s in placement.discovery.values())
    assert sorted(before) == sorted(after) and len(after) == len(placement.instances) + servers, "none lost or duplicated"
    stranded = {(s.namespace, s.instance) for s in result.stranded}
    for instance, node in after.items():
        if before[instance] not in down:
            assert node == before[instance], "healthy instances never move"
        elif instance not in stranded:
            assert node not in down, "a moved instance never lands on a dead node"
    assert {(m.namespace, m.instance) for m in result.moves} | stranded == {i for i, n in before.items() if n in down}


# -- records -------------------------------------------------------------------------------------
def test_a_record_round_trips(record, placed, local_raw):
    _, placement = placed
    assert record.deployment == "pick-and-place" and record.namespace == "kuberos-test-fleet"
    assert record.inventory_raw == local_raw
    assert nodes_of(record.placement) == nodes_of(placement)
    assert record.field_manager == "kuberos"


@pytest.mark.parametrize(
    "damage, expected",
    [
        (lambda cm: cm["binaryData"].pop("spec.yaml.gz"), "spec.yaml.gz"),
        (lambda cm: cm["binaryData"].update({"spec.yaml.gz": "bm90IGd6aXA="}), "not a readable KubeROS record"),
        (lambda cm: cm["binaryData"].update({"placement.json.gz": "bm90IGd6aXA="}), "not a readable KubeROS record"),
        (lambda cm: cm["data"].update({"format": "9"}), "format '9'"),
        (lambda cm: cm["data"].update({"deployment": "other"}), "no RosDeployment named 'other'"),
        (lambda cm: cm["binaryData"].update({"spec.yaml.gz": pack_text("kind: [unclosed")}), "kuberos-record-pick-and-place"),
        (lambda cm: cm["data"].update({"format": "1"}), "KeyError('spec.yaml')"),
    ],
)
def test_a_damaged_record_names_itself_and_the_problem(placed, local_raw, root, damage, expected):
    deployments, placement = placed
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        text = handle.read()
    _revision, configmap = build_records(text, SPEC, deployments, placement, local_raw, RenderOptions(), "kuberos")
    configmap = copy.deepcopy(configmap)
    damage(configmap)
    with pytest.raises(SpecError) as raised:
        parse_record(configmap)
    message = str(raised.value)
    assert "ConfigMap kuberos-test-fleet/kuberos-record-pick-and-place" in message and expected in message


# -- decisions -----------------------------------------------------------------------------------
def test_a_node_fault_waits_for_the_grace_period_from_its_transition(record):
    memory = Memory()
    early = decide(record, healthy(record, edge_1=100.0), memory, Settings(grace_s=5), now=102.0)
    assert early.replacement is None and early.wake_at == 105.0 and early.waiting
    due = decide(record, healthy(record, edge_1=100.0), memory, Settings(grace_s=5), now=105.0)
    assert due.replacement is not None and due.replacement.moves


def test_a_blip_resets_the_grace_period(record):
    memory = Memory()
    decide(record, healthy(record, edge_1=None), memory, Settings(grace_s=5), now=100.0)
    decide(record, healthy(record), memory, Settings(grace_s=5), now=101.0)  # back before the grace ended
    again = decide(record, healthy(record, edge_1=None), memory, Settings(grace_s=5), now=104.0)
    assert again.replacement is None and again.wake_at == 109.0


def test_a_latency_fault_after_a_recent_move_cools_down_but_a_node_fault_does_not(record):
    memory = Memory()
    instance = "pick-and-place-perception-fetch-2"
    node = nodes_of(record.placement)[instance]
    memory.last_move[instance] = 100.0
    view = healthy(record)
    view.measured = {"fetch-2": {node: 45.0}}
    decide(record, view, memory, Settings(grace_s=1, cooldown_s=30), now=101.0)
    cooling = decide(record, view, memory, Settings(grace_s=1, cooldown_s=30), now=110.0)
    assert cooling.replacement is None and any("cooling down" in w for w in cooling.waiting)
    assert cooling.wake_at == 130.0
    cooled = decide(record, view, memory, Settings(grace_s=1, cooldown_s=30), now=130.0)
    assert [m.instance for m in cooled.replacement.moves] == [instance]
    assert cooled.replacement.moves[0].why.startswith(f"measured RTT 45 ms from fetch-2 to {node}")
    memory.last_move[instance] = 130.0
    down = decide(record, healthy(record, **{node.replace("-", "_"): 0.0}), memory, Settings(grace_s=1), now=131.0)
    assert instance in {m.instance for m in down.replacement.moves}, "node loss is never held back by the cooldown"


def test_a_failing_pod_moves_its_instance_and_the_node_is_avoided(record):
    memory = Memory()
    instance = "pick-and-place-motion-planner-fetch-1"
    node = nodes_of(record.placement)[instance]
    view = healthy(record)
    view.pods = {instance: [PodView("p-1", "ns", instance, node, "Running", False, 4, "CrashLoopBackOff")]}
    decide(record, view, memory, Settings(grace_s=2), now=100.0)
    moved = decide(record, view, memory, Settings(grace_s=2), now=102.0)
    (move,) = moved.replacement.moves
    assert move.instance == instance and "keeps failing" in move.why and move.to_node != node
    assert node in memory.avoid[instance]


def _record_of(text: str, local_raw, tmp_path):
    path = tmp_path / "spec.yml"
    path.write_text(text, encoding="utf-8")
    deployments, placement = load_and_place(str(path), local_raw)
    _revision, configmap = build_records(text, str(path), deployments, placement, local_raw, RenderOptions(), "kuberos")
    return parse_record(configmap)


def test_an_offline_robot_keeps_its_modules_where_they_are_while_a_dead_edge_server_loses_its(local_raw, root, tmp_path):
    """A robot's computer that drops off the network is not a failed server: nothing of it moves (not even a module
    that only prefers the robot and could run on the edge), restarts or lands elsewhere, however long it is away;
    an edge server down as long has its modules moved, and nothing moves onto the offline robot."""
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        text = handle.read().replace("  preference: [edge, cloud]", "  preference: [onboard, edge]", 1)
    record = _record_of(text, local_raw, tmp_path)
    where = nodes_of(record.placement)
    assert where["pick-and-place-perception-fetch-1"] == "fetch-1", "perception prefers the robot and fits there"
    on_robot = {i for i, n in where.items() if n == "fetch-1"}
    on_edge = {i for i, n in where.items() if n == "edge-1"}
    assert {"pick-and-place-perception-fetch-1", "pick-and-place-controller-fetch-1"} <= on_robot and on_edge
    memory = Memory()
    decision = decide(record, healthy(record, fetch_1=0.0), memory, Settings(grace_s=5), now=3600.0)
    assert decision.replacement is None and decision.waiting == [], "an hour offline moves nothing"
    assert set(decision.offline) == {"fetch-1"} and "NotReady" in decision.offline["fetch-1"]
    both = decide(record, healthy(record, fetch_1=0.0, edge_1=0.0), memory, Settings(grace_s=5), now=3600.0)
    moved = {m.instance for m in both.replacement.moves} | {s.instance for s in both.replacement.stranded}
    assert moved == on_edge and not on_robot & moved
    after = nodes_of(both.replacement.placement)
    assert all(after[i] == "fetch-1" for i in on_robot) and "fetch-1" not in {m.to_node for m in both.replacement.moves}
    rows = status_rows(record, healthy(record, fetch_1=0.0), {}, {})
    offline = [r for r in rows if r["node"] == "fetch-1"]
    assert offline and all(r["phase"] == "Offline" for r in offline)
    assert all(r["note"].startswith("robot offline since 1970-01-01T00:00:00Z: node fetch-1 is NotReady") for r in offline)
    assert all(r["phase"] != "Offline" for r in rows if r["node"] != "fetch-1")


def test_status_rows_and_table(record):
    instance = "pick-and-place-perception-fetch-1"
    node = nodes_of(record.placement)[instance]
    view = healthy(record)
    view.pods = {instance: [PodView("p-1", "ns", instance, node, "Running", True)]}
    history = {instance: {"at": "2026-11-22T00:00:00Z", "from": "edge-9", "to": node, "why": "node edge-9 is NotReady"}}
    rows = status_rows(record, view, {"pick-and-place-controller-fetch-2": "robot down"}, history)
    by = {(r["robot"], r["module"]): r for r in rows}
    assert by[("fetch-1", "perception")]["phase"] == "Running"
    assert by[("fetch-2", "controller")]["phase"] == "Stranded"
    assert by[("fetch-2", "perception")]["phase"] == "Missing"
    table = controller_table("pick-and-place", rows)
    assert "from edge-9: node edge-9 is NotReady" in table and "robot down" in table


def test_deploy_places_nothing_on_an_unavailable_node_and_says_why_when_that_leaves_no_room(local_raw, root):
    _, placement = load_and_place(f"{root}/{SPEC}", local_raw, unavailable={"edge-1": "node edge-1 is NotReady"})
    assert "edge-1" not in nodes_of(placement).values()
    with pytest.raises(Exception) as raised:
        load_and_place(f"{root}/{SPEC}", local_raw, unavailable={"fetch-1": "node fetch-1 is NotReady"})
    assert "fetch-1 (onboard): node fetch-1 is NotReady" in str(raised.value)


def test_a_deploy_while_a_robot_is_offline_keeps_what_runs_on_it(local_raw, root, tmp_path):
    """Deploy (and a rollout, which places the same way) with a robot offline: what already runs on it stays, also
    a module that only prefers the robot; nothing new lands on it, and the rest is placed as usual."""
    with open(f"{root}/{SPEC}", encoding="utf-8") as handle:
        text = handle.read().replace("  preference: [edge, cloud]", "  preference: [onboard, edge]", 1)
    path = tmp_path / "spec.yml"
    path.write_text(text, encoding="utf-8")
    _, running = load_and_place(str(path), local_raw)
    on_robot = {i for i, n in nodes_of(running).items() if n == "fetch-1"}
    assert {"pick-and-place-perception-fetch-1", "pick-and-place-controller-fetch-1"} <= on_robot
    offline = {"fetch-1": "node fetch-1 is NotReady (Ready=Unknown (NodeStatusUnknown))"}
    _, again = load_and_place(str(path), local_raw, unavailable=offline, previous=running)
    assert nodes_of(again) == nodes_of(running), "a redeploy with the robot offline moves nothing"
    edited = text.replace("  preference: [onboard, edge]", "  preference: [edge, cloud]", 1)
    path.write_text(edited, encoding="utf-8")
    _, moved = load_and_place(str(path), local_raw, unavailable=offline, previous=running)
    assert nodes_of(moved)["pick-and-place-perception-fetch-1"] != "fetch-1", "the developer asked for the move"
    assert nodes_of(moved)["pick-and-place-controller-fetch-1"] == "fetch-1"
