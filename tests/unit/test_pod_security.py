"""Restricted by default (kuberos/pod_security.py): every rendered pod of every example passes the restricted Pod
Security level as this reading of the standard sees it, modules that ask for root or privileges are admitted only
where they must be, the fleet namespaces enforce what their pods allow, and a hostile spec cannot smuggle a
privilege in. The cluster tests hold the API server's own admission to the same verdicts (tests/cluster)."""

from __future__ import annotations

import pytest
from admission import BATCH_EXAMPLES, DECLARED, EXAMPLES, render_batch_example, render_example

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import parse_rosdeployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import controller_objects


def test_every_example_is_checked():
    assert len(EXAMPLES) >= 5 and BATCH_EXAMPLES, EXAMPLES


def pods(objects: list[dict]) -> list[tuple[dict, dict]]:
    return [(o, spec) for o in objects if (spec := pod_security.pod_spec_of(o)) is not None]


@pytest.mark.parametrize("path", EXAMPLES)
def test_every_pod_of_every_example_passes_restricted_and_its_namespace_enforces_it(path):
    objects = render_example(path)
    found = pods(objects)
    assert found, f"{path} rendered no pod"
    levels = []
    for obj, spec in found:
        name = f"{obj['kind']}/{obj['metadata']['name']}"
        levels.append(pod_security.level(spec)[0])
        assert levels[-1] == DECLARED.get((path, name), "restricted"), name  # restricted, or the level it declares
    namespaces = [o for o in objects if o["kind"] == "Namespace"]
    assert namespaces
    for namespace in namespaces:
        assert namespace["metadata"]["labels"][pod_security.ENFORCE] == pod_security.loosest(levels)
        assert namespace["metadata"]["labels"][pod_security.WARN] == "restricted"


@pytest.mark.parametrize("path", BATCH_EXAMPLES)
def test_the_batch_examples_run_restricted(path):
    found = pods(render_batch_example(path))
    assert found
    for obj, spec in found:
        assert pod_security.level(spec) == ("restricted", []), obj["metadata"]["name"]


def test_the_controller_runs_restricted():
    objects = controller_objects("kuberos-system", "kuberos.local/controller:1", ["picking"], [], tls_secret="tls")
    [(_, spec)] = pods(objects)
    assert pod_security.level(spec) == ("restricted", [])
    namespace = next(o for o in objects if o["kind"] == "Namespace" and o["metadata"]["name"] == "kuberos-system")
    assert namespace["metadata"]["labels"][pod_security.ENFORCE] == "restricted"


def deployment(**fields) -> dict:
    return {
        "metadata": {"name": "app", "targetFleet": "test-fleet"},
        "rosModules": [
            {"name": "plain", "image": "ros:jazzy-ros-base", "launch": "ros2 run demo_nodes_cpp talker"},
            {"name": "special", "image": "ros:jazzy-ros-base", "launch": "ros2 run demo_nodes_cpp listener", **fields},
        ],
    }


@pytest.mark.parametrize(
    "fields, level, why",
    [
        ({"user": 0}, "baseline", "container special: runAsNonRoot not true"),
        ({"privileged": True}, "privileged", "container special: privileged"),
        ({"privileged": True, "user": 1000}, "privileged", "container special: privileged"),
        ({"user": 4242}, "restricted", ""),
    ],
)
def test_a_module_that_asks_for_more_gets_only_what_it_asks_and_its_namespace_says_so(fields, level, why, local_inventory):
    dep = parse_rosdeployment(deployment(**fields))
    objects = render_deployment([dep], place_modules([dep], local_inventory), RenderOptions())
    levels = {o["metadata"]["name"]: pod_security.level(s) for o, s in pods(objects)}
    special = [found for name, found in levels.items() if "-special-" in name]
    plain = [found for name, found in levels.items() if "-plain-" in name or "discovery" in name]
    assert special and all(found[0] == level for found in special)
    assert why == "" or all(why in found[1] for found in special)
    assert plain and all(found == ("restricted", []) for found in plain), "the other pods stay restricted"
    [namespace] = [o for o in objects if o["kind"] == "Namespace"]
    assert namespace["metadata"]["labels"][pod_security.ENFORCE] == level
    if level == "restricted":
        assert not dep.notes
        user = fields["user"]
        context = next(
            c["securityContext"] for o, s in pods(objects) if "-special-" in o["metadata"]["name"] for c in s["containers"]
        )
        assert (context["runAsUser"], context["runAsGroup"]) == (user, user)
    else:
        assert [note for note in dep.notes if note.startswith("module special:")] and level in " ".join(dep.notes), dep.notes


def test_non_root_modules_have_somewhere_to_log(local_inventory):
    dep = parse_rosdeployment(deployment(env={"ROS_LOG_DIR": "/var/log/ros"}))
    objects = render_deployment([dep], place_modules([dep], local_inventory), RenderOptions())
    env = {
        o["metadata"]["name"]: {e["name"]: e.get("value") for e in s["containers"][0]["env"]}
        for o, s in pods(objects)
        if "discovery" not in o["metadata"]["name"]
    }
    assert {name: vars_.get("ROS_HOME") for name, vars_ in env.items()} == {
        name: (None if "-special-" in name else pod_security.ROS_HOME) for name in env
    }, "the module that chose where to log keeps its choice"


@pytest.mark.parametrize(
    "fields, expected",
    [
        ({"securityContext": {"privileged": True}}, "securityContext"),
        ({"hostNetwork": True}, "hostNetwork"),
        ({"volumes": [{"name": "root", "hostPath": {"path": "/"}}]}, "volumes"),
        ({"privileged": "yes"}, "privileged"),
        ({"user": -1}, "user"),
        ({"user": "root"}, "user"),
        ({"user": True}, "user"),
        ({"user": 2**31}, "user"),
        ({"requirements": {"privileged": True}}, "requirements"),
    ],
)
def test_a_hostile_spec_cannot_smuggle_a_privilege_in(fields, expected):
    with pytest.raises(SpecError) as error:
        parse_rosdeployment(deployment(**fields), "hostile.yml")
    assert "hostile.yml" in str(error.value) and expected in str(error.value)


@pytest.mark.parametrize(
    "field, value",
    [
        ("env", {"LD_PRELOAD": "/host/evil.so", "SECURITY": "privileged: true"}),
        ("launch", "ros2 run x y --ros-args -p securityContext:=privileged hostNetwork:=true"),
        ("parameterFiles", [{"map": "files", "mountPath": "/proc"}]),
        ("workspace", "/host"),
    ],
)
def test_privileges_written_into_free_text_fields_stay_text(field, value, local_inventory):
    """Fields whose value is the module's own business (environment, launch lines, mount paths of its parameter
    files, its workspace) carry no privilege: the pods stay restricted whatever they say."""
    spec = deployment(**{field: value})
    if field == "parameterFiles":
        spec["parameterMaps"] = [{"name": "files", "type": "yaml", "data": {"a.yaml": "{}"}}]
    try:
        dep = parse_rosdeployment(spec, "hostile.yml")
    except SpecError as exc:  # refused is fine too, as long as it says where
        assert "hostile.yml" in str(exc)
        return
    objects = render_deployment([dep], place_modules([dep], local_inventory), RenderOptions())
    for obj, spec_ in pods(objects):
        assert pod_security.level(spec_) == ("restricted", []), obj["metadata"]["name"]


RESTRICTED = {
    "securityContext": {"seccompProfile": {"type": "RuntimeDefault"}, "runAsNonRoot": True},
    "containers": [{"name": "c", "securityContext": {"allowPrivilegeEscalation": False, "capabilities": {"drop": ["ALL"]}}}],
}


@pytest.mark.parametrize(
    "spec, level, why",
    [
        *[({**RESTRICTED, **extra}, level, why) for extra, level, why in [
            ({}, "restricted", ""),
            ({"volumes": [{"name": "n", "nfs": {"server": "s", "path": "/"}}]}, "baseline", "volume n: nfs"),
        ]],
        ({"hostNetwork": True, "containers": []}, "privileged", "hostNetwork: true"),
        ({"volumes": [{"name": "h", "hostPath": {"path": "/dev"}}], "containers": []}, "privileged", "volume h: hostPath"),
        ({"containers": [{"name": "c", "securityContext": {"capabilities": {"add": ["SYS_ADMIN"]}}}]}, "privileged",
         "container c: adds capabilities SYS_ADMIN"),
        ({"containers": [{"name": "c", "ports": [{"containerPort": 80, "hostPort": 80}]}]}, "privileged",
         "container c: hostPort"),
        ({"containers": [{"name": "c"}]}, "baseline", "container c: allowPrivilegeEscalation not false"),
    ],
)  # fmt: skip
def test_the_levels_are_read_as_the_standard_writes_them(spec, level, why):
    found, reasons = pod_security.level(spec)
    assert found == level and (why in reasons if why else reasons == [])


def test_a_namespace_enforces_the_loosest_level_its_pods_need():
    assert pod_security.loosest([]) == "restricted"
    assert pod_security.loosest(["restricted", "baseline", "restricted"]) == "baseline"
    assert pod_security.loosest(["baseline", "privileged"]) == "privileged"
    with pytest.raises(ValueError):
        pod_security.namespace_labels("lenient")


def _namespace(level: str) -> dict:
    return {"apiVersion": "v1", "kind": "Namespace",
            "metadata": {"name": "kuberos-f", "labels": pod_security.namespace_labels(level)}}  # fmt: skip


def _deployment(name: str, context: dict) -> dict:
    return {"kind": "Deployment", "metadata": {"name": name, "namespace": "kuberos-f"},
            "spec": {"template": {"spec": {"containers": [{"name": "c", "securityContext": context}]}}}}  # fmt: skip


def test_a_deploy_keeps_the_level_the_other_deployments_of_its_fleet_need():
    """Another RosDeployment of the fleet (from another file) runs a privileged module: labelling the namespace for
    this file's pods alone would refuse that module's next pod. Objects this pass renders or removes do not count."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import object_key
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.deploy_pass import keep_pod_security_levels

    ours = _deployment("ours", pod_security.container_security_context())
    others = _deployment("theirs", {"privileged": True})
    removed = _deployment("removed", {"privileged": True})
    live = {object_key(o): o for o in (ours, others, removed)}
    namespace = _namespace("restricted")
    keep_pod_security_levels([namespace], [_deployment("ours", {"privileged": True})], live, [removed])
    assert namespace["metadata"]["labels"][pod_security.ENFORCE] == "privileged"
    namespace = _namespace("restricted")
    keep_pod_security_levels([namespace], [ours], {object_key(ours): ours, object_key(removed): removed}, [removed])
    assert namespace["metadata"]["labels"][pod_security.ENFORCE] == "restricted"


def test_a_rollout_that_needs_a_looser_level_relabels_the_namespace_before_its_first_wave():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.rollout import plan_rollout

    before, after = [_namespace("restricted")], [_namespace("baseline")]
    plan = plan_rollout(before, after, robots=["r1"])
    assert [(c.kind, c.name, c.summary) for c in plan.prepare] == [
        ("Namespace", "kuberos-f", "enforces the baseline Pod Security level (was restricted)")
    ]
    assert not plan_rollout(after, before, robots=["r1"]).prepare, "stricter waits for the next deploy"
