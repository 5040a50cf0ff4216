"""The live check of declared topics (ros_graph_probe --topics) with real rclpy nodes and a Fast DDS discovery server.

The modules are processes on loopback with ROS_DISCOVERY_SERVER set as rendered modules have it; the probe joins
as a super client, as it does after a deploy and after each rollout wave. The declarations come from a spec,
through ``kuberos.topics.expectations``, as the deploy and the rollout give them (KUBEROS_TOPICS).
"""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from helpers import ROOT
from test_ros_probe import PROBE, PYTHON, graph  # noqa: F401  (the fixture: a discovery server on loopback)

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import expectations

NODE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "ros", "topic_node.py")

SPEC = """\
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata: {name: pnp, targetFleet: lab}
rosModules:
- name: perception
  image: reg/perception:1
  launch: perceive
  topics:
    publishes:
    - {name: detections, type: std_msgs/msg/String, qos: {reliability: RELIABILITY QOS}, rate: {min: 5, max: 40}}
- name: planner
  image: reg/planner:1
  launch: plan
  topics:
    subscribes:
    - {name: detections, type: std_msgs/msg/String, qos: {reliability: RELIABILITY QOS}}
"""


def _declared(reliability: str, qos: str = "") -> str:
    text = SPEC.replace("RELIABILITY", reliability).replace(" QOS", f", {qos}" if qos else "")
    (deployment,) = load_rosdeployments(text, "spec.yml")
    return json.dumps([e.to_dict() for e in expectations(deployment.modules)])


@pytest.fixture
def modules(graph):  # noqa: F811
    """Start module processes in the graph: ``start(name, *endpoint args)``; all are killed afterwards."""
    env, _server = graph
    started = []

    def start(name, *endpoints):
        node = subprocess.Popen([PYTHON, NODE, name, "/fetch_1", *endpoints], env=env, stdout=subprocess.PIPE, text=True)
        started.append(node)
        assert node.stdout.readline().strip() == "up"
        return node

    yield env, start
    for node in started:
        node.kill()
        node.wait(10)


def _probe(env, declared, *extra, timeout="10"):
    return subprocess.run(
        [PYTHON, "-m", PROBE, "--topics", "--timeout", timeout, "--window", "2", "--json", *extra],
        env={**env, "KUBEROS_ROBOTS": "fetch-1", "KUBEROS_TOPICS": declared}, capture_output=True, text=True, timeout=90,
    )  # fmt: skip


@pytest.mark.ros
def test_declared_topics_that_really_connect_pass_with_their_measured_rate(modules):
    env, start = modules
    start("perception", "--pub", "detections:best_effort:20")
    start("planner", "--sub", "detections:best_effort")
    done = _probe(env, _declared("best_effort"))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 topic(s) on 1 robot(s) as declared" in done.stdout
    (topic,) = json.loads(done.stdout.splitlines()[0])["topics"]
    assert topic["name"] == "/fetch_1/detections" and 15 <= topic["rate"] <= 25, topic
    assert [p["node"] for p in topic["publishers"]] == ["/fetch_1/perception"]
    assert [s["node"] for s in topic["subscribers"]] == ["/fetch_1/planner"], "the probe's own subscription left out"
    (publisher,) = topic["publishers"]
    assert (publisher["deadline_ms"], publisher["liveliness"], publisher["lease_ms"]) == (None, "automatic", None), publisher


@pytest.mark.ros
def test_a_module_that_lies_about_its_qos_is_caught_live(modules):
    """The declarations say reliable on both sides (deploy accepts them); perception really publishes best effort,
    so the planner's reliable subscription never receives anything: the probe names both nodes and why."""
    env, start = modules
    start("perception", "--pub", "detections:best_effort:20")
    start("planner", "--sub", "detections:reliable")
    done = _probe(env, _declared("reliable"))
    assert done.returncode == 1, done.stdout + done.stderr
    assert (
        "ros_graph_probe: /fetch_1/detections: /fetch_1/planner and /fetch_1/perception never match: a reliable "
        "subscription gets nothing from a best_effort publisher"
    ) in done.stderr, done.stderr


@pytest.mark.ros
def test_a_module_that_lies_about_its_deadline_is_caught_live(modules):
    """Both declare a 100 ms deadline (deploy accepts them). A perception that offers 50 ms keeps its word and
    passes; a second one that really offers 500 ms never serves the planner's request for 100 ms and is named."""
    env, start = modules
    declared = _declared("best_effort", "deadline: 100 ms")
    start("planner", "--sub", "detections:best_effort:100")
    start("perception", "--pub", "detections:best_effort:20:50")
    kept = _probe(env, declared)
    assert kept.returncode == 0, kept.stdout + kept.stderr
    (topic,) = json.loads(kept.stdout.splitlines()[0])["topics"]
    assert [(p["node"], p["deadline_ms"]) for p in topic["publishers"]] == [("/fetch_1/perception", 50.0)], topic
    assert [s["deadline_ms"] for s in topic["subscribers"]] == [100.0], topic
    start("perception_spare", "--pub", "detections:best_effort:2:500")  # the two together stay within 5-40 Hz
    done = _probe(env, declared)
    assert done.returncode == 1, done.stdout + done.stderr
    problems = [line for line in done.stderr.splitlines() if line.startswith("ros_graph_probe: ")]
    assert problems == [
        "ros_graph_probe: /fetch_1/detections: /fetch_1/planner and /fetch_1/perception_spare never match: a "
        "subscription requesting a deadline of 100 ms gets nothing from a publisher offering 500 ms (expected the "
        "publisher's deadline at most the subscription's)"
    ], done.stderr


@pytest.mark.ros
def test_a_rate_below_its_bound_and_a_missing_subscriber_fail(modules):
    env, start = modules
    start("perception", "--pub", "detections:reliable:2")
    slow = _probe(env, _declared("reliable"), timeout="4")
    assert slow.returncode == 1
    assert "/fetch_1/detections: no subscription in the graph (planner declares one)" in slow.stderr, slow.stderr
    start("planner", "--sub", "detections:reliable")
    slow = _probe(env, _declared("reliable"))
    assert slow.returncode == 1, slow.stdout + slow.stderr
    assert "/fetch_1/detections: " in slow.stderr and "Hz over 2 s, outside 5-40 Hz (declared by perception)" in slow.stderr


def test_bad_declarations_are_refused_with_exit_2():
    for text in ("", "{", '{"name": "/a"}', json.dumps([{"name": "/a"}])):
        env = {**os.environ, "KUBEROS_TOPICS": text, "PYTHONPATH": os.path.join(ROOT, ".collections")}
        done = subprocess.run([PYTHON, "-m", PROBE, "--topics"], env=env,
                              capture_output=True, text=True, timeout=60)  # fmt: skip
        assert done.returncode == 2, (text, done.stderr)
        assert done.stderr.startswith("ros_graph_probe: KUBEROS_TOPICS"), done.stderr
        assert "Traceback" not in done.stderr
