"""Bad input: every malformed spec, inventory or request fails with a clear, located error.

Each case is a row of a table: the input, the field path the error must name, substrings the
message must contain (the reason, the offending value, a "did you mean" hint) and, for specs,
the line. Every case asserts the exception type (``SpecError`` or ``PlacementError``, never a
``KeyError``, ``TypeError``, ``RecursionError`` ...) and that the rendered message names the
source, the path, the line and the reason.

Cases marked ``xfail(strict=True)`` document a defect of the code: the test says what the
behaviour should be, and starts passing (so must lose its mark) once the code is fixed.
"""

from __future__ import annotations

import copy

import pytest
from helpers import SPEC_BASE, yml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import errors, inventory, scheduler, spec, yaml_source

SOURCE = "specs/bad.yml"
INVENTORY_SOURCE = "inventories/bad"


def defect(reason: str):
    """A case the code gets wrong today; the test states the expected behaviour."""
    return pytest.mark.xfail(strict=True, reason=f"code defect: {reason}")


BASE = SPEC_BASE  # lines 1-7 of every spec built with ``module()``; extra module lines start at line 8


def module(*lines: str) -> str:
    """The base spec with ``lines`` added to its only module (first added line is line 8)."""
    return BASE + "".join(f"  {line}\n" for line in lines)


def metadata(*lines: str) -> str:
    """The base spec with ``lines`` added to metadata (first added line is line 4)."""
    head, tail = BASE.split("rosModules:\n", 1)
    return head + "".join(f"  {line}\n" for line in lines) + "rosModules:\n" + tail


def top(*lines: str) -> str:
    """The base spec with top-level ``lines`` appended (first added line is line 8)."""
    return BASE + "".join(f"{line}\n" for line in lines)


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    """The "billion laughs": each anchor refers ``width`` times to the one before."""
    text = 'lol0: &lol0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n'
    for level in range(1, levels + 1):
        refs = ", ".join([f"*lol{level - 1}"] * width)
        text += f"lol{level}: &lol{level} [{refs}]\n"
    return text


def case(case_id, text, path, contains, line=None, marks=()):
    return pytest.param(text, path, list(contains), line, id=case_id, marks=marks)


def assert_problem(exc: errors.SpecError, source: str, path: str | None, contains: list[str], line: int | None):
    """One problem of ``exc`` names ``source``, ``path`` and ``line`` and says every substring."""
    message = str(exc)
    assert source in message, message
    matching = [p for p in exc.problems if (path is None or p.path == path)]
    assert matching, f"no problem at path {path!r} in:\n{message}"
    complete = [p for p in matching if all(s in str(p) for s in contains) and source in p.source]
    assert complete, f"no problem at {path!r} says all of {contains} in:\n{message}"
    if line is not None:
        assert any(p.line == line for p in complete), f"no problem at {path!r} on line {line} in:\n{message}"
    problem = next(p for p in complete if line is None or p.line == line)
    assert str(problem) in message
    if path:
        assert f": {path}: " in str(problem)
    if line is not None:
        assert f"{problem.source}:{line}: " in str(problem)


# --------------------------------------------------------------------------------------------
# Malformed RosDeployment specs
# --------------------------------------------------------------------------------------------

SPEC_CASES = [
    # -- not a spec at all --------------------------------------------------------------------
    case("empty-file", "", "", ["no RosDeployment found", "empty"]),
    case("only-comments-and-empty-documents", "# nothing here\n---\n---\n", "", ["no RosDeployment found"]),
    case("tab-indentation", "metadata:\n\tname: demo\n", "", ["not valid YAML", "cannot start any token"], 2),
    case(
        "bad-indentation",
        "metadata:\n  name: demo\n targetFleet: test-fleet\nrosModules: []\n",
        "",
        ["not valid YAML"],
        3,
    ),
    case("unclosed-flow-mapping", "metadata: {name: demo\n", "", ["not valid YAML", "expected ',' or '}'"], 2),
    case(
        "top-level-list",
        "- name: planner\n- name: controller\n",
        "",
        ["(list) is not valid", "expected a mapping with metadata and rosModules"],
        1,
    ),
    case("top-level-scalar", "just some text\n", "", ["'just some text' is not valid", "expected a mapping"], 1),
    case("top-level-number", "42\n", "", ["42 (int) is not valid", "expected a mapping"], 1),
    case(
        "control-character",
        "metadata:\n  name: \x1f\n",
        "metadata.name",
        ["control character U+001F in column 9", "expected printable text"],
        2,
    ),
    case(
        "python-tag-is-not-constructed",
        "metadata: !!python/object/apply:os.system [echo hi]\n",
        "",
        ["not valid YAML", "could not determine a constructor"],
        1,
    ),
    # -- duplicate keys -----------------------------------------------------------------------
    case(
        "duplicate-key-in-metadata",
        metadata("name: other"),
        "metadata.name",
        ["duplicate key (first written on line 2)"],
        4,
    ),
    case(
        "duplicate-top-level-key",
        top("rosModules: []"),
        "rosModules",
        ["duplicate key (first written on line 4)"],
        8,
    ),
    case(
        "duplicate-key-in-module",
        module("image: registry/other:2.0"),
        "rosModules[0].image",
        ["duplicate key (first written on line 6)"],
        8,
    ),
    # -- unknown fields, at every level, with a hint ------------------------------------------
    case(
        "unknown-top-level-rosModule",
        BASE.replace("rosModules:", "rosModule:"),
        "rosModule",
        ["unknown field; did you mean 'rosModules'?", "allowed here:"],
    ),
    case(
        "unknown-field-line-is-the-key-line",
        BASE.replace("rosModules:", "rosModule:"),
        "rosModule",
        ["unknown field"],
        4,
    ),
    case(
        "missing-rosModules-when-misspelt",
        BASE.replace("rosModules:", "rosModule:"),
        "",
        ["missing required field 'rosModules'"],
        1,
    ),
    case(
        "unknown-top-level-apiversion",
        "apiversion: kuberos.io/v1alpha1\n" + BASE,
        "apiversion",
        ["unknown field; did you mean 'apiVersion'?"],
        1,
    ),
    case(
        "unknown-metadata-targetFleet-typo",
        BASE.replace("targetFleet:", "targetFlet:"),
        "metadata.targetFlet",
        ["unknown field; did you mean 'targetFleet'?", "allowed here: developer, labels, name, robotSelector, targetFleet"],
        3,
    ),
    case(
        "unknown-metadata-target_fleet",
        BASE.replace("targetFleet:", "target_fleet:"),
        "metadata.target_fleet",
        ["unknown field; did you mean 'targetFleet'?"],
        3,
    ),
    case(
        "unknown-module-prefrence",
        module("prefrence: cloud"),
        "rosModules[0].prefrence",
        ["unknown field; did you mean 'preference'?"],
        8,
    ),
    case(
        "unknown-requirements-maxLatency",
        module("requirements:", "  maxLatency: 20 ms"),
        "rosModules[0].requirements.maxLatency",
        ["unknown field; did you mean 'max_latency'?", "allowed here: arch, devices, max_latency, onboard"],
        9,
    ),
    case(
        "unknown-resources-memroy",
        module("resources: {cpu: 1, memroy: 1Gi}"),
        "rosModules[0].resources.memroy",
        ["unknown field; did you mean 'memory'?"],
        8,
    ),
    case(
        "unknown-discovery-server",
        top("discovery:", "  server: 3"),
        "discovery.server",
        ["unknown field; did you mean 'servers'?"],
        9,
    ),
    case(
        "unknown-robotSelector-robots",
        metadata("robotSelector:", "  robots: [fetch-1]"),
        "metadata.robotSelector.robots",
        ["unknown field; did you mean 'robot'?"],
        5,
    ),
    case(
        "non-string-top-level-key",
        top("1: one"),
        "1",
        ["unknown field"],
        8,
    ),
    case(
        "non-string-and-string-unknown-keys",
        top("1: one", "colour: blue"),
        "colour",
        ["unknown field"],
        9,
    ),
    # -- missing required fields --------------------------------------------------------------
    case(
        "missing-metadata",
        "rosModules:\n- name: planner\n  image: registry/planner:1.0\n  launch: ros2 run planner node\n",
        "",
        ["missing required field 'metadata'"],
        1,
    ),
    case(
        "missing-metadata-name",
        BASE.replace("  name: demo\n", ""),
        "metadata",
        ["missing required field 'name'"],
        1,
    ),
    case(
        "missing-targetFleet",
        BASE.replace("  targetFleet: test-fleet\n", ""),
        "metadata",
        ["missing required field 'targetFleet'"],
        1,
    ),
    case(
        "missing-module-name",
        BASE.replace("- name: planner\n  image:", "- image:"),
        "rosModules[0]",
        ["missing required field 'name'"],
        5,
    ),
    case(
        "missing-image",
        BASE.replace("  image: registry/planner:1.0\n", ""),
        "rosModules[0]",
        ["missing required field 'image'"],
        5,
    ),
    case(
        "missing-launch",
        BASE.replace("  launch: ros2 launch planner planner.launch.py\n", ""),
        "rosModules[0]",
        ["missing required field 'launch'"],
        5,
    ),
    case(
        "metadata-null",
        "metadata:\nrosModules:\n- name: planner\n  image: registry/planner:1.0\n  launch: ros2 run planner node\n",
        "metadata",
        ["None (NoneType) is not valid", "expected a mapping with name and targetFleet"],
    ),
    # -- wrong types --------------------------------------------------------------------------
    case(
        "launch-as-number",
        BASE.replace("launch: ros2 launch planner planner.launch.py", "launch: 42"),
        "rosModules[0].launch",
        ["42 (int) is not valid", "expected a command line or a non-empty list of command lines"],
        7,
    ),
    case(
        "launch-empty-list",
        BASE.replace("launch: ros2 launch planner planner.launch.py", "launch: []"),
        "rosModules[0].launch",
        ["[] (list) is not valid", "non-empty list of command lines"],
        7,
    ),
    case(
        "image-as-list",
        BASE.replace("image: registry/planner:1.0", "image: [registry/planner, '1.0']"),
        "rosModules[0].image",
        ["(list) is not valid", "expected a container image reference"],
        6,
    ),
    case(
        "image-with-space",
        BASE.replace("image: registry/planner:1.0", "image: registry/planner 1.0"),
        "rosModules[0].image",
        ["'registry/planner 1.0' is not valid", "without spaces"],
        6,
    ),
    case(
        "onboard-maybe",
        module("requirements:", "  onboard: maybe"),
        "rosModules[0].requirements.onboard",
        ["'maybe' is not valid", "expected true or false"],
        9,
    ),
    case(
        "rosDomainId-999",
        top("rosDomainId: 999"),
        "rosDomainId",
        ["999 (int) is not valid", "expected an integer from 0 to 232"],
        8,
    ),
    case(
        "rosDomainId-string",
        top("rosDomainId: seven"),
        "rosDomainId",
        ["'seven' is not valid", "expected an integer from 0 to 232"],
        8,
    ),
    case(
        "discovery-servers-0",
        top("discovery:", "  servers: 0"),
        "discovery.servers",
        ["0 (int) is not valid", "expected an integer from 1 to 8"],
        9,
    ),
    case(
        "discovery-port-privileged",
        top("discovery: {port: 80}"),
        "discovery.port",
        ["80 (int) is not valid", "expected a port number from 1024 to 65535"],
        8,
    ),
    case(
        "apiVersion-wrong",
        "apiVersion: kuberos.io/v1\n" + BASE,
        "apiVersion",
        ["'kuberos.io/v1' is not valid", "expected 'kuberos.io/v1alpha1'"],
        1,
    ),
    case(
        "kind-wrong",
        "kind: Deployment\n" + BASE,
        "kind",
        ["'Deployment' is not valid", "expected 'RosDeployment'"],
        1,
    ),
    case(
        "rosModules-empty",
        "metadata: {name: demo, targetFleet: test-fleet}\nrosModules: []\n",
        "rosModules",
        ["[] (list) is not valid", "expected a non-empty list of at most 100 modules"],
        2,
    ),
    case(
        "rosModules-mapping",
        "metadata: {name: demo, targetFleet: test-fleet}\nrosModules:\n  planner: {image: x, launch: y}\n",
        "rosModules",
        ["(dict) is not valid", "expected a non-empty list of at most 100 modules"],
        2,
    ),
    case(
        "module-as-string",
        "metadata: {name: demo, targetFleet: test-fleet}\nrosModules:\n- planner\n",
        "rosModules[0]",
        ["'planner' is not valid", "expected a mapping with name, image and launch"],
        3,
    ),
    case(
        "strategy-unknown",
        module("strategy: exclusive"),
        "rosModules[0].strategy",
        ["'exclusive' is not valid", "expected dedicated or shared"],
        8,
    ),
    case(
        "devices-as-string",
        module("requirements: {devices: camera}"),
        "rosModules[0].requirements.devices",
        ["'camera' is not valid", "expected a list of distinct device names"],
        8,
    ),
    case(
        "env-value-list",
        module("env: {LOG_LEVEL: [info, debug]}"),
        "rosModules[0].env.LOG_LEVEL",
        ["(list) is not valid", "expected a string, number or boolean"],
        8,
    ),
    case(
        "rosParameters-list",
        module("rosParameters: [voxel_size]"),
        "rosModules[0].rosParameters",
        ["(list) is not valid", "expected a mapping of parameter names to values"],
        8,
    ),
    case(
        "robotSelector-empty",
        metadata("robotSelector: {robot: []}"),
        "metadata.robotSelector.robot",
        ["[] (list) is not valid", "a non-empty list of distinct robot names"],
        4,
    ),
    case(
        "robotSelector-repeats",
        metadata("robotSelector: {robot: [fetch-1, fetch-1]}"),
        "metadata.robotSelector.robot",
        ["has repeated entries", "distinct robot names"],
        4,
    ),
    case(
        "label-value-not-string",
        metadata("labels: {team: 5}"),
        "metadata.labels.team",
        ["5 (int) is not valid", "expected a label value"],
        4,
    ),
    case(
        "label-key-invalid",
        metadata("labels: {'Bad Key!': demo}"),
        "metadata.labels.Bad Key!",
        ["'Bad Key!'", "label"],
        4,
    ),
    case(
        "label-value-invalid",
        metadata("labels: {team: 'not ok!'}"),
        "metadata.labels.team",
        ["'not ok!'", "label"],
        4,
    ),
    # -- bad units ----------------------------------------------------------------------------
    case(
        "max_latency-parsecs",
        module("requirements:", "  max_latency: 200 parsecs"),
        "rosModules[0].requirements.max_latency",
        ["'200 parsecs' is not valid", "expected a latency such as '200 ms'"],
        9,
    ),
    case(
        "cpu-four",
        module("resources:", "  cpu: four"),
        "rosModules[0].resources.cpu",
        ["'four' is not valid", "expected a CPU quantity such as 2, 0.5 or '500m'"],
        9,
    ),
    case(
        "memory-lots",
        module("resources:", "  memory: lots"),
        "rosModules[0].resources.memory",
        ["'lots' is not valid", "expected a memory quantity such as '512Mi'"],
        9,
    ),
    case(
        "memory-zero",
        module("resources: {memory: 0Mi}"),
        "rosModules[0].resources.memory",
        ["must be more than zero"],
        8,
    ),
    case(
        "gpu-two",
        module("resources: {gpu: two}"),
        "rosModules[0].resources.gpu",
        ["'two' is not valid", "expected a whole number of GPUs from 0 to 16"],
        8,
    ),
    case(
        "cpu-infinite",
        module("resources: {cpu: .inf}"),
        "rosModules[0].resources.cpu",
        ["inf (float) is not valid", "expected a CPU quantity"],
        8,
    ),
    case(
        "max_latency-nan",
        module("requirements: {max_latency: .nan}"),
        "rosModules[0].requirements.max_latency",
        ["nan (float) is not valid", "expected a latency"],
        8,
    ),
    # -- negative values ----------------------------------------------------------------------
    case(
        "cpu-negative",
        module("resources: {cpu: -1}"),
        "rosModules[0].resources.cpu",
        ["-1 (int) is not valid", "expected a CPU quantity"],
        8,
    ),
    case(
        "memory-negative",
        module("resources: {memory: -512Mi}"),
        "rosModules[0].resources.memory",
        ["'-512Mi' is not valid", "expected a memory quantity"],
        8,
    ),
    case(
        "gpu-negative",
        module("resources: {gpu: -1}"),
        "rosModules[0].resources.gpu",
        ["-1 (int) is not valid", "from 0 to 16"],
        8,
    ),
    case(
        "max_latency-negative",
        module("requirements: {max_latency: -5}"),
        "rosModules[0].requirements.max_latency",
        ["-5 (int) is not valid", "expected a latency"],
        8,
    ),
    case(
        "rosDomainId-negative",
        top("rosDomainId: -1"),
        "rosDomainId",
        ["-1 (int) is not valid", "from 0 to 232"],
        8,
    ),
    case(
        "robotsPerInstance-zero",
        module("strategy: shared", "robotsPerInstance: 0"),
        "rosModules[0].robotsPerInstance",
        ["0 (int) is not valid", "a whole number from 1 to 1000"],
        9,
    ),
    # -- names --------------------------------------------------------------------------------
    case(
        "module-name-uppercase",
        BASE.replace("- name: planner", "- name: Planner"),
        "rosModules[0].name",
        ["'Planner' is not valid", "lowercase letters, digits and '-'"],
        5,
    ),
    case(
        "module-name-underscore",
        BASE.replace("- name: planner", "- name: motion_planner"),
        "rosModules[0].name",
        ["'motion_planner' is not valid", "lowercase letters, digits and '-'"],
        5,
    ),
    case(
        "module-name-too-long",
        BASE.replace("- name: planner", "- name: " + "a" * 41),
        "rosModules[0].name",
        ["'aaaa", "at most 40"],
        5,
    ),
    case(
        "module-name-leading-dash",
        BASE.replace("- name: planner", "- name: '-planner'"),
        "rosModules[0].name",
        ["'-planner' is not valid"],
        5,
    ),
    case(
        "deployment-name-uppercase",
        BASE.replace("name: demo", "name: Demo"),
        "metadata.name",
        ["'Demo' is not valid", "at most 40 lowercase letters"],
        2,
    ),
    case(
        "targetFleet-empty",
        BASE.replace("targetFleet: test-fleet", "targetFleet: ''"),
        "metadata.targetFleet",
        ["'' is not valid", "expected the name of a fleet in the inventory"],
        3,
    ),
    case(
        "duplicate-module-names",
        BASE + "- name: planner\n  image: registry/other:1.0\n  launch: ros2 run other node\n",
        "rosModules[1].name",
        ["'planner' is already the name of rosModules[0]", "expected a unique module name"],
        8,
    ),
    # -- preference and strategy --------------------------------------------------------------
    case(
        "preference-not-a-tier",
        module("preference: fog"),
        "rosModules[0].preference",
        ["'fog' is not valid", "one of onboard, edge, cloud"],
        8,
    ),
    case(
        "preference-list-with-unknown-tier",
        module("preference: [edge, fog]"),
        "rosModules[0].preference",
        ["['edge', 'fog'] (list) is not valid", "one of onboard, edge, cloud"],
        8,
    ),
    case(
        "preference-list-with-repeats",
        module("preference: [edge, cloud, edge]"),
        "rosModules[0].preference",
        ["['edge', 'cloud', 'edge'] (list) is not valid", "without repeats"],
        8,
    ),
    case(
        "onboard-true-with-preference-cloud",
        module("preference: cloud", "requirements:", "  onboard: true"),
        "rosModules[0].preference",
        ["'cloud' contradicts requirements.onboard: true", "expected preference onboard"],
        8,
    ),
    case(
        "onboard-true-with-preference-list-not-starting-onboard",
        module("preference: [cloud, onboard]", "requirements: {onboard: true}"),
        "rosModules[0].preference",
        ["contradicts requirements.onboard: true"],
        8,
    ),
    case(
        "strategy-shared-with-onboard",
        module("strategy: shared", "requirements: {onboard: true}"),
        "rosModules[0].strategy",
        ["'shared' cannot run onboard", "strategy dedicated"],
        8,
    ),
    case(
        "strategy-shared-with-preference-onboard",
        module("strategy: shared", "preference: onboard"),
        "rosModules[0].strategy",
        ["'shared' cannot run onboard"],
        8,
    ),
    case(
        "robotsPerInstance-without-shared",
        module("robotsPerInstance: 4"),
        "rosModules[0].robotsPerInstance",
        ["only applies with strategy: shared"],
        8,
    ),
    # -- environment --------------------------------------------------------------------------
    case(
        "env-reserved-ROS_DISCOVERY_SERVER",
        module("env:", "  ROS_DISCOVERY_SERVER: 10.0.0.1:11811"),
        "rosModules[0].env.ROS_DISCOVERY_SERVER",
        ["is set by KubeROS", "remove it"],
        9,
    ),
    case(
        "env-reserved-ROS_DOMAIN_ID",
        module("env: {ROS_DOMAIN_ID: 3}"),
        "rosModules[0].env.ROS_DOMAIN_ID",
        ["is set by KubeROS", "rosDomainId"],
        8,
    ),
    case(
        "env-KUBEROS-prefix",
        module("env:", "  KUBEROS_TOKEN: secret"),
        "rosModules[0].env.KUBEROS_TOKEN",
        ["names starting with KUBEROS_ are reserved"],
        9,
    ),
    case(
        "env-name-with-dash",
        module("env: {MY-VAR: x}"),
        "rosModules[0].env.MY-VAR",
        ["'MY-VAR' is not a valid name", "expected an environment variable name of letters, digits and '_'"],
        8,
    ),
    case(
        "env-name-starting-with-digit",
        module("env: {1BAD: x}"),
        "rosModules[0].env.1BAD",
        ["'1BAD' is not a valid name", "not starting with a digit"],
        8,
    ),
    case(
        "env-name-integer-key",
        module("env: {1: x}"),
        "rosModules[0].env.1",
        ["1 (int) is not a valid name", "environment variable name"],
        8,
    ),
    case(
        "env-name-null-key",
        module("env: {null: x}"),
        "rosModules[0].env.None",
        ["None (NoneType) is not a valid name", "environment variable name"],
        8,
    ),
    # -- launch command lines -----------------------------------------------------------------
    case(
        "launch-unbalanced-quote",
        BASE.replace(
            "launch: ros2 launch planner planner.launch.py",
            'launch: "ros2 run planner node --ros-args -p name:=\'x"',
        ),
        "rosModules[0].launch",
        ["is not a valid command line (No closing quotation)", "expected e.g. 'ros2 launch pkg file.launch.py'"],
        7,
    ),
    case(
        "launch-list-second-line-unbalanced",
        BASE.replace(
            "  launch: ros2 launch planner planner.launch.py\n",
            '  launch:\n  - ros2 run planner node\n  - "ros2 run planner helper \'oops"\n',
        ),
        "rosModules[0].launch[1]",
        ["No closing quotation"],
        9,
    ),
    case(
        "launch-whitespace-only",
        BASE.replace("launch: ros2 launch planner planner.launch.py", "launch: '   '"),
        "rosModules[0].launch",
        ["is not a valid command line (empty command)"],
        7,
    ),
    # -- hostile documents --------------------------------------------------------------------
    case("alias-bomb", alias_bomb(), "", ["document too large", "YAML nodes"]),
    case("self-referencing-alias", "metadata: &loop [*loop]\n", "", ["document too large", "nested deeper than 64 levels"]),
    case(
        "deep-flow-nesting-5000",
        "[" * 5000 + "]" * 5000 + "\n",
        "",
        ["document too large", "nested deeper than 64 levels"],
    ),
    case(
        "deep-block-nesting-200",
        "".join("  " * i + "a:\n" for i in range(200)) + "  " * 200 + "leaf\n",
        "",
        ["document too large", "nested deeper than 64 levels"],
    ),
    case("larger-than-1MiB", "# " + "x" * (1024 * 1024 + 10) + "\n" + BASE, "", ["file is larger than 1048576 bytes"]),
    # -- several documents --------------------------------------------------------------------
    case(
        "document-2-bad",
        BASE
        + "---\n"
        + BASE.replace("name: demo", "name: second").replace("launch: ros2 launch planner planner.launch.py", "launch: 7"),
        "rosModules[0].launch",
        [f"{SOURCE} (document 2)", "7 (int) is not valid"],
        15,
    ),
    case(
        "duplicate-deployment-names-across-documents",
        BASE + "---\n" + BASE,
        "metadata.name",
        [f"{SOURCE} (document 2)", f"'demo' is already used by {SOURCE} (document 1)", "expected a unique name"],
        10,
    ),
    case(
        "yaml-error-in-document-2",
        BASE + "---\nmetadata: [\n",
        "",
        ["not valid YAML"],
        10,
    ),
]


@pytest.mark.parametrize(("text", "path", "contains", "line"), SPEC_CASES)
def test_bad_spec(text, path, contains, line):
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments(text, SOURCE)
    assert_problem(info.value, SOURCE, path, contains, line)


def test_alias_bomb_is_refused_before_anything_is_constructed(monkeypatch):
    """Deterministic stand-in for "fails fast" (the time it takes is measured by bench/bench_refusal.py)."""
    constructed = []

    class RecordingLoader(yaml_source.LOADER):
        def construct_document(self, node):
            constructed.append(node)
            return super().construct_document(node)

    monkeypatch.setattr(yaml_source, "LOADER", RecordingLoader)
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments(alias_bomb(), SOURCE)
    assert "too large" in str(info.value)
    assert SOURCE in str(info.value)
    assert constructed == []


def test_deep_nesting_stops_soon_after_the_depth_limit(monkeypatch):
    """Deterministic stand-in for "fails fast": count the YAML tokens read before giving up (libyaml's composer
    would overflow the C stack on deep nesting, so the depth is checked on the tokens first)."""
    consumed = []

    class CountingLoader(yaml_source.LOADER):
        def get_token(self):
            consumed.append(1)
            return super().get_token()

    monkeypatch.setattr(yaml_source, "LOADER", CountingLoader)
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments("[" * 200_000 + "]" * 200_000, SOURCE)
    assert "too large" in str(info.value)
    assert yaml_source.MAX_DEPTH < len(consumed) <= 2 * yaml_source.MAX_DEPTH + 10, f"read {len(consumed)} tokens"


def test_all_problems_of_one_spec_at_once():
    text = yml(
        """
        metadata:
          name: Demo
          targetFleet: test-fleet
          prefrence: cloud
        rosDomainId: 999
        rosModules:
        - name: planner
          image: registry/planner:1.0
          launch: ros2 launch planner planner.launch.py
          resources: {cpu: four}
        - name: controller
          image: registry/controller:1.0
          launch: "ros2 run controller node 'oops"
          env: {ROS_DISCOVERY_SERVER: x}
          robotsPerInstance: 2
        - name: controller
          image: [registry/other]
          launch: ros2 run other node
        """
    )
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments(text, SOURCE)
    exc = info.value
    expected = [
        ("metadata.name", ["'Demo' is not valid"], 2),
        ("metadata.prefrence", ["unknown field"], 4),
        ("rosDomainId", ["999 (int) is not valid"], 5),
        ("rosModules[0].resources.cpu", ["'four' is not valid"], 10),
        ("rosModules[1].launch", ["No closing quotation"], 13),
        ("rosModules[1].env.ROS_DISCOVERY_SERVER", ["is set by KubeROS"], 14),
        ("rosModules[1].robotsPerInstance", ["only applies with strategy: shared"], 15),
        ("rosModules[2].image", ["(list) is not valid"], 17),
    ]
    for path, contains, line in expected:
        assert_problem(exc, SOURCE, path, contains, line)
    assert len(exc.problems) >= len(expected)
    assert f"({len(exc.problems)} problems)" in str(exc)


def test_all_problems_of_all_documents_at_once():
    bad_one = BASE.replace("name: demo", "name: one").replace("image: registry/planner:1.0", "image: [x]")
    good = BASE.replace("name: demo", "name: two")
    bad_three = BASE.replace("name: demo", "name: three").replace("targetFleet: test-fleet", "targetFlet: test-fleet")
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments(bad_one + "---\n" + good + "---\n" + bad_three, SOURCE)
    assert_problem(info.value, f"{SOURCE} (document 1)", "rosModules[0].image", ["(list) is not valid"], 6)
    assert_problem(info.value, f"{SOURCE} (document 3)", "metadata.targetFlet", ["did you mean 'targetFleet'?"], 19)
    assert not any("(document 2)" in p.source for p in info.value.problems)


def test_all_invalid_env_names_are_reported():
    text = module("env: {MY-VAR: x, 1BAD: y, GOOD: z}")
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployments(text, SOURCE)
    message = str(info.value)
    assert "'MY-VAR'" in message
    assert "'1BAD'" in message
    assert "'GOOD'" not in message


# -- floats where integers are expected --------------------------------------------------------
# JSON Schema counts 2.0 as an integer. The spec must either reject such a value with a located
# SpecError or normalise it to an int; it must never reach the scheduler or the manifests as a
# float (range(2.0) raises TypeError; ROS_DOMAIN_ID would be rendered "3.0").

FLOAT_CASES = [
    pytest.param(
        top("discovery: {servers: 2.0}"),
        "discovery.servers",
        lambda dep: dep.discovery_servers,
        8,
        id="discovery-servers-2.0",
    ),
    pytest.param(
        top("rosDomainId: 3.0"),
        "rosDomainId",
        lambda dep: dep.ros_domain_id,
        8,
        id="rosDomainId-3.0",
    ),
    pytest.param(
        top("discovery: {port: 11811.0}"),
        "discovery.port",
        lambda dep: dep.discovery_port,
        8,
        id="discovery-port-float",
    ),
    pytest.param(
        module("strategy: shared", "robotsPerInstance: 2.0"),
        "rosModules[0].robotsPerInstance",
        lambda dep: dep.modules[0].robots_per_instance,
        9,
        id="robotsPerInstance-2.0",
    ),
]


@pytest.mark.parametrize(("text", "path", "getter", "line"), FLOAT_CASES)
def test_integral_float_is_rejected_or_normalised(text, path, getter, line, inventory_model):
    try:
        deployments = spec.load_rosdeployments(text, SOURCE)
    except errors.SpecError as exc:
        assert_problem(exc, SOURCE, path, ["is not valid"], line)
        return
    value = getter(deployments[0])
    assert type(value) is int, f"{path} is {value!r} ({type(value).__name__})"
    scheduler.place_modules(deployments, inventory_model)


# -- files --------------------------------------------------------------------------------------


def test_non_utf8_file(tmp_path):
    data = b"metadata:\n  name: d\xe9mo\n  targetFleet: test-fleet\n"
    path = tmp_path / "latin1.yml"
    path.write_bytes(data)
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(path))
    offset = data.index(b"\xe9")
    assert_problem(info.value, str(path), "", [f"not UTF-8 text (byte {offset})"], None)


def test_utf16_file(tmp_path):
    path = tmp_path / "utf16.yml"
    path.write_bytes(BASE.encode("utf-16"))
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(path), display="specs/utf16.yml")
    assert_problem(info.value, "specs/utf16.yml", "", ["not UTF-8 text (byte 0)"], None)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.yml"
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(path))
    assert_problem(info.value, str(path), "", ["cannot read the file", "No such file or directory"], None)


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(tmp_path), display="specs/")
    assert_problem(info.value, "specs/", "", ["cannot read the file", "Is a directory"], None)


def test_bad_document_in_file_names_the_file_and_line(tmp_path):
    path = tmp_path / "two.yml"
    path.write_text(BASE + "---\n" + BASE.replace("name: demo", "name: two").replace("- name: planner", "- name: Planner"))
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(path), display="specs/two.yml")
    assert_problem(info.value, "specs/two.yml (document 2)", "rosModules[0].name", ["'Planner' is not valid"], 13)


# --------------------------------------------------------------------------------------------
# Malformed inventories
# --------------------------------------------------------------------------------------------

_ROBOT = {"kuberos_cpu": 4, "kuberos_memory": "8Gi", "kuberos_gpu": 0, "kuberos_arch": "amd64"}
_EDGE = {"kuberos_cpu": 16, "kuberos_memory": "32Gi", "kuberos_resource_group": "site-a"}
_CLOUD = {"kuberos_cpu": 32, "kuberos_memory": "64Gi", "kuberos_gpu": 1, "kuberos_resource_group": "cloud-eu"}

# The plain-data form of inventories/local (what the fleet_inventory filter produces).
GOOD_INVENTORY = {
    "hosts": {
        "fetch-1": {
            **_ROBOT,
            "kuberos_fleet": "test-fleet",
            "kuberos_devices": ["camera", "gripper"],
            "kuberos_link_latency_ms": {"cloud-2": 180},
        },
        "fetch-2": {**_ROBOT, "kuberos_fleet": "test-fleet", "kuberos_devices": ["camera", "gripper"]},
        "tiago-1": {**_ROBOT, "kuberos_fleet": "warehouse-fleet", "kuberos_devices": ["camera", "lidar"]},
        "tiago-2": {
            **_ROBOT,
            "kuberos_fleet": "warehouse-fleet",
            "kuberos_devices": ["camera", "lidar"],
            "kuberos_arch": "arm64",
        },
        "edge-1": dict(_EDGE),
        "edge-2": dict(_EDGE),
        "edge-3": {**_EDGE, "kuberos_fleets": ["warehouse-fleet"], "kuberos_latency_ms": 3},
        "cloud-1": dict(_CLOUD),
        "cloud-2": {**_CLOUD, "kuberos_latency_ms": 60},
    },
    "groups": {
        "robots": ["fetch-1", "fetch-2", "tiago-1", "tiago-2"],
        "edge": ["edge-1", "edge-2", "edge-3"],
        "cloud": ["cloud-1", "cloud-2"],
    },
    "default_latency_ms": {"onboard": 0, "edge": 5, "cloud": 40},
}

_DROP = object()


def inv(hosts: dict | None = None, groups: dict | None = None, **top_level):
    """GOOD_INVENTORY with host variables set (``_DROP`` deletes one), groups or top-level keys replaced."""
    raw = copy.deepcopy(GOOD_INVENTORY)
    for host, variables in (hosts or {}).items():
        if not isinstance(variables, dict):
            raw["hosts"][host] = variables
            continue
        target = raw["hosts"].setdefault(host, {})
        for key, value in variables.items():
            if value is _DROP:
                target.pop(key, None)
            else:
                target[key] = value
    raw["groups"].update(groups or {})
    raw.update(top_level)
    return raw


def inv_case(case_id, raw, path, contains, marks=()):
    return pytest.param(raw, path, list(contains), id=case_id, marks=marks)


INVENTORY_CASES = [
    inv_case(
        "missing-kuberos_cpu",
        inv(hosts={"fetch-1": {"kuberos_cpu": _DROP}}),
        "hosts.fetch-1.kuberos_cpu",
        ["is required", "expected a CPU quantity such as 2, 0.5 or '500m'"],
    ),
    inv_case(
        "missing-kuberos_memory",
        inv(hosts={"edge-2": {"kuberos_memory": _DROP}}),
        "hosts.edge-2.kuberos_memory",
        ["is required", "expected a memory quantity"],
    ),
    inv_case(
        "cpu-four",
        inv(hosts={"edge-1": {"kuberos_cpu": "four"}}),
        "hosts.edge-1.kuberos_cpu",
        ["'four' is not valid", "expected a CPU quantity"],
    ),
    inv_case(
        "cpu-negative",
        inv(hosts={"edge-1": {"kuberos_cpu": -2}}),
        "hosts.edge-1.kuberos_cpu",
        ["-2 (int) is not valid", "expected a CPU quantity"],
    ),
    inv_case(
        "cpu-bool",
        inv(hosts={"edge-1": {"kuberos_cpu": True}}),
        "hosts.edge-1.kuberos_cpu",
        ["True (bool) is not valid"],
    ),
    inv_case(
        "memory-lots",
        inv(hosts={"cloud-1": {"kuberos_memory": "lots"}}),
        "hosts.cloud-1.kuberos_memory",
        ["'lots' is not valid", "expected a memory quantity such as '512Mi'"],
    ),
    inv_case(
        "memory-wrong-unit",
        inv(hosts={"cloud-1": {"kuberos_memory": "64GB"}}),
        "hosts.cloud-1.kuberos_memory",
        ["'64GB' is not valid", "expected a memory quantity"],
    ),
    inv_case(
        "robot-without-fleet",
        inv(hosts={"fetch-2": {"kuberos_fleet": _DROP}}),
        "hosts.fetch-2.kuberos_fleet",
        ["is required for a robot", "expected the name of its fleet"],
    ),
    inv_case(
        "fleet-not-a-name",
        inv(hosts={"fetch-2": {"kuberos_fleet": "Test Fleet"}}),
        "hosts.fetch-2.kuberos_fleet",
        ["'Test Fleet' is not valid", "fleet name"],
    ),
    inv_case(
        "host-in-two-tier-groups",
        inv(groups={"edge": ["edge-1", "edge-2", "edge-3", "fetch-1"]}),
        "hosts.fetch-1",
        ["is in groups robots, edge", "expected exactly one of robots, edge, cloud"],
    ),
    inv_case(
        "duplicate-robot-names",
        inv(hosts={"fetch-2": {"kuberos_robot": "fetch-1"}}),
        "hosts.fetch-2.kuberos_robot",
        ["'fetch-1' names another robot already", "expected unique robot names"],
    ),
    inv_case(
        "duplicate-node-names",
        inv(hosts={"edge-2": {"kuberos_node_name": "edge-1"}}),
        "hosts.edge-2.kuberos_node_name",
        ["'edge-1' is already the node name of another host", "expected unique node names"],
    ),
    inv_case(
        "invalid-node-name",
        inv(hosts={"edge-2": {"kuberos_node_name": "Edge_2"}}),
        "hosts.edge-2.kuberos_node_name",
        ["'Edge_2' is not valid", "node name"],
    ),
    inv_case(
        "link-latency-to-unknown-node",
        inv(hosts={"fetch-1": {"kuberos_link_latency_ms": {"cloud-3": 20}}}),
        "hosts.fetch-1.kuberos_link_latency_ms.cloud-3",
        ["is not a host or node in the inventory", "did you mean 'cloud-"],
    ),
    inv_case(
        "link-latency-typo",
        inv(hosts={"fetch-1": {"kuberos_link_latency_ms": {"edg-2": 20}}}),
        "hosts.fetch-1.kuberos_link_latency_ms.edg-2",
        ["is not a host or node in the inventory; did you mean 'edge-2'?"],
    ),
    inv_case(
        "link-latency-bad-value",
        inv(hosts={"fetch-1": {"kuberos_link_latency_ms": {"cloud-2": "fast"}}}),
        "hosts.fetch-1.kuberos_link_latency_ms.cloud-2",
        ["'fast' is not valid", "expected a latency such as '200 ms'"],
    ),
    inv_case(
        "link-latency-negative",
        inv(hosts={"fetch-1": {"kuberos_link_latency_ms": {"cloud-2": -1}}}),
        "hosts.fetch-1.kuberos_link_latency_ms.cloud-2",
        ["-1 (int) is not valid", "expected a latency"],
    ),
    inv_case(
        "link-latency-not-a-mapping",
        inv(hosts={"fetch-1": {"kuberos_link_latency_ms": ["cloud-2", 180]}}),
        "hosts.fetch-1.kuberos_link_latency_ms",
        ["(list) is not valid", "expected a mapping of node names to latencies"],
    ),
    inv_case(
        "edge-latency-bad-value",
        inv(hosts={"edge-3": {"kuberos_latency_ms": "3 parsecs"}}),
        "hosts.edge-3.kuberos_latency_ms",
        ["'3 parsecs' is not valid", "expected a latency"],
    ),
    inv_case(
        "fleets-names-unknown-fleet",
        inv(hosts={"edge-3": {"kuberos_fleets": ["warehouse-flet"]}}),
        "hosts.edge-3.kuberos_fleets",
        ["'warehouse-flet' is not a fleet of any robot", "did you mean 'warehouse-fleet'?"],
    ),
    inv_case(
        "fleets-not-a-list-of-names",
        inv(hosts={"edge-3": {"kuberos_fleets": {"warehouse-fleet": True}}}),
        "hosts.edge-3.kuberos_fleets",
        ["is not valid", "expected a list of names"],
    ),
    inv_case(
        "gpu-negative",
        inv(hosts={"cloud-1": {"kuberos_gpu": -1}}),
        "hosts.cloud-1.kuberos_gpu",
        ["-1 (int) is not valid", "expected a whole number >= 0"],
    ),
    inv_case(
        "gpu-string",
        inv(hosts={"cloud-1": {"kuberos_gpu": "two"}}),
        "hosts.cloud-1.kuberos_gpu",
        ["'two' is not valid", "expected a whole number >= 0"],
    ),
    inv_case(
        "gpu-fraction",
        inv(hosts={"cloud-1": {"kuberos_gpu": 0.5}}),
        "hosts.cloud-1.kuberos_gpu",
        ["0.5 (float) is not valid", "expected a whole number >= 0"],
    ),
    inv_case(
        "pods-negative",
        inv(hosts={"edge-1": {"kuberos_pods": -10}}),
        "hosts.edge-1.kuberos_pods",
        ["-10 (int) is not valid"],
    ),
    inv_case(
        "arch-invalid",
        inv(hosts={"tiago-2": {"kuberos_arch": "arm 64"}}),
        "hosts.tiago-2.kuberos_arch",
        ["'arm 64' is not valid", "expected e.g. amd64 or arm64"],
    ),
    inv_case(
        "device-invalid",
        inv(hosts={"tiago-1": {"kuberos_devices": ["Lidar!"]}}),
        "hosts.tiago-1.kuberos_devices",
        ["'Lidar!' is not valid", "device names"],
    ),
    inv_case(
        "shared-not-bool",
        inv(hosts={"edge-1": {"kuberos_shared": "yes"}}),
        "hosts.edge-1.kuberos_shared",
        ["'yes' is not valid", "expected true or false"],
    ),
    inv_case(
        "resource-group-invalid",
        inv(hosts={"edge-1": {"kuberos_resource_group": "site a"}}),
        "hosts.edge-1.kuberos_resource_group",
        ["'site a' is not valid"],
    ),
    inv_case(
        "default-latency-unknown-tier",
        inv(default_latency_ms={"egde": 5}),
        "kuberos_default_latency_ms.egde",
        ["unknown tier; did you mean 'edge'?", "expected onboard, edge or cloud"],
    ),
    inv_case(
        "default-latency-bad-value",
        inv(default_latency_ms={"cloud": "slow"}),
        "kuberos_default_latency_ms.cloud",
        ["'slow' is not valid", "expected a latency"],
    ),
    inv_case(
        "no-hosts-at-all",
        {"hosts": {}, "groups": {"robots": [], "edge": [], "cloud": []}},
        "groups",
        ["no hosts in the groups robots, edge or cloud", "expected at least one robot"],
    ),
    inv_case("empty-mapping", {}, "groups", ["no hosts in the groups robots, edge or cloud"]),
    inv_case(
        "inventory-is-a-list",
        ["fetch-1", "edge-1"],
        "",
        ["(list) is not an inventory", "expected a mapping with hosts and groups"],
    ),
    inv_case("inventory-is-none", None, "", ["None (NoneType) is not an inventory"]),
    inv_case("inventory-is-a-string", "inventories/local", "", ["'inventories/local' is not an inventory"]),
    inv_case(
        "host-vars-not-a-mapping",
        inv(hosts={"fetch-1": "kuberos_cpu=4"}),
        "hosts.fetch-1",
        ["'kuberos_cpu=4' is not valid", "mapping"],
    ),
    inv_case(
        "hosts-not-a-mapping",
        {**copy.deepcopy(GOOD_INVENTORY), "hosts": ["fetch-1"]},
        "hosts",
        ["(list) is not valid", "mapping"],
    ),
    inv_case(
        "groups-not-a-mapping",
        {**copy.deepcopy(GOOD_INVENTORY), "groups": ["robots", "edge"]},
        "groups",
        ["(list) is not valid", "mapping"],
    ),
    inv_case(
        "group-members-a-string",
        inv(groups={"edge": "edge-1"}),
        "groups.edge",
        ["'edge-1' is not valid", "list of host names"],
    ),
    inv_case(
        "group-member-not-a-string",
        inv(groups={"edge": ["edge-1", None]}),
        "groups.edge[1]",
        ["None (NoneType) is not valid", "host name"],
    ),
    inv_case(
        "default-latency-not-a-mapping",
        inv(default_latency_ms=5),
        "kuberos_default_latency_ms",
        ["5 (int) is not valid", "mapping"],
    ),
]


@pytest.mark.parametrize(("raw", "path", "contains"), INVENTORY_CASES)
def test_bad_inventory(raw, path, contains):
    with pytest.raises(errors.SpecError) as info:
        inventory.load_inventory(raw, INVENTORY_SOURCE)
    assert_problem(info.value, INVENTORY_SOURCE, path, contains, None)


def test_good_inventory_is_valid():
    """The baseline the bad inventories are derived from must itself be valid."""
    model = inventory.load_inventory(copy.deepcopy(GOOD_INVENTORY), INVENTORY_SOURCE)
    assert set(model.fleets) == {"test-fleet", "warehouse-fleet"}


def test_all_inventory_problems_at_once():
    raw = inv(
        hosts={
            "fetch-1": {"kuberos_cpu": _DROP, "kuberos_link_latency_ms": {"clod-2": 5}},
            "fetch-2": {"kuberos_fleet": _DROP},
            "edge-1": {"kuberos_memory": "lots"},
            "cloud-1": {"kuberos_gpu": -1},
        }
    )
    with pytest.raises(errors.SpecError) as info:
        inventory.load_inventory(raw, INVENTORY_SOURCE)
    exc = info.value
    assert_problem(exc, INVENTORY_SOURCE, "hosts.fetch-1.kuberos_cpu", ["is required"], None)
    assert_problem(exc, INVENTORY_SOURCE, "hosts.fetch-1.kuberos_link_latency_ms.clod-2", ["did you mean 'cloud-2'?"], None)
    assert_problem(exc, INVENTORY_SOURCE, "hosts.fetch-2.kuberos_fleet", ["is required for a robot"], None)
    assert_problem(exc, INVENTORY_SOURCE, "hosts.edge-1.kuberos_memory", ["'lots' is not valid"], None)
    assert_problem(exc, INVENTORY_SOURCE, "hosts.cloud-1.kuberos_gpu", ["-1 (int) is not valid"], None)


# --------------------------------------------------------------------------------------------
# Spec vs inventory mismatches and infeasible placements
# --------------------------------------------------------------------------------------------


@pytest.fixture
def inventory_model():
    return inventory.load_inventory(copy.deepcopy(GOOD_INVENTORY), "inventories/local")


MISMATCH_CASES = [
    case(
        "unknown-targetFleet",
        BASE.replace("targetFleet: test-fleet", "targetFleet: test-flet"),
        "metadata.targetFleet",
        ["'test-flet' is not a fleet in the inventory", "did you mean 'test-fleet'?", "fleets: test-fleet, warehouse-fleet"],
        3,
    ),
    case(
        "robotSelector-robot-of-another-fleet",
        metadata("robotSelector:", "  robot: [fetch-1, tiago-1]"),
        "metadata.robotSelector.robot[1]",
        ["'tiago-1' is not a robot of fleet test-fleet", "it belongs to fleet warehouse-fleet"],
        5,
    ),
    case(
        "robotSelector-unknown-robot",
        metadata("robotSelector: {robot: [fetch-3]}"),
        "metadata.robotSelector.robot[0]",
        ["'fetch-3' is not a robot of fleet test-fleet", "robots of test-fleet: fetch-1, fetch-2", "did you mean 'fetch-"],
        4,
    ),
    case(
        "discovery-port-differs-within-fleet",
        top("discovery: {port: 11811}") + "---\n" + top("discovery: {port: 12000}").replace("name: demo", "name: other"),
        "discovery.port",
        [f"{SOURCE} (document 2)", "12000 differs from port 11811", "expected one port per fleet"],
        17,
    ),
]


@pytest.mark.parametrize(("text", "path", "contains", "line"), MISMATCH_CASES)
def test_spec_does_not_match_inventory(text, path, contains, line, inventory_model):
    deployments = spec.load_rosdeployments(text, SOURCE)
    with pytest.raises(errors.SpecError) as info:
        scheduler.place_modules(deployments, inventory_model)
    assert_problem(info.value, SOURCE, path, contains, line)


def placement_case(case_id, lines, contains):
    return pytest.param(module(*lines), list(contains), id=case_id)


INFEASIBLE_CASES = [
    placement_case(
        "max_latency-too-strict-for-every-node",
        ["preference: [edge, cloud]", "requirements: {max_latency: 1 ms}"],
        [
            "rosModules[0] 'planner' of demo has no feasible node for robot fetch-1 (tiers tried: edge, cloud)",
            "edge-1 (edge): latency 5 ms to fetch-1 > max_latency 1 ms",
            "edge-2 (edge): latency 5 ms to fetch-1 > max_latency 1 ms",
            "cloud-1 (cloud): latency 40 ms to fetch-1 > max_latency 1 ms",
            "cloud-2 (cloud): latency 180 ms to fetch-1 > max_latency 1 ms",
            "cloud-2 (cloud): latency 60 ms to fetch-2 > max_latency 1 ms",
            "for robot fetch-2",
        ],
    ),
    placement_case(
        "gpu-more-than-any-node",
        ["preference: cloud", "resources: {gpu: 4}"],
        [
            "has no feasible node for robot fetch-1 (tiers tried: cloud, edge, onboard)",
            "cloud-1 (cloud): gpu: needs 4, 1 free of 1",
            "cloud-2 (cloud): gpu: needs 4, 1 free of 1",
            "edge-1 (edge): gpu: needs 4, node has none",
            "fetch-1 (onboard): gpu: needs 4, node has none",
            "fetch-2 (onboard): gpu: needs 4, node has none",
        ],
    ),
    placement_case(
        "cpu-more-than-any-node",
        ["resources: {cpu: 64}"],
        [
            "edge-1 (edge): cpu: needs 64, ",  # the fleet's discovery server already took 100m
            "free of 16",
            "cloud-1 (cloud): cpu: needs 64, 32 free of 32",
            "fetch-1 (onboard): cpu: needs 64, 4 free of 4",
        ],
    ),
    placement_case(
        "memory-more-than-any-node",
        ["preference: [cloud]", "resources: {memory: 128Gi}"],
        ["cloud-1 (cloud): memory: needs 128Gi, 64Gi free of 64Gi", "tiers tried: cloud)"],
    ),
    placement_case(
        "device-no-node-has",
        ["requirements: {devices: [thermal-camera]}"],
        ["edge-1 (edge): lacks device(s) thermal-camera", "fetch-1 (onboard): lacks device(s) thermal-camera"],
    ),
    placement_case(
        "arch-no-node-has",
        ["requirements: {arch: riscv64}"],
        ["edge-1 (edge): arch amd64, needs riscv64", "cloud-2 (cloud): arch amd64, needs riscv64"],
    ),
    placement_case(
        "shared-module-too-strict-latency",
        ["strategy: shared", "requirements: {max_latency: 2 ms}"],
        ["(tiers tried: edge, cloud)", "edge-1 (edge): latency 5 ms to fetch-1 > max_latency 2 ms"],
    ),
]


@pytest.mark.parametrize(("text", "contains"), INFEASIBLE_CASES)
def test_infeasible_placement(text, contains, inventory_model):
    deployments = spec.load_rosdeployments(text, SOURCE)
    with pytest.raises(errors.PlacementError) as info:
        scheduler.place_modules(deployments, inventory_model)
    message = str(info.value)
    assert message.startswith("cannot place ")
    assert f"{SOURCE}:5: rosModules[0] 'planner'" in message, message
    for substring in contains:
        assert substring in message, f"{substring!r} not in:\n{message}"
    assert info.value.failures


def test_infeasible_placement_lists_each_rejected_node_once_per_robot(inventory_model):
    deployments = spec.load_rosdeployments(module("preference: [edge, cloud]", "requirements: {max_latency: 1 ms}"), SOURCE)
    with pytest.raises(errors.PlacementError) as info:
        scheduler.place_modules(deployments, inventory_model)
    assert len(info.value.failures) == 2  # fetch-1 and fetch-2
    for failure in info.value.failures:
        rejected = [line.strip().split(" ")[0] for line in failure.splitlines()[1:]]
        # edge-3 serves warehouse-fleet only, so it is not a candidate for test-fleet
        assert rejected == ["edge-1", "edge-2", "cloud-1", "cloud-2"], failure


ALLOCATION_CASES = [
    pytest.param({"edge-1": {"cpu": "lots"}}, "edge-1", ["'lots'", "expected cpu, memory, gpu and pods"], id="cpu-lots"),
    pytest.param({"edge-1": "full"}, "edge-1", ["'full' is not valid"], id="entry-not-a-mapping"),
    pytest.param({"cloud-1": {"gpu": "one"}}, "cloud-1", ["'one'", "is not valid"], id="gpu-not-a-number"),
]


@pytest.mark.parametrize(("allocated", "path", "contains"), ALLOCATION_CASES)
def test_bad_allocation_data(allocated, path, contains, inventory_model):
    deployments = spec.load_rosdeployments(BASE, SOURCE)
    with pytest.raises(errors.SpecError) as info:
        scheduler.place_modules(deployments, inventory_model, allocated)
    assert_problem(info.value, "allocated", path, contains, None)
