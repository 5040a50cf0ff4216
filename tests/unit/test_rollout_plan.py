"""The pure parts of a rollout: the plan (waves, canary, what is never touched), the gate and downtime, revisions."""

from __future__ import annotations

import dataclasses

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    build_records,
    fingerprint,
    next_revision,
    parse_record,
    parse_revision,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.rollout import (
    Downtime,
    PodState,
    behind_live,
    gate_verdict,
    plan_rollout,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs


def _fleet(robots: int) -> dict:
    robot = {"kuberos_fleet": "f", "kuberos_devices": ["gripper"], "kuberos_cpu": 4, "kuberos_memory": "8Gi"}
    hosts = {f"robot-{i:02d}": dict(robot) for i in range(robots)}
    hosts.update(
        {"edge-1": {"kuberos_cpu": 64, "kuberos_memory": "128Gi"}, "cloud-1": {"kuberos_cpu": 64, "kuberos_memory": "128Gi"}}
    )
    return {
        "hosts": hosts,
        "groups": {"robots": [h for h in hosts if h.startswith("robot")], "edge": ["edge-1"], "cloud": ["cloud-1"]},
    }


def _spec(planner="r/planner:1", control="r/control:1", coordinator="shared"):
    modules = [
        {"name": "planner", "image": planner, "launch": "plan", "preference": "cloud"},
        {"name": "control", "image": control, "launch": "ctl", "requirements": {"onboard": True, "devices": ["gripper"]}},
        {"name": "coordinator", "image": "r/coord:1", "launch": "co", "strategy": coordinator},
    ]
    if coordinator == "dedicated":
        modules[2].pop("strategy")
    return {"metadata": {"name": "app", "targetFleet": "f"}, "rosModules": modules}


def _render(spec, raw, previous=None):
    deployments = load_specs(spec)
    placement = place_modules(deployments, load_inventory(raw), previous=previous)
    return deployments, placement, render_deployment(deployments, placement)


@pytest.mark.parametrize(
    ("robots", "canary", "wave_size", "expected"),
    [
        (25, 1, 10, [1, 10, 10, 4]),
        (25, 3, 10, [3, 10, 10, 2]),
        (4, 1, 10, [1, 3]),
        (4, 0, 2, [2, 2]),
        (1, 1, 10, [1]),
    ],
)
def test_waves_canary_first_then_wave_size_robots(robots, canary, wave_size, expected):
    raw = _fleet(robots)
    _d, placement, before = _render(_spec(coordinator="dedicated"), raw)
    _d, _p, after = _render(_spec(planner="r/planner:2", coordinator="dedicated"), raw, placement)
    order = sorted(h for h in raw["hosts"] if h.startswith("robot"))
    plan = plan_rollout(before, after, order, canary, wave_size)
    assert [len(w.robots) for w in plan.waves] == expected
    assert plan.waves[0].canary == (canary > 0) and not any(w.canary for w in plan.waves[1:])
    assert [r for w in plan.waves for r in w.robots] == order, "every robot once, in the fleet's order"
    assert all(c.module == "planner" and c.action == "update" for w in plan.waves for c in w.changes)
    assert plan.prepare == [] and plan.removals == [] and plan.untouched == ()
    assert (
        "version" not in plan.waves[0].changes[0].summary
        and "image r/planner:1 -> r/planner:2" in plan.waves[0].changes[0].summary
    )


def test_robots_without_a_change_are_in_no_wave_and_named_canaries_go_first():
    raw = _fleet(6)
    _d, placement, before = _render(_spec(coordinator="dedicated"), raw)
    spec = _spec(planner="r/planner:2", coordinator="dedicated")
    spec["metadata"]["robotSelector"] = {"robot": ["robot-02", "robot-04", "robot-05"]}
    # Robots outside the selector lose their modules (removals); the selected ones change.
    _d, _p, after = _render(spec, raw, placement)
    plan = plan_rollout(
        before, after, sorted(h for h in raw["hosts"] if h.startswith("robot")), canary_robots=("robot-05",), wave_size=1
    )
    assert [w.robots for w in plan.waves] == [("robot-05",), ("robot-02",), ("robot-04",)]
    assert {c.robot for c in plan.removals} == {"robot-00", "robot-01", "robot-03"}


def test_nothing_to_change_is_an_empty_plan():
    raw = _fleet(3)
    _d, placement, before = _render(_spec(), raw)
    _d, _p, after = _render(_spec(), raw, placement)
    plan = plan_rollout(before, after, ["robot-00", "robot-01", "robot-02"])
    assert not plan.changed and plan.untouched == ("robot-00", "robot-01", "robot-02")


def test_a_shared_instance_goes_with_the_first_of_its_robots_reached():
    raw = _fleet(6)
    _d, placement, before = _render(_spec(), raw)
    spec = _spec()
    spec["rosModules"][2]["image"] = "r/coord:2"
    _d, _p, after = _render(spec, raw, placement)
    plan = plan_rollout(before, after, sorted(h for h in raw["hosts"] if h.startswith("robot")), canary=1, wave_size=10)
    canary = plan.waves[0]
    assert canary.canary and canary.robots == ("robot-00", "robot-01", "robot-02", "robot-03")  # robotsPerInstance 4
    assert [c.name for c in canary.changes] == ["app-coordinator-shared-0"]
    assert plan.waves[1].robots == ("robot-04", "robot-05")


def test_an_offline_robot_is_left_pending_and_the_next_run_finishes_it():
    """A robot that is offline is in no wave: its changes are pending (shown per robot), the others roll out; once
    the record says the new state, the robot's modules still run the old image (live), and a plan against the same
    new state, with the robot back, has it in a wave."""
    raw = _fleet(4)
    _d, placement, before = _render(_spec(coordinator="dedicated"), raw)
    _d, _p, after = _render(_spec(planner="r/planner:2", control="r/control:2", coordinator="dedicated"), raw, placement)
    order = [f"robot-0{i}" for i in range(4)]
    plan = plan_rollout(before, after, order, canary=1, wave_size=10, offline={"robot-00"})
    assert [w.robots for w in plan.waves] == [("robot-01",), ("robot-02", "robot-03")], "the canary is an online robot"
    assert plan.pending_robots == ("robot-00",) and {c.module for c in plan.pending} == {"planner", "control"}
    assert plan.changed and "robot-00" not in plan.untouched
    assert all("pending, the robot is offline" in line for line in plan.per_robot()["robot-00"])
    assert plan.to_dict()["pending_robots"] == ["robot-00"]
    # The rollout done for the others: the record renders the new state; robot-00 still runs the old images.
    live = [o for o in before if o["kind"] == "Deployment" and "robot-00" in o["metadata"]["name"]]
    assert live
    seen = behind_live(after, live)
    still = plan_rollout(seen, after, order, canary=1, wave_size=10)
    assert [w.robots for w in still.waves] == [("robot-00",)], "the next run finishes the robot, as its canary"
    assert {c.module for c in still.waves[0].changes} == {"planner", "control"}
    assert not plan_rollout(behind_live(after, live), after, order, offline={"robot-00"}).waves, "still away: pending"
    caught_up = [o for o in after if o["kind"] == "Deployment" and "robot-00" in o["metadata"]["name"]]
    assert not plan_rollout(behind_live(after, caught_up), after, order).changed, "nothing behind: nothing to do"


def test_a_pending_robot_behind_on_its_environment_alone_is_finished_by_the_next_run():
    """A change of a module's environment only (no new image or version), left pending on robot-00: the live
    Deployment still has the old environment, so the next plan has robot-00 in a wave; once caught up, nothing."""
    raw = _fleet(2)
    _d, placement, before = _render(_spec(coordinator="dedicated"), raw)
    spec = _spec(coordinator="dedicated")
    spec["rosModules"][1]["env"] = {"GRIP_FORCE": "40"}
    _d, _p, after = _render(spec, raw, placement)
    order = ["robot-00", "robot-01"]
    live = [o for o in before if o["kind"] == "Deployment" and "robot-00" in o["metadata"]["name"]]
    still = plan_rollout(behind_live(after, live), after, order)
    assert [w.robots for w in still.waves] == [("robot-00",)] and {c.module for c in still.waves[0].changes} == {"control"}
    caught_up = [o for o in after if o["kind"] == "Deployment" and "robot-00" in o["metadata"]["name"]]
    assert not plan_rollout(behind_live(after, caught_up), after, order).changed


def test_the_fleets_discovery_servers_can_be_left_out():
    raw = _fleet(2)
    deps, placement, before = _render(_spec(), raw)
    after = render_deployment(deps, placement, RenderOptions(discovery_image="other:1"))
    assert plan_rollout(before, after, ["robot-00", "robot-01"]).prepare
    plan = plan_rollout(before, after, ["robot-00", "robot-01"], skip=lambda o: "discovery" in o["metadata"]["name"])
    assert not plan.changed


@pytest.mark.parametrize(("canary", "wave_size"), [(-1, 10), (1, 0)])
def test_bad_wave_settings_are_refused(canary, wave_size):
    with pytest.raises(ValueError, match="canary must be 0 or more and wave_size 1 or more"):
        plan_rollout([], [], [], canary, wave_size)


def _pod(name, node="n1", phase="Running", ready=True, restarts=0, waiting="", image="img:2", deleting=False):
    return PodState(name, node, phase, ready, restarts, waiting, deleting, image)


@pytest.mark.parametrize(
    ("pods", "failures", "pending"),
    [
        ([_pod("a")], [], []),
        ([_pod("a", image="img:1"), _pod("b", ready=False, phase="Pending")], [], ["i"]),  # surge: both for a while
        ([_pod("a", image="img:1", deleting=True), _pod("b")], [], []),
        ([_pod("a", node="n2")], [], ["i"]),  # not yet on its placed node
        ([_pod("a", ready=False, restarts=3, waiting="CrashLoopBackOff")], ["i: pod a is in CrashLoopBackOff (3 restarts)"], []),
        ([_pod("a", ready=False, waiting="ImagePullBackOff")], ["i: pod a is in ImagePullBackOff (0 restarts)"], []),
        ([_pod("a", phase="Failed", ready=False)], ["i: pod a failed"], []),
        ([_pod("a", image="img:1", restarts=9)], [], ["i"]),  # the old pod's restarts are not the new version's
        ([], [], ["i"]),
    ],
)
def test_the_gate(pods, failures, pending):
    assert gate_verdict({"i": pods}, {"i": ("n1", "img:2")}) == (failures, pending)


def test_downtime_counts_only_the_time_without_a_ready_pod():
    downtime = Downtime()
    for now, ready in [(0.0, True), (1.0, False), (1.5, False), (2.25, True), (3.0, True), (4.0, False)]:
        downtime.observe("i", ready, now)
    downtime.observe("j", True, 0.0)
    assert downtime.finish(4.5) == {"i": 1.75, "j": 0.0}


def test_revisions_count_what_a_deployment_asks_for_not_where_it_runs(root, local_raw, local_inventory):
    (dep,) = load_specs(f"{root}/examples/pick-and-place.yml")
    assert next_revision(dep, None) == 1
    assert next_revision(dep, {"revision": 4, "hash": fingerprint(dep)}) == 4
    assert next_revision(dep, {"revision": 4, "hash": "other"}) == 5
    moved = dataclasses.replace(dep, source="elsewhere.yml", lines={})
    assert fingerprint(moved) == fingerprint(dep)


def test_a_catalog_deployment_records_and_revisions_read_back_alone(root, local_raw, local_inventory):
    catalog = load_catalog(f"{root}/inventories/local/catalog")
    path = f"{root}/examples/pick-and-place-catalog.yml"
    deployments = load_specs(path, catalog=catalog)
    placement = place_modules(deployments, local_inventory)
    used = catalog.subset((m.catalog_module, m.version) for d in deployments for m in d.modules if m.version)
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    revision, record = build_records(text, path, deployments, placement, local_raw, RenderOptions(), "kuberos", {}, used)
    assert revision["metadata"]["name"] == "kuberos-rev-pick-and-place-1" and record["data"]["revision"] == "1"
    parsed = parse_record(record)
    assert parsed.revision == 1 and {m.version for m in parsed.spec.modules} == {"0.1.0"}
    number, cause, dep, spec_text, kept = parse_revision(revision)
    assert (number, cause) == (1, "deploy") and dep.modules == deployments[0].modules
    # the deployment's own document, its lines where they are in the file
    assert text.endswith(spec_text.lstrip("\n")) and spec_text.count("\n") == text.count("\n")
    assert kept == used


def test_the_gate_ignores_the_past_of_pods_from_before_the_wave():
    old = _pod("a", image="img:2", restarts=4, waiting="CrashLoopBackOff", ready=False)
    assert gate_verdict({"i": [old]}, {"i": ("n1", "img:2")}) == (["i: pod a is in CrashLoopBackOff (4 restarts)"], [])
    assert gate_verdict({"i": [old]}, {"i": ("n1", "img:2")}, {"a"}) == ([], ["i"])
    assert gate_verdict({"i": [_pod("a", restarts=4)]}, {"i": ("n1", "img:2")}, {"a"}) == ([], [])


def test_prestage_lists_each_robots_new_onboard_images_with_their_pull_secrets_and_nothing_else():
    """A new control image (onboard) is pre-pulled onto each robot in a wave, with the pull secret its pods use; a
    new planner image (cloud) is not, nor an offline robot's (pending), nor an image whose policy is Never."""
    raw = _fleet(3)
    _d, placement, before = _render(_spec(coordinator="dedicated"), raw)
    spec = _spec(planner="r/planner:2", control="reg.example/r/control:2", coordinator="dedicated")
    spec["imageRegistries"] = [{"name": "default", "pullSecret": "robots-pull"}]
    _d, _p, after = _render(spec, raw, placement)
    robots = ["robot-00", "robot-01", "robot-02"]
    plan = plan_rollout(before, after, robots, offline={"robot-02"})
    assert plan.pending_robots == ("robot-02",)
    assert plan.prestage() == {
        robot: {"images": [("reg.example/r/control:2", "IfNotPresent")], "pull_secrets": ["robots-pull"]}
        for robot in ("robot-00", "robot-01")
    }
    spec["imageRegistries"] = [{"name": "default", "pullSecret": "robots-pull", "pullPolicy": "Never"}]
    _d, _p, never = _render(spec, raw, placement)
    assert plan_rollout(before, never, robots).prestage() == {}
    _d, _p, planner_only = _render(_spec(planner="r/planner:2", coordinator="dedicated"), raw, placement)
    assert plan_rollout(before, planner_only, robots).prestage() == {}
