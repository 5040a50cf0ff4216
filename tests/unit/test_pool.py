"""The robot pool (plugins/module_utils/kuberos/pool.py): reservations, what production deployments leave out, what
a development deployment may run on; placement with the pool."""

from __future__ import annotations

import datetime

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments

NOW = datetime.datetime(2026, 11, 28, 12, 0, tzinfo=datetime.UTC)
SPEC = """\
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata: {name: app, targetFleet: test-fleet}
rosModules:
- name: driver
  image: reg/driver:1
  launch: drive
  requirements: {onboard: true}
- name: planner
  image: reg/planner:1
  launch: plan
  preference: edge
"""
DEV = SPEC.replace("name: app, targetFleet: test-fleet", "name: app-dev, targetFleet: test-fleet, developer: alice,\n"
                   "  robotSelector: {robot: [fetch-2]}")  # fmt: skip


def _held(owner="alice", robot="fetch-2", hours=4):
    return {robot: pool.Reservation(robot, "test-fleet", owner, "grasp tests", NOW + datetime.timedelta(hours=hours), NOW)}


def test_until_is_a_duration_or_a_time_in_the_next_90_days():
    assert pool.parse_until("4h", NOW) == NOW + datetime.timedelta(hours=4)
    assert pool.parse_until("90m", NOW) == NOW + datetime.timedelta(minutes=90)
    assert pool.parse_until("2026-11-28T18:00:00Z", NOW).hour == 18
    for bad, why in (("yesterday", "is not a time"), ("2026-11-28T18:00:00", "no time zone"),
                     ("2026-11-27T18:00:00Z", "not in the future"), ("100d", "more than 90 days")):  # fmt: skip
        with pytest.raises(ValueError, match=why):
            pool.parse_until(bad, NOW)


def test_a_reservation_travels_as_a_configmap_and_ends_at_its_time():
    (reservation,) = _held().values()
    configmap = pool.reservation_configmap(reservation)
    assert configmap["metadata"]["name"] == "kuberos-reservation-fetch-2"
    assert configmap["metadata"]["namespace"] == "kuberos-test-fleet"
    assert configmap["metadata"]["labels"][pool.LABEL] == "true"
    assert pool.reservation_of(configmap) == reservation
    assert pool.reservation_of({"data": {"robot": "x"}}) is None, "unreadable: it holds nothing"
    assert reservation.active(NOW) and not reservation.active(NOW + datetime.timedelta(hours=4))
    assert pool.held([reservation], NOW + datetime.timedelta(hours=5)) == {}
    assert reservation.describe() == "reserved by alice until 2026-11-28T16:00:00Z (grasp tests)"


def test_production_deployments_leave_a_reserved_robot_out_and_nothing_else_moves(local_inventory):
    (dep,) = load_rosdeployments(SPEC, "app.yml")
    before = place_modules([dep], local_inventory, reserved={})
    during = place_modules([dep], local_inventory, reserved=_held(), previous=before)
    assert before.deployments[0]["robots"] == ["fetch-1", "fetch-2"]
    assert during.deployments[0]["robots"] == ["fetch-1"]
    assert during.deployments[0]["left_out"] == {"fetch-2": "reserved by alice until 2026-11-28T16:00:00Z (grasp tests)"}
    assert not [i for i in during.instances if "fetch-2" in i.robots], "nothing placed for the reserved robot"
    kept = {(i.name, i.node) for i in before.instances if "fetch-2" not in i.robots}
    assert {(i.name, i.node) for i in during.instances} == kept
    objects = {o["metadata"]["name"]: o for o in render_deployment([dep], before, RenderOptions())}
    after = {o["metadata"]["name"]: o for o in render_deployment([dep], during, RenderOptions())}
    gone = sorted(set(objects) - set(after))
    assert gone == ["app-driver-fetch-2", "app-planner-fetch-2", "kuberos-robot-discovery-app-fetch-2"], gone
    assert all(after[name] == objects[name] for name in after), "the other robots' objects and the fleet's servers as they were"
    back = place_modules([dep], local_inventory, reserved={}, previous=during)
    assert sorted(i.name for i in back.instances) == sorted(i.name for i in before.instances), "given back: it returns"


def test_the_pass_a_reservation_or_a_release_needs_is_read_from_the_placements(local_inventory):
    (dep,) = load_rosdeployments(SPEC, "app.yml")
    (dev,) = load_rosdeployments(DEV, "dev.yml")
    before = place_modules([dep], local_inventory, reserved={}).deployments
    during = place_modules([dep], local_inventory, reserved=_held()).deployments
    developing = place_modules([dev], local_inventory, reserved=_held()).deployments
    assert pool.passes(before, "fetch-2", reserving=True) == ["app"], "it runs there: its pass stops it"
    assert pool.passes(during, "fetch-2", reserving=True) == [], "already left out: nothing to stop"
    assert pool.passes(developing, "fetch-2", reserving=True) == [], "the developer's own deployment stays"
    assert pool.passes(during, "fetch-2", reserving=False) == ["app"], "left out for the reservation: it returns"
    assert pool.passes(before, "fetch-2", reserving=False) == [], "never left out: nothing to return"
    assert pool.passes(during, "fetch-1", reserving=False) == [] and pool.passes(during, "fetch-1", reserving=True) == ["app"]


def test_a_development_deployment_runs_only_on_robots_its_developer_holds(local_inventory):
    (dev,) = load_rosdeployments(DEV, "dev.yml")
    assert dev.developer == "alice" and dev.robots == ("fetch-2",)
    placed = place_modules([dev], local_inventory, reserved=_held())
    assert sorted(i.name for i in placed.instances) == ["app-dev-driver-fetch-2", "app-dev-planner-fetch-2"]
    assert "left_out" not in placed.deployments[0]
    objects = render_deployment([dev], placed, RenderOptions())
    driver = next(o for o in objects if o["metadata"]["name"] == "app-dev-driver-fetch-2")
    assert driver["metadata"]["annotations"]["kuberos.io/developer"] == "alice"
    for holding, why in (({}, "robot fetch-2 is not reserved"), (_held("bob"), "robot fetch-2 is reserved by bob until")):
        with pytest.raises(SpecError) as caught:
            place_modules([dev], local_inventory, reserved=holding)
        (problem,) = caught.value.problems
        assert str(problem).startswith("dev.yml:4: metadata.robotSelector.robot[0]: " + why), str(problem)
        assert "the development deployment of alice runs only on robots alice holds" in str(problem)
    assert place_modules([dev], local_inventory).instances, "a render without a cluster does not know the pool"


def test_a_development_deployment_names_its_robots():
    with pytest.raises(SpecError, match=r"metadata.developer: needs metadata.robotSelector.robot"):
        load_rosdeployments(SPEC.replace("targetFleet: test-fleet", "targetFleet: test-fleet, developer: alice"), "x.yml")
    with pytest.raises(SpecError, match=r"metadata.developer: .* does not match|expected the name the robots"):
        load_rosdeployments(DEV.replace("developer: alice", "developer: '-bad name'"), "x.yml")


@pytest.mark.parametrize(
    ("owner", "reason", "why"),
    [
        ("alice@example.com", "grasp tests: the new planner", ""),
        ("", "", "is empty"),
        ("Alice Smith", "", "cannot be a RosDeployment's metadata.developer"),
        ("a" * 64, "", "at most 63 characters"),
        ("alice", "line one\nline two", "control character U+000A"),
        ("alice", "\x1b[31mred", "control character U+001B (ESC)"),
        ("alice", "x" * 201, "has 201 characters; expected at most 200"),
    ],
)
def test_who_holds_a_robot_and_why_are_checked_before_anything_is_written(owner, reason, why):
    found = pool.owner_problem(owner) or pool.reason_problem(reason)
    assert (why in found) if why else found == "", found
