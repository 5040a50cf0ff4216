"""The RosDeployment spec: the paper's Listing 1 as written, defaults, and normalisation."""

from __future__ import annotations

import glob
import os

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import (
    load_rosdeployment_file,
    load_rosdeployments,
    parse_rosdeployment,
)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SEED = os.path.join(os.path.dirname(ROOT), "shared", "seed")

LISTING_1 = """\
metadata:
  name: kubeross-demo-picking
  targetFleet: test-fleet
  robotSelector:
    robot: [fetch-1, fetch-2]
rosModules:
- name: fetch-motion-planner
  image: container-registry/planner:tag
  launch: [ros2 launch package launch_file]
  preference: cloud
  requirements:
    max_latency: 200 ms
- name: fetch-controller-foxy
  image: container-registry/controller:tag
  launch: [ros2 run package script]
  preference: onboard
  requirements:
    onboard: true
"""


def test_listing_1_as_written():
    (dep,) = load_rosdeployments(LISTING_1, "listing1.yml")
    assert (dep.name, dep.fleet, dep.robots) == ("kubeross-demo-picking", "test-fleet", ("fetch-1", "fetch-2"))
    planner, controller = dep.modules
    assert planner.launch == ("ros2 launch package launch_file",)
    assert planner.tiers == ("cloud", "edge", "onboard")
    assert planner.requirements.max_latency_ms == 200.0
    assert controller.tiers == ("onboard",) and controller.requirements.onboard
    assert (dep.ros_domain_id, dep.discovery_servers, dep.discovery_port) == (0, 2, 11811)


def test_listing_1_example_file_is_the_papers_text():
    with open(os.path.join(ROOT, "examples", "listing1.yml"), encoding="utf-8") as handle:
        body = "".join(line for line in handle if not line.startswith("#"))
    assert body == LISTING_1
    seeds = glob.glob(os.path.join(SEED, "*.txt"))
    if not seeds:
        pytest.skip("the paper's text (../shared/seed) is not beside this checkout")
    with open(seeds[0], encoding="utf-8") as handle:
        assert LISTING_1 in handle.read()


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(ROOT, "examples", "*.yml"))))
def test_examples_are_valid(path):
    # Examples may name modules of the local site's software catalog (examples/pick-and-place-catalog.yml).
    assert load_rosdeployment_file(path, catalog=load_catalog(os.path.join(ROOT, "inventories", "local", "catalog")))


def module(**fields):
    return {
        "metadata": {"name": "app", "targetFleet": "f"},
        "rosModules": [{"name": "m", "image": "i", "launch": "run", **fields}],
    }


TIERS = [
    ({}, ("edge", "cloud", "onboard")),
    ({"preference": "onboard"}, ("onboard", "edge", "cloud")),
    ({"preference": "edge"}, ("edge", "cloud", "onboard")),
    ({"preference": "cloud"}, ("cloud", "edge", "onboard")),
    ({"preference": ["cloud"]}, ("cloud",)),
    ({"preference": ["edge", "onboard"]}, ("edge", "onboard")),
    ({"requirements": {"onboard": True}}, ("onboard",)),
    ({"preference": "onboard", "requirements": {"onboard": True}}, ("onboard",)),
    ({"strategy": "shared"}, ("edge", "cloud")),
    ({"strategy": "shared", "preference": "cloud"}, ("cloud", "edge")),
]


@pytest.mark.parametrize(("fields", "tiers"), TIERS)
def test_tier_order(fields, tiers):
    (mod,) = parse_rosdeployment(module(**fields)).modules
    assert mod.tiers == tiers


def test_defaults_and_normalisation():
    dep = parse_rosdeployment(
        module(
            resources={"cpu": "1500m", "memory": "1Gi", "gpu": 1},
            env={"A": 1, "B": True, "C": "x"},
            requirements={"arch": "arm64", "devices": ["camera"], "max_latency": "0.25 s"},
            strategy="shared",
            robotsPerInstance=3,
        )
    )
    (mod,) = dep.modules
    assert (mod.resources.cpu_millis, mod.resources.memory_bytes, mod.resources.gpu) == (1500, 1024**3, 1)
    assert mod.env == (("A", "1"), ("B", "true"), ("C", "x"))
    assert mod.requirements.arch == ("arm64",) and mod.requirements.devices == ("camera",)
    assert mod.requirements.max_latency_ms == 250.0
    assert (mod.strategy, mod.robots_per_instance) == ("shared", 3)
    assert dep.robots is None
    default = parse_rosdeployment(module()).modules[0]
    assert (default.resources.cpu_millis, default.resources.memory_bytes, default.resources.gpu) == (100, 128 * 1024**2, 0)
    assert (default.strategy, default.robots_per_instance) == ("dedicated", 1)


def test_api_version_and_kind_are_optional_but_checked():
    assert parse_rosdeployment({**module(), "apiVersion": "kuberos.io/v1alpha1", "kind": "RosDeployment"})
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError

    with pytest.raises(SpecError, match=r"apiVersion: 'v1' is not valid; expected 'kuberos.io/v1alpha1'"):
        parse_rosdeployment({**module(), "apiVersion": "v1"})


def test_multi_document_file_and_line_numbers():
    deps = load_rosdeployments(LISTING_1 + "---\n" + LISTING_1.replace("kubeross-demo-picking", "second"), "two.yml")
    assert [d.name for d in deps] == ["kubeross-demo-picking", "second"]
    assert deps[1].source == "two.yml (document 2)"
    assert deps[0].line_of("rosModules[1]") == 13


# -- what the hostile-input checks must still accept (tests/unit/test_hostile_input.py has what they refuse) ------

MODULE_WITH = """\
metadata:
  name: demo
  targetFleet: test-fleet
  labels: {{team: picking, example.com/owner: lab-3, app.kubernetes.io/name: planner}}
rosModules:
- name: planner
  image: {image}
  launch: ros2 run planner node
  requirements: {{max_latency: 0.5 ms}}
  rosParameters: {parameters}
"""


@pytest.mark.parametrize(
    "image",
    [
        "planner",
        "ros:jazzy-ros-base",
        "ghcr.io/kuberos/bridge:0.2.0",
        "localhost/planner",
        "localhost:5000/planner:1.0",
        "registry.example.com:5000/a/b/c:v1.2_3-rc.1",
        "Registry.Example.COM/planner:1",  # a registry host may have capitals
        "10.0.0.1:5000/planner",
        "'[fd00::1]:5000/planner:1'",
        "docker.io/library/ubuntu",
        "a__b/c--d.e_f/g-h:_tag",
        "planner:" + "t" * 128,
        "planner@sha256:" + "0123456789abcdef" * 4,
        "ghcr.io/x/planner:1.0@sha512:" + "ab" * 64,
    ],
)
def test_valid_image_references_are_accepted(image):
    (deployment,) = load_rosdeployments(MODULE_WITH.format(image=image, parameters="{}"), "ok.yml")
    assert deployment.modules[0].image == image.strip("'")


@pytest.mark.parametrize(
    "parameters",
    [
        "{use_sim_time: true}",
        "{rate: 10, scale: 0.5, frame: map, flags: [true, false]}",
        "{weights: [1.0, 2.5, .inf], ids: [1, -2, 9223372036854775807], names: [a, b]}",
        "{planner: {ompl: {range: 0.1, goal_bias: 0.05}}}",
        "{qos_overrides: {/tf: {publisher: {depth: 10}}}}",
        "{since: '2024-05-01', empty_text: ''}",
        "{<<: {merged: 1}, own: 2}",
    ],
)
def test_ros_parameters_ros2_reads_are_accepted(parameters):
    (deployment,) = load_rosdeployments(MODULE_WITH.format(image="planner:1", parameters=parameters), "ok.yml")
    assert deployment.modules[0].ros_parameters
    assert deployment.modules[0].requirements.max_latency_ms == 0.5
    assert dict(deployment.labels)["example.com/owner"] == "lab-3"
