"""Fuzzing the spec (a RosDeployment file, its declared topics and catalog references) and the software catalog:
valid files with one field made hostile, and raw text. Each case gives deployments, or one ``SpecError`` whose every
problem names the file, and the line of the field it names, within the tier's bounds (fuzz_bounds.run_case)."""

from __future__ import annotations

import os
import re

from fuzz_bounds import fuzz_settings, run_case
from fuzz_yaml import Bases, mutated, raw_yaml
from helpers import CATALOG_BASE, ROOT, SPEC_BASE, yml
from hypothesis import given

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import catalog as catalogs
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import spec
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError

SPEC = "spec.yml"
CATALOG = "catalog"


def _example(name: str) -> str:
    with open(os.path.join(ROOT, "examples", name), encoding="utf-8") as handle:
        return handle.read()


# A module with most of what a module may say, and topics with every QoS field, rate, and external subscriptions.
EVERYTHING = yml(
    """
    apiVersion: kuberos.io/v1alpha1
    kind: RosDeployment
    metadata:
      name: everything
      targetFleet: test-fleet
      labels: {app.kubernetes.io/part-of: everything}
    rosDomainId: 7
    discovery: {servers: 2}
    rosModules:
    - name: driver
      image: registry.example.com/driver@sha256:0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef
      launch: [ros2 run driver node, ros2 run driver filter]
      requirements: {onboard: true, devices: [lidar], arch: [amd64, arm64]}
      resources: {cpu: 250m, memory: 256Mi}
      env: {LOG_LEVEL: info}
      rosParameters: {rate_hz: 10.0, frame: base_link, enabled: true, gains: [1, 2, 3]}
      topics:
        publishes:
        - name: scan
          type: sensor_msgs/msg/LaserScan
          qos: {reliability: best_effort, depth: 5, deadline: 100}
          rate: {min: 5, max: 20}
        - name: /{robot}/status
          type: std_msgs/msg/String
          qos: {durability: transient_local, liveliness: automatic, lease_duration: 1000}
    - name: mapper
      image: registry.example.com/mapper:2.1
      launch: ros2 launch mapper mapper.launch.py
      preference: [edge, cloud]
      requirements: {max_latency: 30 ms}
      resources: {cpu: 2, memory: 2Gi, gpu: 1}
      strategy: shared
      robotsPerInstance: 3
      topics:
        subscribes:
        - {name: scan, type: sensor_msgs/msg/LaserScan, qos: {reliability: best_effort, deadline: 200}, rate: {min: 1}}
        - {name: "/{robot}/status", type: std_msgs/msg/String, qos: {durability: transient_local}}
        - {name: odom, type: nav_msgs/msg/Odometry, external: true}
    """
)
SPECS = Bases(
    "specs",
    [
        SPEC_BASE,
        EVERYTHING,
        _example("pick-and-place.yml"),
        _example("partner-cloud.yml"),
        _example("scaling.yml"),
        _example("two-fleets.yml"),
    ],
)


def _catalog_files() -> dict[str, str]:
    folder = os.path.join(ROOT, "inventories", "local", "catalog")
    files = {}
    for name in sorted(os.listdir(folder)):
        with open(os.path.join(folder, name), encoding="utf-8") as handle:
            files[name] = handle.read()
    return files


CATALOG_TEXTS = Bases("catalogs", [CATALOG_BASE, *_catalog_files().values()])
LOCAL_CATALOG = catalogs.load_catalog(os.path.join(ROOT, "inventories", "local", "catalog"), CATALOG)
CATALOG_SPECS = Bases("catalog specs", [_example("pick-and-place-catalog.yml")])
_LOCATION = re.compile(r"(?P<source>.+?)(?::(?P<line>\d+))?: ")


def spec_located(error: SpecError, sources=(SPEC,)) -> str:
    """'' when every problem names the file (or a document of it) and, when it names a field, that field's line."""
    if not isinstance(error, SpecError) or not error.problems:
        return "is not a list of problems"
    for problem in error.problems:
        if not problem.source.startswith(sources):
            return f"names {problem.source!r}, not the file ({problem})"
        if problem.path and problem.line is None:
            return f"names field {problem.path} without its line ({problem})"
    return ""


def load_spec(text: str, catalog=None):
    return spec.load_rosdeployments(text, SPEC, catalog)


@fuzz_settings(600)
@given(text=mutated(SPECS))
def test_a_mutated_spec_is_deployments_or_one_located_refusal(text):
    run_case("spec", lambda: load_spec(text), SpecError, spec_located, text)


@fuzz_settings(300)
@given(text=mutated(CATALOG_SPECS))
def test_a_mutated_spec_of_catalog_modules_is_deployments_or_one_located_refusal(text):
    run_case("spec-catalog", lambda: load_spec(text, LOCAL_CATALOG), SpecError, spec_located, text)


@fuzz_settings(300)
@given(text=mutated(CATALOG_TEXTS))
def test_a_mutated_catalog_file_is_a_catalog_or_one_located_refusal(text, tmp_path_factory):
    folder = tmp_path_factory.mktemp("catalog")
    (folder / "modules.yml").write_text(text, encoding="utf-8")

    def located(error):
        return spec_located(error, (f"{CATALOG}/modules.yml",))

    run_case("catalog", lambda: catalogs.load_catalog(str(folder), CATALOG), SpecError, located, text)


@fuzz_settings(400)
@given(text=raw_yaml)
def test_raw_text_is_deployments_or_one_located_refusal(text):
    run_case("spec-raw", lambda: load_spec(text), SpecError, spec_located, text)
