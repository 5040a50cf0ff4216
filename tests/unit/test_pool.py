"""The robot pool (plugins/module_utils/kuberos/pool.py): reservations, what production deployments leave out, what
a development deployment may run on; placement with the pool."""

from __future__ import annotations

import datetime
import json

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


# -- every date and duration bounded; unreadable reservations ignored with a warning (issue 44) ------------------


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("100000000d", "more than 90 days"),
        ("1" * 400 + "d", "more than 90 days"),
        ("9999999999999h", "more than 90 days"),
        ("9999-12-31T23:59:59-12:00", "out of range"),
        ("10000-01-01T00:00:00Z", "is not a time"),
        ("x" * 10000, "is not a time"),
        ("4h\n", ""),
        ("4h\nx", "is not a time"),
        ("\u0664h", "is not a time"),  # ARABIC-INDIC DIGIT FOUR: a digit to \d and to float(), not to the pool
    ],
)
def test_a_hold_out_of_range_is_refused_with_the_bound_never_an_overflow(text, why):
    if not why:
        assert pool.parse_until(text, NOW) == NOW + datetime.timedelta(hours=4)
        return
    with pytest.raises(ValueError, match=why) as caught:
        pool.parse_until(text, NOW)
    assert len(str(caught.value)) < 300, "the text is cut, not repeated whole"


class PoolKube:
    """The reads and writes of the pool module's work: ConfigMaps, Namespaces, and the caller's identity."""

    def __init__(self, configmaps=(), identity="alice@example.com"):
        self.objects = {(c["metadata"]["namespace"], c["metadata"]["name"]): c for c in configmaps}
        self.identity, self.deleted = identity, []

    def get(self, kind, name, namespace=""):
        if kind == "Namespace":
            return {"metadata": {"name": name}}
        return self.objects.get((namespace, name)) if kind == "ConfigMap" else None

    def list(self, kind, namespace="", selector=""):
        if kind != "ConfigMap" or selector != f"{pool.LABEL}=true":
            return []
        return [c for (ns, _n), c in self.objects.items() if not namespace or ns == namespace]

    def apply(self, obj, manager=None):
        self.objects[(obj["metadata"].get("namespace", ""), obj["metadata"]["name"])] = obj
        return obj

    def delete(self, kind, name, namespace=""):
        self.deleted.append((namespace, name))
        return self.objects.pop((namespace, name), None) is not None

    def create(self, obj):
        assert obj["kind"] == "SelfSubjectReview", obj
        if self.identity is None:
            from kubernetes.client.exceptions import ApiException

            raise ApiException(status=404, reason="Not Found")
        return {**obj, "status": {"userInfo": {"username": self.identity, "groups": ["system:authenticated"]}}}


def _configmap(**data):
    base = {"robot": "fetch-2", "fleet": "test-fleet", "owner": "alice", "reason": "tests",
            "until": "2026-11-28T16:00:00Z", "since": "2026-11-28T10:00:00Z"}  # fmt: skip
    merged = {k: v for k, v in {**base, **data}.items() if v is not None}
    robot = merged.get("robot") if isinstance(merged.get("robot"), str) else "x"
    return {"metadata": {"name": f"kuberos-reservation-{robot}", "namespace": "kuberos-test-fleet",
                         "labels": {pool.LABEL: "true"}}, "data": merged}  # fmt: skip


BAD_RESERVATIONS = [
    (_configmap(robot="r1", until="9999-12-31T23:59:59-12:00"), "until: '9999-12-31T23:59:59-12:00' is out of range"),
    (_configmap(robot="r2", since="0001-01-01T00:00:00+01:00"), "since: '0001-01-01T00:00:00+01:00' is out of range"),
    (_configmap(robot="r3", until="tomorrow"), "until: 'tomorrow' is not a time"),
    (_configmap(robot="r4", owner=None), "has no owner"),
    (_configmap(robot="r5", owner="alice\n"), "owner: 'alice\\n' cannot be"),
    (_configmap(robot="r6", reason="\x1b[2J"), "reason: has control character U+001B (ESC)"),
    (_configmap(robot="r7", until=5), "until: is not text"),
    ({"metadata": {"name": "kuberos-reservation-r8", "namespace": "kuberos-test-fleet", "labels": {pool.LABEL: "true"}},
      "data": ["robot"]},
     "its data is not a mapping"),
]  # fmt: skip


def test_an_unreadable_reservation_is_ignored_with_a_warning_naming_it_and_why():
    good = _configmap()
    found, warnings = pool.read([good, *(c for c, _why in BAD_RESERVATIONS)])
    assert [r.robot for r in found] == ["fetch-2"]
    assert len(warnings) == len(BAD_RESERVATIONS), warnings
    for (configmap, why), warning in zip(BAD_RESERVATIONS, warnings, strict=True):
        name = configmap["metadata"]["name"]
        assert warning.startswith(f"reservation kuberos-test-fleet/{name} ignored (it holds nothing): "), warning
        assert why in warning, (why, warning)
    assert pool.readable([c for c, _why in BAD_RESERVATIONS]) == []


def test_an_owner_with_a_trailing_line_break_is_refused_and_the_reason_rule_is_said_as_it_is():
    assert "cannot be a RosDeployment's metadata.developer" in pool.owner_problem("alice\n")
    why = pool.reason_problem("line one\tline two")
    assert "control character U+0009" in why and "one printable line" in why and "only tab" not in why, why


def test_the_pool_module_refuses_a_huge_hold_naming_the_option_not_as_a_cluster_failure():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import robot_pool

    kube = PoolKube()
    for hold in ("100000000d", "9999-12-31T23:59:59-12:00"):
        with pytest.raises(KuberosError, match=r"^until \(playbooks/pool.yml: -e hold=\): ") as caught:
            robot_pool.reserve(kube, "test-fleet", "fetch-2", "alice", "", hold, check_mode=False)
        assert "at most 90 days" in str(caught.value) or "out of range" in str(caught.value), str(caught.value)
    assert not kube.objects


def test_every_reader_of_the_pool_skips_an_unreadable_reservation_and_says_so():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import robot_pool

    kube = PoolKube([_configmap(), *(c for c, _why in BAD_RESERVATIONS)])
    said = []
    found = robot_pool.reservations(kube, "test-fleet", warn=said.append)
    assert [r.robot for r in found] == ["fetch-2"] and len(said) == len(BAD_RESERVATIONS), said
    listed = robot_pool.listing(kube, NOW)
    assert [r["robot"] for r in listed["reservations"]] == ["fetch-2"] and len(listed["ignored"]) == len(BAD_RESERVATIONS)
    # an unreadable reservation holds nothing: reserving replaces it, releasing removes it
    done = robot_pool.reserve(kube, "test-fleet", "r1", "bob", "", "4h", check_mode=False)
    assert done["changed"] and done["before"] is None and done["after"].owner == "bob"
    done = robot_pool.release(kube, "test-fleet", "r3", "bob", force=False, check_mode=False)
    assert done["changed"] and ("kuberos-test-fleet", "kuberos-reservation-r3") in kube.deleted


def test_a_reservation_records_who_the_cluster_says_wrote_it_and_only_they_renew_or_release_it():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import robot_pool

    kube = PoolKube(identity="alice@example.com")
    done = robot_pool.reserve(kube, "test-fleet", "fetch-2", "alice", "tests", "4h", check_mode=False)
    assert done["identity"] == "alice@example.com" and done["after"].identity == "alice@example.com"
    written = kube.objects[("kuberos-test-fleet", "kuberos-reservation-fetch-2")]
    assert written["data"]["identity"] == "alice@example.com"
    assert "advisory" in done["ownership"] and "alice@example.com" in done["ownership"]
    kube.identity = "bob@example.com"  # bob says -e owner=alice
    with pytest.raises(robot_pool.PoolRefused, match=r"written by Kubernetes user alice@example\.com; you are bob@example\.com"):
        robot_pool.reserve(kube, "test-fleet", "fetch-2", "alice", "mine now", "8h", check_mode=False)
    with pytest.raises(robot_pool.PoolRefused, match=r"written by Kubernetes user alice@example\.com"):
        robot_pool.release(kube, "test-fleet", "fetch-2", "alice", force=False, check_mode=False)
    assert robot_pool.release(kube, "test-fleet", "fetch-2", "alice", force=True, check_mode=False)["changed"]
    kube.identity = None  # an API server that cannot say (before Kubernetes 1.28): the name alone, said so
    done = robot_pool.reserve(kube, "test-fleet", "fetch-2", "alice", "tests", "4h", check_mode=False)
    written = kube.objects[("kuberos-test-fleet", "kuberos-reservation-fetch-2")]
    assert done["identity"] == "" and "identity" not in written["data"]
    assert "cannot tell" in done["ownership"]


def test_the_deploy_and_the_rollout_leave_an_unreadable_reservation_out_and_say_so(monkeypatch):
    """What raised OverflowError in both (a reservation whose until is in year 10000 in UTC) holds nothing."""
    import types

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import deploy_pass, rollout_runner

    good = _configmap(until="2099-01-01T00:00:00Z")
    configmaps = [good, *(c for c, _why in BAD_RESERVATIONS)]
    work = deploy_pass.DeployPass({}, check_mode=False, diff_mode=False)
    work.cluster_read = True
    work.local = types.SimpleNamespace(live={("ConfigMap", c["metadata"]["namespace"], c["metadata"]["name"]): c
                                             for c in configmaps})  # fmt: skip
    assert list(work.reservations()) == ["fetch-2"]
    assert len(work.pool_warnings) == len(BAD_RESERVATIONS) and "until: '9999-12-31T23:59:59-12:00'" in work.pool_warnings[0]

    monkeypatch.setattr(rollout_runner, "Kube", lambda clients: PoolKube(configmaps))
    said = []
    assert list(rollout_runner._reserved({}, "test-fleet", said.append)) == ["fetch-2"]
    assert len(said) == len(BAD_RESERVATIONS)
    assert said[0].startswith("reservation kuberos-test-fleet/kuberos-reservation-r1 ignored"), said[0]


def _run_module(monkeypatch, capsys, kube, module=None, **args) -> dict:
    from ansible.module_utils.testing import patch_module_args

    from ansible_collections.kuberos.platform.plugins.modules import robot_pool

    module = module or robot_pool

    monkeypatch.setattr(module, "api_clients", lambda kubeconfig: {})
    monkeypatch.setattr(module, "Kube", lambda clients, manager: kube)
    monkeypatch.setattr(module, "require_packages", lambda m: None)
    monkeypatch.setattr(module.AnsibleModule, "warn", lambda self, text: print(json.dumps({"warned": text})))
    with patch_module_args({"kubeconfig": "/nowhere", **args}), pytest.raises(SystemExit):
        module.main()
    *warned, result = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    return {**json.loads(result), "warned": [json.loads(line)["warned"] for line in warned]}


def test_the_pool_module_lists_every_reservation_warns_of_the_unreadable_and_says_ownership_is_advisory(
    monkeypatch, capsys, local_raw
):
    kube = PoolKube([_configmap(until="2099-01-01T00:00:00Z", identity="alice@example.com"), BAD_RESERVATIONS[0][0]])
    from ansible_collections.kuberos.platform.plugins.modules import robot_pool_info

    listed = _run_module(monkeypatch, capsys, kube, robot_pool_info)
    said = "fetch-2 (test-fleet): alice until 2099-01-01T00:00:00Z [Kubernetes user alice@example.com]: tests"
    assert listed["message"] == said
    assert listed["warned"] == listed["ignored"] and "kuberos-reservation-r1 ignored" in listed["ignored"][0]
    assert "ownership is advisory" in listed["ownership"]
    refused = _run_module(monkeypatch, capsys, kube, robot="fetch-1", owner="alice", until="100000000d", inventory=local_raw)
    assert refused["failed"]
    assert refused["msg"].startswith("until (playbooks/pool.yml: -e hold=): '100000000d' is more than 90 days"), refused
    held = _run_module(monkeypatch, capsys, kube, robot="fetch-1", owner="alice", inventory=local_raw)
    assert held["changed"] and held["identity"] == "alice@example.com" and "advisory" in held["ownership"], held
