"""Hostile input, refused at the door: one row per class of attack (issue 14).

Each row is a file (a RosDeployment, or a software catalog file) and the one problem it must be refused with: the
field, the line and a fragment of the reason. Every row asserts the exact output: the title, then one line per
problem, ``<file>:<line>: <field>: <reason>``, no Python exception text, and the same lines through the filter
that the deploy reads specs with. A few rows run ``ansible-playbook playbooks/deploy.yml`` end to end (render only)
and check the exit code, the message and that nothing was rendered.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass

import pytest
from ansible.errors import AnsibleFilterError
from helpers import CATALOG_BASE, ROOT, SPEC_BASE, playbook

from ansible_collections.kuberos.platform.plugins.filter.rosdeployment_targets import rosdeployment_targets
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import catalog, errors, inventory, spec, yaml_source

SPEC_NAME = "spec.yml"
CATALOG_NAME = "catalog"
TRACEBACK_TEXT = ("Traceback", "Error(", "Exception", 'File "')


BASE = SPEC_BASE  # lines 1-7; a module's extra lines start at line 8, metadata's at line 4
CATALOG = CATALOG_BASE  # 13 lines; fields added to the planner's version start at line 14


def module(*lines: str) -> str:
    return BASE + "".join(f"  {line}\n" for line in lines)


def metadata(*lines: str) -> str:
    head, tail = BASE.split("rosModules:\n", 1)
    return head + "".join(f"  {line}\n" for line in lines) + "rosModules:\n" + tail


def image(reference: str) -> str:
    return BASE.replace("registry/planner:1.0", reference)


def parameters(*lines: str) -> str:
    """rosParameters of the module, ``planner:`` on line 9, the given lines from line 10."""
    return module("rosParameters:", "  planner:", *(f"    {line}" for line in lines))


def planner_version(*lines: str) -> str:
    return CATALOG + "".join(f"    {line}\n" for line in lines)


def renamed(text: str, deployment: str, module_name: str) -> str:
    return text.replace("name: demo", f"name: {deployment}").replace("name: planner", f"name: {module_name}")


@dataclass(frozen=True)
class Row:
    content: str | bytes
    field: str
    line: int | None
    reason: str
    kind: str = "spec"  # spec | catalog
    source: str = ""  # the file named, when not the spec or catalog file itself (e.g. a document of it)


def row(case_id: str, content, field: str, line: int | None, reason: str, **extra):
    return pytest.param(Row(content, field, line, reason, **extra), id=case_id)


ROWS = [
    # -- 1. control characters, raw and escaped; multibyte text over the size limit -------------------------
    row("nul", BASE.replace("name: demo", "name: de\x00mo"), "metadata.name", 2, "control character U+0000 (NUL) in column 11"),
    row(
        "c1-nel", BASE.replace("name: demo", "name: de\x85mo"), "metadata.name", 2, "control character U+0085 (NEL) in column 11"
    ),
    row("del", BASE.replace("name: demo", "name: de\x7fmo"), "metadata.name", 2, "control character U+007F (DEL)"),
    row(
        "line-separator",
        BASE.replace("planner.launch.py", "planner.launch.py\u2028--evil"),
        "rosModules[0].launch",
        7,
        "control character U+2028 (LINE SEPARATOR) in column 48",
    ),
    row(
        "bidi-override",
        BASE.replace("ros2 launch", "ros2 \u202elaunch"),
        "rosModules[0].launch",
        7,
        "control character U+202E (RIGHT-TO-LEFT OVERRIDE) in column 16",
    ),
    row(
        "escape-sequence-written-as-escape",
        module('env: {COLOR: "\\e[31mred"}'),
        "rosModules[0].env.COLOR",
        8,
        "control character U+001B (ESC) (written as an escape)",
    ),
    row(
        "nul-written-as-escape",
        BASE.replace("launch: ros2 launch planner planner.launch.py", 'launch: "ros2 run x\\0y"'),
        "rosModules[0].launch",
        7,
        "control character U+0000 (NUL) (written as an escape)",
    ),
    row(
        "noncharacter",
        BASE.replace("name: demo", "name: de\ufffemo"),
        "metadata.name",
        2,
        "control character U+FFFE in column 11",
    ),
    row("multibyte-over-the-limit", "# " + "é" * 600_000 + "\n" + BASE, "", None, "file is larger than 1048576 bytes"),
    row("not-utf8", BASE.encode() + b"# \xff\n", "", 8, "not UTF-8 text (byte"),
    row(
        "catalog-nul",
        planner_version("rosDistro: jaz\x00zy"),
        "modules[1].versions[0].rosDistro",
        14,
        "U+0000 (NUL)",
        kind="catalog",
    ),
    # -- 2. image references ------------------------------------------------------------------------------
    row("image-space", image("'registry/planner 1.0'"), "rosModules[0].image", 6, "without spaces"),
    row(
        "image-command-substitution",
        image("'registry/planner:$(reboot)'"),
        "rosModules[0].image",
        6,
        "is not a valid image reference (the tag '$(reboot)' is not 1 to 128 letters",
    ),
    row("image-semicolon", image("'registry/planner:1.0;reboot'"), "rosModules[0].image", 6, "the tag '1.0;reboot'"),
    row("image-backtick", image("'`id`'"), "rosModules[0].image", 6, "the path component '`id`' is not lowercase"),
    row("image-uppercase-path", image("ghcr.io/Example/planner:1.0"), "rosModules[0].image", 6, "the path component 'Example'"),
    row("image-tag-starts-with-dash", image("registry/planner:-1"), "rosModules[0].image", 6, "the tag '-1'"),
    row("image-tag-129-characters", image("registry/planner:" + "a" * 129), "rosModules[0].image", 6, "is not 1 to 128 letters"),
    row("image-empty-tag", image("'registry/planner:'"), "rosModules[0].image", 6, "the tag ''"),
    row("image-bad-port", image("registry:port/planner:1.0"), "rosModules[0].image", 6, "the registry 'registry:port'"),
    row(
        "image-short-digest",
        image("registry/planner@sha256:abc"),
        "rosModules[0].image",
        6,
        "the sha256 digest is not 64 lowercase hex",
    ),
    row(
        "image-uppercase-digest",
        image("registry/planner@sha256:" + "A" * 64),
        "rosModules[0].image",
        6,
        "the sha256 digest is not 64 lowercase hex",
    ),
    row(
        "image-md5-digest",
        image("registry/planner@md5:" + "a" * 32),
        "rosModules[0].image",
        6,
        "the digest algorithm 'md5' is not sha256, sha384 or sha512",
    ),
    row("image-two-digests", image("registry/planner@sha256:" + "a" * 64 + "@x"), "rosModules[0].image", 6, "more than one '@'"),
    row("image-binary-tag", image("!!binary aGVsbG8="), "rosModules[0].image", 6, "b'hello' (bytes) is not valid"),
    row(
        "catalog-image-uppercase",
        CATALOG.replace("registry/planner:1.0", "registry/Planner:1.0"),
        "modules[1].versions[0].image",
        12,
        "the path component 'Planner'",
        kind="catalog",
    ),
    row(
        "catalog-image-metacharacters",
        CATALOG.replace("registry/planner:1.0", "'registry/planner:1.0|sh'"),
        "modules[1].versions[0].image",
        12,
        "the tag '1.0|sh'",
        kind="catalog",
    ),
    # -- 3. labels KubeROS owns; label syntax -------------------------------------------------------------
    row(
        "label-kuberos-io",
        metadata("labels: {kuberos.io/deployment: other}"),
        "metadata.labels.kuberos.io/deployment",
        4,
        "is a label KubeROS sets itself",
    ),
    row(
        "label-subdomain-of-kuberos-io",
        metadata("labels: {robot.kuberos.io/name: fetch-1}"),
        "metadata.labels.robot.kuberos.io/name",
        4,
        "is a label KubeROS sets itself",
    ),
    row(
        "label-managed-by",
        metadata("labels: {app.kubernetes.io/managed-by: helm}"),
        "metadata.labels.app.kubernetes.io/managed-by",
        4,
        "is a label KubeROS sets itself",
    ),
    row(
        "label-prefix-over-253",
        metadata("labels: {" + ".".join(["a" * 60] * 5) + "/team: x}"),
        "metadata.labels." + ".".join(["a" * 60] * 5) + "/team",
        4,
        "has a prefix longer than 253 characters",
    ),
    row("label-value-with-space", metadata("labels: {team: 'a b'}"), "metadata.labels.team", 4, "expected a label value"),
    # -- 4. rosParameters ROS 2 cannot read ---------------------------------------------------------------
    row("params-binary", parameters("key: !!binary aGVsbG8="), "rosModules[0].rosParameters.planner.key", 10, "!!binary"),
    row("params-set", parameters("ids: !!set {a, b}"), "rosModules[0].rosParameters.planner.ids", 10, "is a YAML !!set"),
    row("params-date", parameters("since: 2024-05-01"), "rosModules[0].rosParameters.planner.since", 10, "is a YAML timestamp"),
    row(
        "params-timestamp",
        parameters("since: 2024-05-01T10:00:00Z"),
        "rosModules[0].rosParameters.planner.since",
        10,
        "is a YAML timestamp (2024-05-01T10:00:00+00:00)",
    ),
    row(
        "params-integer-key",
        parameters("1: one"),
        "rosModules[0].rosParameters.planner.1",
        10,
        "1 (int) is not a valid parameter name",
    ),
    row("params-bool-key", parameters("yes: one"), "rosModules[0].rosParameters.planner.True", 10, "True (bool) is not a valid"),
    row("params-null", parameters("goal: null"), "rosModules[0].rosParameters.planner.goal", 10, "ROS 2 parameters have no null"),
    row("params-empty-list", parameters("weights: []"), "rosModules[0].rosParameters.planner.weights", 10, "is an empty list"),
    row(
        "params-int-in-double-array",
        parameters("weights: [1.0, 2.0, 3, 4.0]"),
        "rosModules[0].rosParameters.planner.weights[2]",
        10,
        "3 (int) is an integer, but rosModules[0].rosParameters.planner.weights[0] is a double",
    ),
    row(
        "params-mixed-array",
        parameters("names: [a, 1]"),
        "rosModules[0].rosParameters.planner.names[1]",
        10,
        "ROS 2 arrays hold values of one type",
    ),
    row(
        "params-nested-array",
        parameters("grid: [[1, 2], [3, 4]]"),
        "rosModules[0].rosParameters.planner.grid[0]",
        10,
        "list inside a list",
    ),
    row(
        "params-mapping-in-array",
        parameters("goals: [{x: 1}]"),
        "rosModules[0].rosParameters.planner.goals[0]",
        10,
        "mapping inside a list",
    ),
    row(
        "params-past-int64",
        parameters("seed: 9223372036854775808"),
        "rosModules[0].rosParameters.planner.seed",
        10,
        "does not fit a 64-bit integer",
    ),
    row(
        "params-key-with-space",
        parameters("'max speed': 1.0"),
        "rosModules[0].rosParameters.planner.max speed",
        10,
        "without spaces",
    ),
    row(
        "catalog-params-set",
        planner_version("rosParameters: {ids: !!set {a}}"),
        "modules[1].versions[0].rosParameters.ids",
        14,
        "is a YAML !!set",
        kind="catalog",
    ),
    # -- 5. objects that would get the same name ----------------------------------------------------------
    row(
        "name-clash-across-documents",
        renamed(BASE, "a-b", "c") + "---\n" + renamed(BASE, "a", "b-c"),
        "rosModules[0].name",
        13,
        "'b-c' of deployment a would name a Deployment a-b-c-<robot> (each robot's instance), the name "
        "rosModules[0].name 'c' of deployment a-b (spec.yml (document 1):5) gets",
        source="spec.yml (document 2)",
    ),
    row(
        "name-clash-of-parameter-configmaps",
        renamed(module("strategy: shared", "rosParameters: {x: 1}"), "a-b", "c")
        + "---\n"
        + renamed(module("rosParameters: {x: 1}"), "a", "b-c"),
        "rosModules[0].name",
        15,
        "would name a ConfigMap a-b-c-params (ROS parameters)",
        source="spec.yml (document 2)",
    ),
    row(
        "name-clash-through-robot-names",
        metadata("robotSelector: {robot: [fetch-1, x-fetch-1]}")
        + "- name: planner-x\n  image: registry/planner:1.0\n  launch: run\n",
        "rosModules[1].name",
        9,
        "would name a Deployment demo-planner-x-fetch-1 (the instance of robot fetch-1), the name rosModules[0].name",
    ),
    row(
        "name-reserved-for-kuberos-objects",
        BASE.replace("name: demo", "name: kuberos-discovery"),
        "metadata.name",
        2,
        "starts with 'kuberos', the prefix of KubeROS's own objects",
    ),
    # -- 6. max_latency of zero or less -------------------------------------------------------------------
    row(
        "max-latency-zero",
        module("requirements: {max_latency: 0}"),
        "rosModules[0].requirements.max_latency",
        8,
        "0 (int) is not more than zero",
    ),
    row(
        "max-latency-zero-ms",
        module("requirements: {max_latency: 0 ms}"),
        "rosModules[0].requirements.max_latency",
        8,
        "'0 ms' is not more than zero",
    ),
    row(
        "max-latency-negative",
        module("requirements: {max_latency: -5}"),
        "rosModules[0].requirements.max_latency",
        8,
        "-5 (int) is not valid",
    ),
    row(
        "catalog-max-latency-zero",
        planner_version("requirements: {max_latency: 0 s}"),
        "modules[1].versions[0].requirements.max_latency",
        14,
        "'0 s' is not more than zero",
        kind="catalog",
    ),
    # -- more: names, quantities, documents ---------------------------------------------------------------
    row("name-trailing-newline", BASE.replace("name: demo", 'name: "demo\\n"'), "metadata.name", 2, "'demo\\n' is not valid"),
    row(
        "env-name-trailing-newline",
        module('env: {"PATH\\n": x}'),
        "rosModules[0].env.PATH\\n",
        8,
        "'PATH\\n' is not a valid name",
    ),
    row("name-unicode", BASE.replace("name: demo", "name: démo"), "metadata.name", 2, "'démo' is not valid"),
    row(
        "module-name-with-dots",
        BASE.replace("name: planner", "name: motion.planner"),
        "rosModules[0].name",
        5,
        "'motion.planner' is not valid",
    ),
    row("fleet-uppercase", BASE.replace("test-fleet", "Test_Fleet"), "metadata.targetFleet", 3, "'Test_Fleet' is not valid"),
    row(
        "robot-with-space",
        metadata("robotSelector: {robot: ['fetch 1']}"),
        "metadata.robotSelector.robot[0]",
        4,
        "'fetch 1' is not valid",
    ),
    row(
        "device-path",
        module("requirements: {devices: [/dev/ttyUSB0]}"),
        "rosModules[0].requirements.devices[0]",
        8,
        "'/dev/ttyUSB0' is not valid; expected a device name",
    ),
    row(
        "arch-with-space",
        module("requirements: {arch: 'amd64 arm64'}"),
        "rosModules[0].requirements.arch",
        8,
        "'amd64 arm64' is not valid",
    ),
    row(
        "cpu-past-int64",
        module("resources: {cpu: 99999999999999999999}"),
        "rosModules[0].resources.cpu",
        8,
        "is not valid: it must be at most 1024 CPUs (1024000m); expected a CPU quantity",
    ),
    row(
        "memory-past-int64",
        module("resources: {memory: 99999999999Ti}"),
        "rosModules[0].resources.memory",
        8,
        "'99999999999Ti' is not valid: it must be at most 64Ti; expected a memory quantity",
    ),
    row(
        "too-many-documents",
        "".join("---\n" + BASE.replace("name: demo", f"name: d{i}") for i in range(201)),
        "",
        1601,
        "file too large: more than 200 documents",
    ),
    row(
        "modules-past-100",
        BASE + "".join(f"- {{name: m{i}, image: r/i:1, launch: run}}\n" for i in range(100)),
        "rosModules",
        4,
        "has 101 modules; expected at most 100 in one RosDeployment",
    ),
    row(
        "modules-past-1000-in-a-file",
        "".join(
            f"---\nmetadata: {{name: d{d}, targetFleet: f}}\nrosModules:\n"
            + "".join(f"- {{name: m{i}, image: r/i:1, launch: run}}\n" for i in range(100))
            for d in range(11)
        ),
        "rosModules",
        1033,  # 10 documents of 103 lines before it
        "brings the file past 1000 modules; expected at most 1000 in one file",
        source="spec.yml (document 11)",
    ),
    row(
        "half-a-million-scalars",
        "a: [" + "0," * 520_000 + "0]\n",
        "",
        1,
        "file too large: more than 50000 YAML nodes; expected at most 50000 in one file",
    ),
    row("python-object-tag", "metadata: !!python/object/apply:os.system [echo hi]\n", "", 1, "could not determine a constructor"),
]


def refusal(item: Row, tmp_path) -> tuple[errors.SpecError, str]:
    """The error a row's file is refused with, and the name of the source it must name."""
    data = item.content if isinstance(item.content, bytes) else item.content.encode("utf-8")
    if item.kind == "catalog":
        folder = tmp_path / "catalog"
        folder.mkdir()
        (folder / "pnp.yml").write_bytes(data)
        with pytest.raises(errors.SpecError) as info:
            catalog.load_catalog(str(folder), CATALOG_NAME)
        return info.value, item.source or f"{CATALOG_NAME}/pnp.yml"
    path = tmp_path / SPEC_NAME
    path.write_bytes(data)
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(str(path), SPEC_NAME)
    return info.value, item.source or SPEC_NAME


def assert_one_line(error: errors.SpecError, source: str, item: Row) -> None:
    rendered = str(error)
    lines = rendered.split("\n")
    assert lines[0] == f"{error.title} (1 problem):", rendered
    assert len(lines) == 2, rendered
    where = source if item.line is None else f"{source}:{item.line}"
    head = f"  - {where}: {item.field}: " if item.field else f"  - {where}: "
    assert lines[1].startswith(head), f"expected {head!r} in:\n{rendered}"
    assert item.reason in lines[1][len(head) :], f"expected {item.reason!r} in:\n{rendered}"
    assert lines[1].isprintable(), rendered
    assert not any(text in rendered for text in TRACEBACK_TEXT), rendered


@pytest.mark.parametrize("item", ROWS)
def test_hostile_file_is_refused_with_one_located_line(item, tmp_path):
    error, source = refusal(item, tmp_path)
    assert_one_line(error, source, item)


@pytest.mark.parametrize("item", [p for p in ROWS if p.values[0].kind == "spec"][::4])
def test_the_filter_that_reads_specs_says_the_same(item, tmp_path):
    error, _source = refusal(item, tmp_path)
    with pytest.raises(AnsibleFilterError) as info:
        rosdeployment_targets(str(tmp_path / SPEC_NAME))
    assert str(error).replace(SPEC_NAME, str(tmp_path / SPEC_NAME)) == str(info.value)


# -- the inventory: values carry no line (Ansible hands over host variables without their origin) --------------

INVENTORY_ROWS = [
    pytest.param({"kuberos_fleet": "test-\x00fleet"}, "hosts.fetch-1.kuberos_fleet", "U+0000 (NUL)", id="fleet-nul"),
    pytest.param({"kuberos_fleet": "f", "kuberos_arch": "amd\u202e64"}, "hosts.fetch-1.kuberos_arch", "U+202E", id="arch-bidi"),
    pytest.param(
        {"kuberos_fleet": "f", "kuberos_link_latency_ms": {"edge\x1b[2J": 5}},
        "hosts.fetch-1.kuberos_link_latency_ms.edge\\x1b[2J",
        "U+001B (ESC)",
        id="link-key-escape",
    ),
]


def test_inventory_names_with_a_trailing_line_break():
    raw = {
        "hosts": {"fetch-1": {"kuberos_cpu": 4, "kuberos_memory": "8Gi", "kuberos_fleet": "f\n"}},
        "groups": {"robots": ["fetch-1"]},
    }
    with pytest.raises(errors.SpecError) as info:
        inventory.load_inventory(raw)
    assert str(info.value).split("\n")[1:] == [
        "  - inventory: hosts.fetch-1.kuberos_fleet: 'f\\n' is not valid; "
        "expected a fleet name of lowercase letters, digits, '-' and '.'"
    ]


@pytest.mark.parametrize(("variables", "field", "reason"), INVENTORY_ROWS)
def test_inventory_with_control_characters(variables, field, reason):
    raw = {"hosts": {"fetch-1": {"kuberos_cpu": 4, "kuberos_memory": "8Gi", **variables}}, "groups": {"robots": ["fetch-1"]}}
    with pytest.raises(errors.SpecError) as info:
        inventory.load_inventory(raw)
    rendered = str(info.value)
    assert rendered.split("\n")[1:] == [f"  - inventory: {field}: control character {reason}" + rendered.split(reason, 1)[1]]
    assert rendered.split("\n")[1].isprintable()


@pytest.mark.parametrize("path", ["/dev/zero", "fifo"])
def test_a_file_that_never_ends_is_refused_without_reading_it(path, tmp_path):
    if path == "fifo":
        path = str(tmp_path / "spec.yml")
        os.mkfifo(path)  # opening it would block until a writer comes
    with pytest.raises(errors.SpecError) as info:
        spec.load_rosdeployment_file(path)
    line = str(info.value).split("\n")[1]
    assert line.startswith(f"  - {path}: is a ") and line.endswith(", not a regular file"), str(info.value)


def test_every_control_character_class_is_refused():
    """The set docs/rosdeployment.md names: C0 but tab and line breaks, DEL, C1, U+2028/9, bidi controls, U+FFFE/F."""
    refused = {chr(c) for c in range(0x110000) if 0xD800 > c or c > 0xDFFF if yaml_source.CONTROL_CHARACTERS.match(chr(c))}
    expected = {chr(c) for c in (*range(0x00, 0x20), *range(0x7F, 0xA0))} - {"\t", "\n", "\r"}
    expected |= {
        "\u061c",
        "\u200e",
        "\u200f",
        "\u2028",
        "\u2029",
        *map(chr, range(0x202A, 0x202F)),
        *map(chr, range(0x2066, 0x206A)),
        "\ufffe",
        "\uffff",
    }
    assert refused == expected


# -- end to end: ansible-playbook playbooks/deploy.yml, render only ----------------------------------------------

END_TO_END = [
    "nul",
    "image-command-substitution",
    "label-subdomain-of-kuberos-io",
    "params-binary",
    "name-clash-across-documents",
]


@pytest.mark.parametrize("item", [p for p in ROWS if p.id in END_TO_END])
def test_deploy_playbook_refuses_and_renders_nothing(item, tmp_path):
    path = tmp_path / SPEC_NAME
    path.write_bytes(item.content if isinstance(item.content, bytes) else item.content.encode("utf-8"))
    render = tmp_path / "render"
    result = playbook(
        "deploy.yml", "-e", f"rosdeployment_file={path}", "-e", "kuberos_apply=false", "-e", f"kuberos_render_dir={render}"
    )  # fmt: skip
    output = result.stdout + result.stderr
    assert result.returncode != 0, output[-4000:]
    source = str(path) + (item.source[len(SPEC_NAME) :] if item.source else "")
    where = f"{source}:{item.line}: {item.field}: " if item.field else f"{source}:{item.line}: "
    located = [line for line in output.splitlines() if where in line]
    assert located and item.reason.replace(SPEC_NAME, str(path)) in located[0], output[-4000:]
    assert "Traceback" not in output
    assert not render.exists() or not os.listdir(render)


# -- names against what the cluster holds (the check node_allocations runs with the live objects) ------------------

CLASHING = renamed(BASE, "a", "b-c")  # deployment a, module b-c: its instances are named a-b-c-<robot>


def live(name, deployment="a-b", module="c", kind="Deployment"):
    return {"kind": kind, "namespace": "kuberos-test-fleet", "name": name, "deployment": deployment, "module": module}


@pytest.mark.parametrize(
    ("objects", "expected"),
    [
        pytest.param(
            [live("a-b-c-fetch-1")],
            "spec.yml:5: rosModules[0].name: 'b-c' of deployment a would name a Deployment a-b-c-fetch-1 (the instance of "
            "robot fetch-1) in namespace kuberos-test-fleet, but a Deployment of that name is already there and belongs to "
            "deployment a-b (module c)",
            id="another-deployments-instance",
        ),
        pytest.param(
            [live("a-b-c-fetch-2", deployment="", module="")],
            "but a Deployment of that name is already there and belongs to no KubeROS deployment",
            id="an-object-kuberos-does-not-manage",
        ),
        pytest.param([live("a-b-c-fetch-1", deployment="a", module="b-c")], None, id="its-own-instance"),
        pytest.param([live("a-b-c-fetch-1", kind="ConfigMap")], None, id="another-kind"),
        pytest.param([live("a-b-c-tiago-1")], None, id="a-robot-of-another-fleet"),
    ],
)
def test_names_against_the_objects_in_the_cluster(objects, expected, local_inventory):
    deployments = spec.load_rosdeployments(CLASHING, SPEC_NAME)

    def robots_of(dep):
        return dep.robots or local_inventory.fleets.get(dep.fleet)

    problems = spec.name_clash_problems(deployments, robots_of, objects)
    if expected is None:
        assert problems == []
    else:
        assert len(problems) == 1 and expected in str(problems[0]), problems


def test_deploy_playbook_refuses_an_inventory_value_with_a_control_character(tmp_path):
    site = tmp_path / "site"
    shutil.copytree(os.path.join(ROOT, "inventories", "local"), site)
    hosts = site / "hosts.yml"
    text = hosts.read_text(encoding="utf-8")
    assert "          kuberos_fleet: test-fleet\n" in text
    hosts.write_text(text.replace("          kuberos_fleet: test-fleet\n", '          kuberos_fleet: "test-\\x00fleet"\n', 1))
    render = tmp_path / "render"
    result = playbook(
        "deploy.yml", "-e", f"rosdeployment_file={os.path.join(ROOT, 'examples', 'listing1.yml')}",
        "-e", "kuberos_apply=false", "-e", f"kuberos_render_dir={render}", inventory=site,
    )  # fmt: skip
    output = result.stdout + result.stderr
    assert result.returncode != 0, output[-4000:]
    assert "- inventory: hosts.fetch-1.kuberos_fleet: control character U+0000 (NUL); expected printable text" in output
    assert "Traceback" not in output
    assert not render.exists() or not os.listdir(render)


@pytest.mark.parametrize("option", ["discovery_image", "bridge_image"])
def test_the_images_given_as_render_options_are_image_references_too(option):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import RENDER_ARGS, render_options

    params = {name: spec["default"] for name, spec in RENDER_ARGS.items()}
    assert render_options(params).discovery_image == params["discovery_image"]
    params[option] = "ros:jazzy $(reboot)"
    with pytest.raises(errors.SpecError) as refused:
        render_options(params)
    assert f"render options: {option}: 'ros:jazzy $(reboot)' is not a valid image reference" in str(refused.value)
