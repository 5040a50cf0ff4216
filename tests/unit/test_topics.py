"""Declared topics (plugins/module_utils/kuberos/topics.py): refused before anything is applied when they cannot
match, and judged against what the ROS probe saw in the live graph."""

from __future__ import annotations

import os
import textwrap

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import Catalog, CatalogEntry
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import (
    load_rosdeployment_file,
    load_rosdeployments,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import (
    Endpoint,
    Expectation,
    Observed,
    expectations,
    live_problems,
    qos_mismatch,
    scoped,
    topics_to_watch,
)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

HEAD = """\
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata: {name: pnp, targetFleet: lab}
rosModules:
"""


def _spec(perception: str, planner: str) -> str:
    def topics(text: str) -> str:
        return textwrap.indent(textwrap.dedent(text).strip("\n"), "    ") + "\n"

    return (
        HEAD
        + "- name: perception\n  image: reg/perception:1\n  launch: python3 -m perception\n  topics:\n"
        + topics(perception)
        + "- name: planner\n  image: reg/planner:1\n  launch: python3 -m planner\n  topics:\n"
        + topics(planner)
    )


def _problems(text: str, catalog=None) -> list[str]:
    with pytest.raises(SpecError) as caught:
        load_rosdeployments(text, "spec.yml", catalog=catalog)
    return [str(p) for p in caught.value.problems]


PUBLISHES = """\
publishes:
- {name: detections, type: geometry_msgs/msg/PoseArray, qos: {reliability: best_effort}, rate: {max: 10}}
"""


@pytest.mark.parametrize(
    ("subscribes", "why"),
    [
        pytest.param(
            "subscribes:\n- {name: detections, type: geometry_msgs/msg/PoseArray}",
            "a reliable subscription gets nothing from a best_effort publisher (expected reliability best_effort",
            id="reliable-of-best-effort",
        ),
        pytest.param(
            "subscribes:\n- {name: '/{robot}/detections', type: geometry_msgs/msg/PoseArray,"
            " qos: {reliability: best_effort, durability: transient_local}}",
            "a transient_local subscription gets nothing from a volatile publisher",
            id="latched-of-volatile",
        ),
        pytest.param(
            "subscribes:\n- {name: detections, type: geometry_msgs/msg/PoseStamped, qos: {reliability: best_effort}}",
            "the types differ (geometry_msgs/msg/PoseStamped subscribed, geometry_msgs/msg/PoseArray published)",
            id="type",
        ),
        pytest.param(
            "subscribes:\n- {name: detections, type: geometry_msgs/msg/PoseArray, qos: {reliability: best_effort},"
            " rate: {min: 15}}",
            "it needs at least 15 Hz and the publisher declares at most 10 Hz",
            id="rate",
        ),
    ],
)
def test_declarations_that_cannot_match_are_refused_in_one_line_naming_both_modules_the_topic_and_why(subscribes, why):
    problems = _problems(_spec(PUBLISHES, subscribes))
    assert len(problems) == 1, problems
    (line,) = problems
    assert line.startswith("spec.yml:16: rosModules[1].topics.subscribes[0]: "), line
    assert "planner subscribes to /{robot}/detections but perception publishes it: " + why in line, line


def test_a_subscription_nobody_publishes_is_refused_unless_it_is_external():
    lonely = "subscribes:\n- {name: scene, type: sensor_msgs/msg/PointCloud2}"
    (line,) = _problems(_spec(PUBLISHES, lonely))
    assert "rosModules[1].topics.subscribes[0]: planner subscribes to /{robot}/scene, which no module of the " in line
    assert "or external: true for a topic published outside the deployment" in line
    external = "subscribes:\n- {name: scene, type: sensor_msgs/msg/PointCloud2, external: true}"
    (deployment,) = load_rosdeployments(_spec(PUBLISHES, external), "spec.yml")
    assert [t.external for t in deployment.modules[1].topics] == [True]


def test_a_fleet_wide_name_is_another_topic_than_a_robots_and_matching_declarations_pass():
    fleet = "subscribes:\n- {name: /detections, type: geometry_msgs/msg/PoseArray, qos: {reliability: best_effort}}"
    (line,) = _problems(_spec(PUBLISHES, fleet))
    assert "subscribes to /detections, which no module" in line
    fine = "subscribes:\n- {name: '/{robot}/detections', type: geometry_msgs/msg/PoseArray, qos: {reliability: best_effort}}"
    (deployment,) = load_rosdeployments(_spec(PUBLISHES, fine), "spec.yml")
    assert [scoped(t.name) for m in deployment.modules for t in m.topics] == ["/{robot}/detections"] * 2


def test_a_module_contradicting_itself_is_refused():
    twice = "publishes:\n- {name: a, type: std_msgs/msg/Bool}\n- {name: '/{robot}/a', type: std_msgs/msg/Bool}"
    backwards = "publishes:\n- {name: b, type: std_msgs/msg/Bool, rate: {min: 20, max: 5}}"
    problems = _problems(_spec(twice, backwards))
    assert any("perception already declares publishes /{robot}/a (publishes[0]); expected each topic once" in p for p in problems)
    assert any("rosModules[1].topics.publishes[0]: rate min 20 Hz is above max 5 Hz" in p for p in problems), problems


@pytest.mark.parametrize(
    ("topic", "path", "expected"),
    [
        ("{name: 'a b', type: std_msgs/msg/Bool}", "publishes[0].name", "a ROS topic name such as 'detections'"),
        ("{name: a, type: Bool}", "publishes[0].type", "a message type such as 'std_msgs/msg/String'"),
        ("{name: a, type: std_msgs/msg/Bool, qos: {reliability: sometimes}}", "publishes[0].qos.reliability",
         "reliable or best_effort"),
        ("{name: a, type: std_msgs/msg/Bool, rate: {min: 0}}", "publishes[0].rate.min", "a rate in Hz above 0"),
        ("{name: a, type: std_msgs/msg/Bool, external: true}", "publishes[0]", "external"),
    ],
)  # fmt: skip
def test_malformed_declarations_name_the_field(topic, path, expected):
    problems = _problems(_spec(f"publishes:\n- {topic}", "subscribes: []"))
    assert any(f"rosModules[0].topics.{path}" in p and expected in p for p in problems), problems


CATALOG_TOPICS = {
    "publishes": [{"name": "detections", "type": "geometry_msgs/msg/PoseArray", "qos": {"reliability": "best_effort"}}],
}


def _catalog() -> Catalog:
    return Catalog([CatalogEntry("perception", "0.2.0", "reg/perception:0.2.0", launch=("perceive",), topics=CATALOG_TOPICS)])


def test_catalog_declarations_are_checked_and_named_and_a_spec_replaces_a_direction():
    text = HEAD + textwrap.dedent(
        """\
        - name: perception
          module: perception@^0.2
        - name: planner
          image: reg/planner:1
          launch: plan
          topics:
            subscribes:
            - {name: detections, type: geometry_msgs/msg/PoseArray}
        """
    )
    problems = _problems(text, _catalog())
    assert any(
        "rosModules[1].topics.subscribes[0]: planner subscribes to /{robot}/detections but perception publishes it: "
        "a reliable subscription gets nothing" in p
        for p in problems
    ), problems
    over = text.replace("module: perception@^0.2", "module: perception@^0.2\n  topics:\n    publishes:\n"
                        "    - {name: detections, type: geometry_msgs/msg/PoseArray}")  # fmt: skip
    (deployment,) = load_rosdeployments(over, "spec.yml", catalog=_catalog())
    assert [(t.reliability, t.origin) for t in deployment.modules[0].topics] == [("reliable", "")]
    reverse = text.replace("launch: plan\n", "launch: plan\n  requirements: {onboard: true}\n")
    reverse = reverse.replace("- {name: detections, type: geometry_msgs/msg/PoseArray}",
                              "- {name: detections, type: std_msgs/msg/String, qos: {reliability: best_effort}}")  # fmt: skip
    (line,) = _problems(reverse, _catalog())
    assert "the types differ" in line and "rosModules[1].topics.subscribes[0]" in line
    entry = _catalog().all_entries()[0]
    assert Catalog.from_dict(Catalog([entry]).to_dict()).all_entries()[0].topics == CATALOG_TOPICS


def test_a_catalog_entrys_declaration_problem_points_at_the_module_line_and_names_the_entry():
    listener = CatalogEntry("listener", "1.0.0", "reg/listener:1.0.0", launch=("listen",),
                            topics={"subscribes": [{"name": "scene", "type": "std_msgs/msg/Bool"}]})  # fmt: skip
    text = HEAD + "- name: perception\n  module: perception@^0.2\n- name: listener\n  module: listener\n"
    (line,) = _problems(text, Catalog([*_catalog().all_entries(), listener]))
    assert line == (
        "spec.yml:8: rosModules[1].module: listener subscribes to /{robot}/scene, which no module of the deployment "
        "publishes; expected a module that declares it in publishes, or external: true for a topic published outside "
        "the deployment (subscribes from the catalog's listener 1.0.0)"
    )


def test_the_example_declares_the_pick_and_place_graph_and_it_matches():
    (deployment,) = load_rosdeployment_file(os.path.join(ROOT, "examples", "pick-and-place.yml"))
    wanted = {e.name: e for e in expectations(deployment.modules)}
    assert wanted["/{robot}/plan/request"].publishers == ["task-coordinator"]
    assert wanted["/{robot}/plan/request"].subscribers == ["motion-planner"]
    assert wanted["/{robot}/joint_states"].external and wanted["/{robot}/joint_states"].rate_min == 10


# -- the live graph ------------------------------------------------------------------------------------------------

WANT = Expectation("/{robot}/detections", "geometry_msgs/msg/PoseArray", ["perception"], ["planner"], 5.0, 50.0, ["planner"])


def _seen(pub_reliability="reliable", sub_reliability="reliable", rate=10.0, pub_type="geometry_msgs/msg/PoseArray"):
    return Observed(
        [Endpoint("/fetch_1/perception", pub_type, pub_reliability, "volatile")],
        [Endpoint("/fetch_1/planner", "geometry_msgs/msg/PoseArray", sub_reliability, "volatile")],
        rate,
    )


def test_the_live_check_wants_every_declared_endpoint_on_every_robot():
    watched = topics_to_watch([WANT, Expectation("/fleet/status", "std_msgs/msg/String", ["monitor"])], ["fetch-1", "7x"])
    assert [(name, robot) for name, _want, robot in watched] == [
        ("/fetch_1/detections", "fetch-1"), ("/r_7x/detections", "7x"), ("/fleet/status", ""),
    ]  # fmt: skip
    status = Observed([Endpoint("/m", "std_msgs/msg/String", "reliable", "volatile")])
    observed = {"/fetch_1/detections": _seen(), "/fleet/status": status}
    assert live_problems(watched, observed, 3.0) == [
        "/r_7x/detections: no subscription in the graph (planner declares one)",
        "/r_7x/detections: nobody publishes it (perception declares it)",
    ]


@pytest.mark.parametrize(
    ("seen", "line"),
    [
        (_seen(), None),
        (_seen(pub_reliability="best_effort"), "/fetch_1/detections: /fetch_1/planner and /fetch_1/perception never match: "
                                               "a reliable subscription gets nothing from a best_effort publisher"),
        (_seen(pub_type="std_msgs/msg/String"), "/fetch_1/detections: /fetch_1/perception publishes std_msgs/msg/String, "
                                                "but the declared type is geometry_msgs/msg/PoseArray"),
        (_seen(rate=2.0), "/fetch_1/detections: 2.0 Hz over 3 s, outside 5-50 Hz (declared by planner)"),
        (_seen(rate=80.0), "/fetch_1/detections: 80.0 Hz over 3 s, outside 5-50 Hz (declared by planner)"),
        (_seen(rate=None), "/fetch_1/detections: rate not measured (declared 5-50 Hz by planner)"),
        (Observed([Endpoint("/fetch_1/perception", "geometry_msgs/msg/PoseArray", "reliable", "volatile", 250.0)],
                  [Endpoint("/fetch_1/planner", "geometry_msgs/msg/PoseArray", "reliable", "volatile", 100.0)], 10.0),
         "/fetch_1/detections: /fetch_1/planner and /fetch_1/perception never match: a subscription requesting a "
         "deadline of 100 ms gets nothing from a publisher offering 250 ms"),
    ],
)  # fmt: skip
def test_the_live_check_catches_a_lie_about_qos_a_wrong_type_and_a_rate_out_of_bounds(seen, line):
    problems = live_problems(topics_to_watch([WANT], ["fetch-1"]), {"/fetch_1/detections": seen}, 3.0)
    assert [p[: len(line)] for p in problems] == [line] if line else problems == [], problems


def test_expectations_travel_as_plain_data_and_hostile_data_is_refused():
    assert Expectation.from_dict(WANT.to_dict()) == WANT
    for bad in ("x", {"name": 1, "type": "a"}, {"name": "/a", "type": "t", "rate_min": "fast"},
                {"name": "/a", "type": "t", "publishers": "me"}):  # fmt: skip
        with pytest.raises(ValueError):
            Expectation.from_dict(bad)


def _point(reliability="reliable", durability="volatile", deadline=None, liveliness="automatic", lease=None):
    return Endpoint("/n", "std_msgs/msg/Bool", reliability, durability, deadline, liveliness, lease)


def test_qos_rules_are_the_request_offered_rules_of_ros_2():
    assert qos_mismatch(_point(durability="transient_local"), _point(reliability="best_effort")) == ""
    assert qos_mismatch(_point(), _point()) == ""
    assert "best_effort publisher" in qos_mismatch(_point(reliability="best_effort"), _point())
    assert "volatile publisher" in qos_mismatch(_point(), _point(durability="transient_local"))
    # deadline and lease: the publisher offers at most what the subscription requests; none is infinite
    assert qos_mismatch(_point(deadline=100.0), _point(deadline=200.0)) == ""
    assert qos_mismatch(_point(deadline=100.0), _point()) == "", "a subscription without a deadline takes any"
    assert qos_mismatch(_point(deadline=200.0), _point(deadline=100.0)) == (
        "a subscription requesting a deadline of 100 ms gets nothing from a publisher offering 200 ms (expected the "
        "publisher's deadline at most the subscription's)"
    )
    assert "publisher offering none" in qos_mismatch(_point(), _point(deadline=100.0))
    assert "manual_by_topic subscription gets nothing from an automatic publisher" in qos_mismatch(
        _point(), _point(liveliness="manual_by_topic")
    )
    assert qos_mismatch(_point(liveliness="manual_by_topic"), _point()) == ""
    assert "liveliness lease of 1000 ms gets nothing from a publisher offering 2000 ms" in qos_mismatch(
        _point(lease=2000.0), _point(lease=1000.0)
    )
    assert qos_mismatch(_point(lease=500.0), _point(lease=1000.0)) == ""


@pytest.mark.parametrize(
    ("published", "subscribed", "why"),
    [
        ("deadline: 200 ms", "deadline: 0.1 s",
         "a subscription requesting a deadline of 100 ms gets nothing from a publisher offering 200 ms"),
        ("{}", "deadline: 100",
         "a subscription requesting a deadline of 100 ms gets nothing from a publisher offering none"),
        ("liveliness: automatic", "liveliness: manual_by_topic",
         "a manual_by_topic subscription gets nothing from an automatic publisher"),
        ("lease_duration: 2 s", "lease_duration: 1 s",
         "a subscription requesting a liveliness lease of 1000 ms gets nothing from a publisher offering 2000 ms"),
        ("{deadline: 50 ms, liveliness: manual_by_topic, lease_duration: 1 s}",
         "{deadline: 100 ms, liveliness: manual_by_topic, lease_duration: 1 s}", None),
    ],
)  # fmt: skip
def test_deadline_and_liveliness_are_checked_before_anything_is_applied(published, subscribed, why):
    def qos(text):
        return text if text.startswith("{") else "{" + text + "}"

    pub = f"publishes:\n- {{name: beat, type: std_msgs/msg/Bool, qos: {qos(published)}}}"
    sub = f"subscribes:\n- {{name: beat, type: std_msgs/msg/Bool, qos: {qos(subscribed)}}}"
    if why is None:
        (deployment,) = load_rosdeployments(_spec(pub, sub), "spec.yml")
        assert deployment.modules[0].topics[0].deadline_ms == 50.0 and deployment.modules[1].topics[0].lease_ms == 1000.0
        return
    (line,) = _problems(_spec(pub, sub))
    assert "planner subscribes to /{robot}/beat but perception publishes it: " + why in line, line
