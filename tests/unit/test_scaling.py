"""Scaling shared modules: the pure decisions (``kuberos.scaling``), the spec's policy, what is rendered for a
scaled module, and how the controller reads a module's load signal (``kuberos_controller.signals``)."""

from __future__ import annotations

import http.server
import threading
from dataclasses import replace

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import scaling
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Instance
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import ScalingPolicy, load_rosdeployments
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import signals

POLICY = ScalingPolicy(min_instances=1, max_instances=4, metric="queue", target=2.0, scale_down_window_s=60, drain_s=15)


# -- recommendation and windows ---------------------------------------------------------------------------------
def test_recommend_follows_the_hpa_rule_with_a_tolerance():
    assert scaling.recommend(2, [4.0, 4.0], 2.0) == 4  # twice the target: twice the instances
    assert scaling.recommend(2, [2.1, 2.1], 2.0) == 2  # within 10 %
    assert scaling.recommend(3, [1.0, 1.0, 1.0], 2.0) == 2  # ceil(3 * 0.5)
    assert scaling.recommend(2, [0.0, 0.0], 2.0) == 1  # never below one
    assert scaling.recommend(2, [], 2.0) is None  # nobody reported


def test_bounds_respect_robots_per_instance_and_the_robot_count():
    assert scaling.bounds(POLICY, 8, 4) == (2, 4)  # 8 robots need 2 instances of 4
    assert scaling.bounds(POLICY, 3, 4) == (1, 3)  # never more instances than robots
    assert scaling.bounds(replace(POLICY, min_instances=5), 3, 4) == (3, 3)
    assert scaling.bounds(POLICY, 0, 4) == (0, 0)


def test_scale_up_is_immediate_and_scale_down_waits_for_its_window():
    windows = scaling.Windows()
    assert windows.desired(POLICY, 0.0, 2, 4) == (4, "")  # up: at once (scaleUpWindow 0)
    windows.restart(10.0)
    desired, held = windows.desired(POLICY, 20.0, 4, 1)
    assert desired == 4 and "scale-down window" in held  # watched 10 of 60 s
    desired, held = windows.desired(POLICY, 75.0, 4, 1)
    assert desired == 1 and held == ""  # watched 65 s, every recommendation in the last 60 s is 1


def test_a_flapping_signal_does_not_scale_down():
    windows = scaling.Windows()
    windows.restart(0.0)
    outcomes = []
    for second in range(0, 300, 10):  # the load swings every 10 s between 1 and 3 instances' worth
        recommendation = 1 if (second // 10) % 2 else 3
        outcomes.append(windows.desired(POLICY, float(second), 3, recommendation)[0])
    assert outcomes == [3] * len(outcomes)  # a 3 within every 60 s window holds the count


def test_scale_up_takes_the_lowest_recommendation_of_its_window():
    policy = replace(POLICY, scale_up_window_s=30)
    windows = scaling.Windows()
    assert windows.desired(policy, 0.0, 1, 2)[0] == 2
    assert windows.desired(policy, 10.0, 1, 4)[0] == 2  # 2 was recommended 10 s ago
    assert windows.desired(policy, 45.0, 1, 4)[0] == 4  # 2 left the window


# -- re-assignment ----------------------------------------------------------------------------------------------
def test_grow_moves_only_what_the_new_instances_take_and_evens_the_load():
    before = {"a": ("r1", "r2", "r3", "r4"), "b": ("r5", "r6", "r7", "r8")}
    after, moved = scaling.grow(before, ["c", "d"])
    assert sorted(len(r) for r in after.values()) == [2, 2, 2, 2]
    assert len(moved) == 4  # exactly the robots the two new instances serve
    for robot, (old, new) in moved.items():
        assert robot in before[old] and robot in after[new]
    unmoved = {r for robots in before.values() for r in robots} - set(moved)
    assert all(any(r in after[n] for n in before if r in before[n]) for r in unmoved)


def test_grow_respects_which_robots_may_use_the_new_instance():
    after, _moved = scaling.grow({"a": ("near", "far", "x", "y")}, ["b"], fits=lambda robot, inst: robot != "far")
    assert "far" in after["a"] and len(after["b"]) == 2


def test_shrink_gives_the_robots_to_the_least_loaded_with_room():
    before = {"a": ("r1", "r2"), "b": ("r3",), "c": ("r4",)}
    assert scaling.leaving_instances(before, 1) == ["c"]  # fewest robots, newest first
    after, moved = scaling.shrink(before, ["c"], per_instance=2)
    assert after["c"] == () and after["b"] == ("r3", "r4") and moved == {"r4": ("c", "b")}
    assert scaling.shrink({"a": ("r1", "r2"), "b": ("r3",)}, ["b"], per_instance=2) is None  # a is full


def test_a_handed_over_robot_stays_served_by_its_old_instance_until_the_new_one_is_ready():
    placed = {"a": ("r1",), "b": ("r2",)}
    state = scaling.ScaleState(handover={"r2": "a"})
    assert scaling.serving(placed, state) == {"a": ("r1", "r2"), "b": ()}
    state, stop = scaling.settle(state, placed, ready={"a"}, now=0.0)
    assert state.handover == {"r2": "a"} and stop == []
    state, stop = scaling.settle(state, placed, ready={"a", "b"}, now=1.0)
    assert state.handover == {} and scaling.serving(placed, state) == {"a": ("r1",), "b": ("r2",)}


def test_a_leaving_instance_stops_only_after_its_drain_time():
    placed = {"a": ("r1", "r2"), "b": ()}
    state = scaling.ScaleState(leaving={"b": 100.0})
    assert scaling.settle(state, placed, {"a", "b"}, 99.0)[1] == []
    state, stop = scaling.settle(state, placed, {"a", "b"}, 100.0)
    assert stop == ["b"] and state.leaving == {}
    assert scaling.ScaleState.from_dict({"handover": "x", "leaving": {"b": "soon"}}) == scaling.ScaleState()


# -- one step ---------------------------------------------------------------------------------------------------
def _instance(name, node, robots, tier="edge"):
    return Instance(name, "app", "f", "kuberos-f", "planner", node, tier, tuple(robots), "preferred tier edge", 5.0, 500,
                    2**28, 0, shared=True)  # fmt: skip


class _Node:
    def __init__(self, name):
        self.name = name


def _step(instances, values, ready=None, state=None, windows=None, now=0.0, place=None, policy=POLICY):
    module = type("M", (), {"name": "planner", "scaling": policy, "robots_per_instance": 4, "tiers": ("edge", "cloud")})
    dep = type("D", (), {"name": "app"})
    return scaling.step(
        dep, module, instances, state or scaling.ScaleState(), {i.name for i in instances} if ready is None else ready,
        values, windows or scaling.Windows(), now, place or (lambda robots: (_Node("edge-2"), "edge", 5.0, "most free")),
        lambda robot, node: isinstance(node, str) and node.startswith("edge-"),  # a node's name, as the inventory has it
    )  # fmt: skip


def test_a_step_up_places_a_new_instance_and_hands_robots_over():
    step = _step([_instance("app-planner-shared-0", "edge-1", ["r1", "r2", "r3", "r4"])], {"app-planner-shared-0": 5.0})
    assert step.start == ["app-planner-shared-1", "app-planner-shared-2"] and step.summary["desired"] == 3
    new = [i for i in step.instances if i.name in step.start]
    assert len(new) == 2 and {i.node for i in new} == {"edge-2"}
    assert sum(len(i.robots) for i in step.instances) == 4
    assert set(step.state.handover.values()) == {"app-planner-shared-0"}  # still served by the old one
    assert step.events[0][1] == "ModuleScaledUp" and "1 -> 3 instances" in step.events[0][2]


def test_a_step_down_drains_and_a_later_step_stops_the_instance():
    instances = [_instance("app-planner-shared-0", "edge-1", ["r1", "r2"]), _instance("app-planner-shared-1", "edge-2", ["r3"])]
    windows = scaling.Windows()
    windows.restart(-100.0)
    step = _step(instances, {"app-planner-shared-0": 0.5, "app-planner-shared-1": 0.5}, windows=windows)
    assert step.events[0][1] == "ModuleScaledDown" and step.state.leaving == {"app-planner-shared-1": 15.0}
    assert dict((i.name, i.robots) for i in step.instances)["app-planner-shared-1"] == ()
    assert step.start == [] and step.stop == [] and step.wake_at == 15.0
    later = _step(step.instances, {}, state=step.state, now=15.0)
    assert later.stop == ["app-planner-shared-1"] and [i.name for i in later.instances] == ["app-planner-shared-0"]


def test_a_step_down_takes_the_least_preferred_tier_first_so_a_peaks_vms_can_go():
    instances = [
        _instance("app-planner-shared-0", "edge-1", ["r1"]),
        _instance("app-planner-shared-1", "edge-2", ["r2"]),
        _instance("app-planner-shared-2", "cloud-vm-1", ["r3", "r4"], tier="cloud"),  # serves the most, leaves first
    ]
    windows = scaling.Windows()
    windows.restart(-100.0)
    step = _step(instances, {i.name: 1.2 for i in instances}, windows=windows)  # 3 -> 2
    assert list(step.state.leaving) == ["app-planner-shared-2"], step.events
    assert scaling.leaving_instances({"a": ("r1",), "b": ("r2", "r3")}, 1, {"b": 1}) == ["b"]
    assert scaling.leaving_instances({"a": ("r1",), "b": ("r2", "r3")}, 1) == ["a"]


def test_a_step_holds_while_an_instance_is_not_ready_or_nothing_reports():
    instances = [_instance("app-planner-shared-0", "edge-1", ["r1", "r2"])]
    assert _step(instances, {"app-planner-shared-0": 9.0}, ready=set()).summary["held"].startswith("waiting")
    assert _step(instances, {}).summary["held"] == "no signal from the instances"


def test_a_step_without_a_node_is_blocked_and_changes_nothing():
    instances = [_instance("app-planner-shared-0", "edge-1", ["r1", "r2"])]
    step = _step(instances, {"app-planner-shared-0": 9.0}, place=lambda robots: (None, None, None, ["edge-2: cpu full"]))
    assert step.instances == instances and step.start == [] and step.state == scaling.ScaleState()
    assert step.events[0][1] == "ModuleScaleBlocked" and "edge-2: cpu full" in step.summary["held"]


# -- spec and manifests -----------------------------------------------------------------------------------------
def test_the_example_renders_a_robots_configmap_instead_of_a_robots_variable(root, local_raw):
    deployments, placement = load_and_place(f"{root}/examples/scaling.yml", local_raw)
    module = deployments[0].modules[0]
    assert module.scaling == ScalingPolicy(1, 2, "kuberos_planner_queue_depth", 2.0, 9464, 0.0, 60.0, 15.0)
    objects = render_deployment(deployments, placement)
    robots = next(o for o in objects if o["metadata"]["name"] == "scaled-planning-motion-planner-robots")
    assert robots["data"] == {placement.instances[0].name: "fetch-1,fetch-2"}
    deployment = next(o for o in objects if o["kind"] == "Deployment" and "motion-planner" in o["metadata"]["name"])
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert "KUBEROS_ROBOTS" not in env  # the pod template never changes when robots move
    assert env["KUBEROS_ROBOTS_FILE"] == f"/etc/kuberos-robots/{placement.instances[0].name}"
    assert {"name": "robots", "mountPath": "/etc/kuberos-robots", "readOnly": True} in container["volumeMounts"]


@pytest.mark.parametrize(
    ("scaling_yaml", "message"),
    [
        ("{maxInstances: 2}", "scaling: only applies with strategy: shared"),
        ("{maxInstances: 0}", "scaling.maxInstances: 0 (int) is not valid"),
        ("{minInstances: 3, maxInstances: 2}", "scaling.maxInstances: 2 is below minInstances 3"),
        ("{maxInstances: 2, metric: queue}", "scaling.target: is required with metric queue"),
        ("{maxInstances: 2, metric: 'a b', target: 1}", "scaling.metric: 'a b' is not valid"),
        ("{maxInstances: 2, target: -1}", "scaling.target: -1 (int) is not valid"),
        ("{maxInstances: 2, drainTime: soon}", "scaling.drainTime: 'soon' is not valid"),
        ("{maxInstances: 2, replicas: 3}", "replicas"),
    ],
)
def test_a_bad_policy_names_the_field(scaling_yaml, message):
    shared = "" if message.startswith("scaling: only") else "\n  strategy: shared"
    text = (
        "metadata: {name: app, targetFleet: test-fleet}\nrosModules:\n- name: p\n  image: x/p:1\n  launch: [p]"
        f"{shared}\n  scaling: {scaling_yaml}\n"
    )
    with pytest.raises(SpecError) as caught:
        load_rosdeployments(text, "app.yml")
    assert "app.yml:" in str(caught.value) and message in str(caught.value)


# -- signals ----------------------------------------------------------------------------------------------------
def test_gauges_and_cpu_usages_are_read():
    text = '# TYPE q gauge\nq{robot="a"} 2\nq{robot="b"} 1.5\nother 9\n'
    assert scaling.gauge_value(text, "q") == 3.5
    assert scaling.gauge_value(text, "missing") is None
    assert scaling.gauge_value("not { a metric", "q") is None
    assert signals.cpu_millis("250000000n") == 250.0 and signals.cpu_millis("2") == 2000.0
    with pytest.raises(ValueError):
        signals.cpu_millis("lots")


def test_a_pods_own_metric_is_scraped_from_its_address_and_a_silent_pod_gives_nothing():
    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = b"# TYPE kuberos_planner_queue_depth gauge\nkuberos_planner_queue_depth 3\n"
            self.send_response(200 if self.path == "/metrics" else 404)
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        policy = ScalingPolicy(1, 2, "kuberos_planner_queue_depth", 2.0, server.server_address[1])
        pods = {
            "a": {"metadata": {"name": "a-1"}, "status": {"podIP": "127.0.0.1"}},
            "b": {"metadata": {"name": "b-1"}, "status": {}},  # no address yet
        }
        assert signals.Signals(timeout=1.0).values("ns", policy, pods, 500, 0.0) == {"a": 3.0}
    finally:
        server.shutdown()
        server.server_close()


def test_a_shortfall_stands_while_the_step_that_found_it_waits_and_ends_when_a_step_decides():
    instances = [_instance("app-planner-shared-0", "edge-1", ["r1", "r2", "r3", "r4"])]
    full = _step(instances, {"app-planner-shared-0": 9.0}, place=lambda robots: (None, None, None, ["edge-2: cpu full"]))
    why = scaling.lacking(full, None)
    assert full.decided and "edge-2: cpu full" in why
    waiting = _step(instances, {"app-planner-shared-0": 9.0}, ready=set())  # an instance it placed is not Ready yet
    assert not waiting.decided and scaling.lacking(waiting, why) == why, "still lacking while the step waits"
    silent = _step(instances, {})
    assert not silent.decided and scaling.lacking(silent, why) == why
    windows = scaling.Windows()
    windows.restart(-100.0)
    calm = _step(instances, {"app-planner-shared-0": 2.0}, windows=windows)  # at the target: nothing more wanted
    assert calm.decided and calm.events == [] and scaling.lacking(calm, why) is None
