"""The software catalog: loading and validation, resolution, specs that name catalog modules.

Every error case is a table row in the style of test_bad_input.py: the input, the field path the
problem must name, substrings of its message and the line. Bad input only ever raises ``SpecError``.
"""

from __future__ import annotations

import dataclasses
import json
import os

import pytest
from helpers import CATALOG_BASE
from hypothesis import given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import service
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import (
    Catalog,
    CatalogEntry,
    catalog_problems_against_inventory,
    load_catalog,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import (
    load_rosdeployment_file,
    load_rosdeployments,
    parse_rosdeployment,
)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLE_CATALOG = os.path.join(ROOT, "inventories", "local", "catalog")
DATA_CATALOG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "catalog")
DIGEST = "sha256:" + "0123456789abcdef" * 4


@pytest.fixture(scope="module")
def example():
    return load_catalog(EXAMPLE_CATALOG, "inventories/local/catalog")


@pytest.fixture(scope="module")
def data():
    return load_catalog(DATA_CATALOG, "data/catalog")


def assert_problem(exc: SpecError, source: str, path: str, contains: list[str], line: int | None):
    message = str(exc)
    matching = [p for p in exc.problems if p.path == path and source in p.source]
    assert matching, f"no problem at {path!r} of {source} in:\n{message}"
    complete = [p for p in matching if all(s in str(p) for s in contains)]
    assert complete, f"no problem at {path!r} says all of {contains} in:\n{message}"
    if line is not None:
        assert any(p.line == line for p in complete), f"no problem at {path!r} on line {line} in:\n{message}"
        problem = next(p for p in complete if p.line == line)
        assert (f"{problem.source}:{line}: {path}: " if path else f"{problem.source}:{line}: ") in message
    else:
        assert str(complete[0]) in message


# --------------------------------------------------------------------------------------------
# The example catalog
# --------------------------------------------------------------------------------------------


def test_example_catalog_loads(example):
    assert example.names() == ["pnp-control", "pnp-coordinator", "pnp-perception", "pnp-planner"]
    assert not example.missing and example.source == "inventories/local/catalog"
    for name in example.names():
        assert [e.version for e in example.entries(name)] == ["0.1.0", "0.2.0"]
    planner = example.entries("pnp-planner")[0]
    assert planner == example.get("pnp-planner", "0.1.0")
    assert (planner.image, planner.image_ref, planner.launch) == (
        "ghcr.io/kuberos/pnp-planner:0.1",
        "ghcr.io/kuberos/pnp-planner:0.1",
        ("python3 -m kuberos_pnp.planner",),
    )
    assert (planner.ros_distro, planner.architectures, planner.preference) == ("jazzy", ("amd64",), "cloud")
    assert planner.dependencies == (("pnp-perception", "^0.1"),) and planner.interfaces == (("pnp_msgs", 1),)
    assert planner.source == "inventories/local/catalog/pick-and-place.yml" and planner.line == 42
    assert example.entries("pnp-control")[1].upgrade == "recreate"
    assert example.entries("pnp-perception")[1].preference == ("edge", "cloud")
    assert example.entries("nothing") == [] and example.get("pnp-planner", "9.9.9") is None


def test_example_0_1_images_are_those_of_the_plain_example(example):
    with open(os.path.join(ROOT, "examples", "pick-and-place.yml"), encoding="utf-8") as handle:
        text = handle.read()
    for name in example.names():
        old, new = example.entries(name)
        assert old.image in text and new.image.endswith(":0.2.0")
        assert all(line in text for line in old.launch)


def test_catalog_example_spec_is_the_plain_example_from_the_catalog(example, local_inventory):
    (plain,) = load_rosdeployment_file(os.path.join(ROOT, "examples", "pick-and-place.yml"))
    (catalogued,) = load_rosdeployment_file(os.path.join(ROOT, "examples", "pick-and-place-catalog.yml"), catalog=example)
    assert catalogued.name == plain.name == "pick-and-place"
    for old, new in zip(plain.modules, catalogued.modules, strict=True):
        assert (new.catalog_module, new.version, new.ros_distro) == (
            "pnp-" + new.image.split("pnp-")[1].split(":")[0],
            "0.1.0",
            "jazzy",
        )
        assert new.requirements.arch == ("amd64",)  # the catalog's architectures
        # The plain example declares its topics; the local catalog's entries do not (a spec that takes a subset of
        # them would have to re-declare what the others publish).
        assert old.topics and not new.topics
        same = dataclasses.replace(
            new, version="", catalog_module="", ros_distro="", requirements=old.requirements, topics=old.topics
        )
        assert same == old and new.ros_parameters == old.ros_parameters
        assert dataclasses.replace(new.requirements, arch=old.requirements.arch) == old.requirements
    before = place_modules([plain], local_inventory)
    after = place_modules([catalogued], local_inventory)
    assert [(i.name, i.node, i.robots) for i in before.instances] == [(i.name, i.node, i.robots) for i in after.instances]


# --------------------------------------------------------------------------------------------
# Resolution
# --------------------------------------------------------------------------------------------


def test_entries_are_sorted_by_version(data):
    assert [e.version for e in data.entries("arm-driver")] == ["1.0.0", "1.1.0", "1.2.0-rc.1", "2.0.0"]


RESOLVE = [
    ("arm-driver", None, "2.0.0"),
    ("arm-driver", "", "2.0.0"),
    ("arm-driver", "*", "2.0.0"),
    ("arm-driver", "^1", "1.1.0"),
    ("arm-driver", "~1.0", "1.0.0"),
    ("arm-driver", "1.0.0", "1.0.0"),
    ("arm-driver", ">=1.2.0-rc.0 <2", "1.2.0-rc.1"),
    ("arm-driver", "<1.1 || >=2", "2.0.0"),
    ("arm-driver", "1.0.0 - 1.2.0", "1.1.0"),
    ("lidar", "^0.1", "0.1.0"),
]


@pytest.mark.parametrize(("name", "wanted", "version"), RESOLVE)
def test_resolve(data, name, wanted, version):
    assert data.resolve(name, wanted).version == version


RESOLVE_ERRORS = [
    ("arm-driver", "^3", LookupError, "no version of arm-driver satisfies ^3 (versions: 1.0.0, 1.1.0, 1.2.0-rc.1, 2.0.0)"),
    ("arm-drivr", None, LookupError, "'arm-drivr' is not a module of the catalog data/catalog; did you mean 'arm-driver'?"),
    ("camera", "^1", LookupError, "(modules: arm-driver, lidar, nav, viz, viz-bridge)"),
    ("arm-driver", ">>1", ValueError, "invalid version range after 'arm-driver@': '>>1' has two operators"),
]


@pytest.mark.parametrize(("name", "wanted", "error", "message"), RESOLVE_ERRORS)
def test_resolve_errors(data, name, wanted, error, message):
    with pytest.raises(error) as info:
        data.resolve(name, wanted)
    assert message in str(info.value)


def test_prereleases_only_when_named(data):
    assert data.resolve("arm-driver", "1.2.0-rc.1").version == "1.2.0-rc.1"
    assert data.resolve("arm-driver", "^1.1").version == "1.1.0"  # 1.2.0-rc.1 is not offered to ^1.1


def test_digest_and_sources(data):
    newest = data.resolve("arm-driver")
    assert newest.image_ref == "registry.example.com:5000/robots/arm-driver:2.0.0@" + DIGEST
    assert newest.launch == ("ros2 launch arm_driver driver.launch.py", "ros2 run arm_driver watchdog")
    assert newest.source == "data/catalog/a-drivers.yml" and newest.line == 27
    assert data.resolve("viz").source == "data/catalog/b-apps.yaml (document 2)"
    assert data.resolve("nav").source == "data/catalog/b-apps.yaml (document 1)"
    assert data.resolve("arm-driver", "1.0.0").description == "Driver of the arm; holds the hardware."


def test_missing_catalog(tmp_path):
    catalog = load_catalog(tmp_path / "nowhere", "inventories/site/catalog")
    assert catalog.missing and catalog.names() == [] and catalog.source == "inventories/site/catalog"
    with pytest.raises(LookupError, match="'pnp-planner' is not in the catalog: no catalog at inventories/site/catalog"):
        catalog.resolve("pnp-planner", "^1")


def test_empty_directory_is_an_empty_catalog(tmp_path):
    (tmp_path / "README.md").write_text("not a catalog file\n")
    (tmp_path / ".hidden.yml").write_text("not: read\n")
    (tmp_path / "dir.yml").mkdir()
    catalog = load_catalog(tmp_path, "cat")
    assert not catalog.missing and catalog.names() == []
    with pytest.raises(LookupError, match="'x' is not in the catalog: the catalog cat has no modules"):
        catalog.resolve("x")


def test_single_file_catalog():
    catalog = load_catalog(os.path.join(DATA_CATALOG, "a-drivers.yml"), "drivers.yml")
    assert catalog.names() == ["arm-driver", "lidar"] and catalog.resolve("lidar").source == "drivers.yml"
    # nav depends on arm-driver, which this file alone does not have
    with pytest.raises(SpecError) as info:
        load_catalog(os.path.join(DATA_CATALOG, "b-apps.yaml"), "apps.yml")
    assert_problem(info.value, "apps.yml (document 1)", "modules[0].versions[0].dependencies.arm-driver", ["not a module"], 15)


# --------------------------------------------------------------------------------------------
# to_dict / from_dict / subset
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["example", "data"])
def test_round_trip(which, request):
    catalog = request.getfixturevalue(which)
    data = json.loads(json.dumps(catalog.to_dict()))
    again = Catalog.from_dict(data)
    assert again == catalog
    assert again.to_dict() == catalog.to_dict()
    assert [e.line for e in again.all_entries()] == [e.line for e in catalog.all_entries()]


def test_round_trip_of_a_subset_and_of_a_missing_catalog(example, tmp_path):
    used = example.subset([("pnp-planner", "0.1.0"), ("pnp-perception", "0.1.0"), ("pnp-planner", "0.1.0")])
    assert used.names() == ["pnp-perception", "pnp-planner"]
    assert [e.version for e in used.entries("pnp-planner")] == ["0.1.0"]
    assert Catalog.from_dict(used.to_dict()) == used
    assert used.resolve("pnp-planner").version == "0.1.0"
    missing = load_catalog(tmp_path / "none", "x")
    assert Catalog.from_dict(missing.to_dict()) == missing and Catalog.from_dict(missing.to_dict()).missing


def test_subset_of_unknown_entries(example):
    with pytest.raises(
        LookupError, match=r"pnp-planner 9.0.0 is not in the catalog inventories/local/catalog \(versions: 0.1.0, 0.2.0\)"
    ):
        example.subset([("pnp-planner", "9.0.0")])
    with pytest.raises(LookupError, match="is not a module of"):
        example.subset([("camera", "1.0.0")])


def test_from_dict_validates(example):
    data = example.to_dict()
    data["modules"][0]["versions"][0]["image"] = "Bad Image"
    data["modules"][1]["versions"][1]["dependencies"] = {"pnp-nothing": "^1"}
    with pytest.raises(SpecError) as info:
        Catalog.from_dict(data, "record kuberos-record-x")
    assert_problem(info.value, "record kuberos-record-x", "modules[0].versions[0].image", ["'Bad Image' is not valid"], None)
    assert_problem(
        info.value, "record kuberos-record-x", "modules[1].versions[1].dependencies.pnp-nothing", ["not a module"], None
    )
    deep: list = []
    for _ in range(5000):
        deep = [deep]
    wide = {"modules": [{"name": "a"}] * 200_000}
    for garbage in (None, [], "catalog", {"modules": "x"}, {"apiVersion": 1}, {"modules": deep}, wide):
        with pytest.raises(SpecError):
            Catalog.from_dict(garbage)


def test_from_dict_keeps_the_written_source_and_names_the_given_one(example):
    again = Catalog.from_dict(example.to_dict(), "record kuberos-record-pick-and-place")
    assert again == example and again.source == "inventories/local/catalog"
    data = example.to_dict()
    del data["source"]
    for version in data["modules"][0]["versions"]:
        del version["source"]
    assert Catalog.from_dict(data, "record x").source == "record x"
    assert Catalog.from_dict(data, "record x").entries("pnp-control")[0].source == "record x"


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4),
    max_leaves=20,
)


@settings(max_examples=200, deadline=None)
@given(
    st.fixed_dictionaries(
        {"apiVersion": st.just("kuberos.io/v1alpha1"), "kind": st.just("RosModuleCatalog")},
        optional={
            "modules": st.lists(
                st.fixed_dictionaries(
                    {"name": st.sampled_from(["a", "b", "B"]) | JSON},
                    optional={
                        "versions": st.lists(
                            st.dictionaries(
                                st.sampled_from(["version", "image", "launch", "dependencies", "interfaces", "env"]),
                                JSON | st.sampled_from(["1.0.0", "^1", "img:1"]),
                            ),
                            max_size=3,
                        )
                    },
                ),
                max_size=3,
            )
        },
    )
)
def test_hostile_catalog_data_only_raises_spec_error(data):
    try:
        Catalog.from_dict(data)
    except SpecError:
        pass


# --------------------------------------------------------------------------------------------
# Bad catalogs: every problem with file, line and field
# --------------------------------------------------------------------------------------------

# Lines 1-13; lines added with ``planner()`` start at line 14 (fields of planner 1.0.0).
BASE = CATALOG_BASE
PLANNER = "modules[1].versions[0]"


def planner(*lines: str) -> str:
    return BASE + "".join(f"    {line}\n" for line in lines)


def another_version(*lines: str) -> str:
    """A second version of planner (its '- version' on line 14, further fields from line 15)."""
    return BASE + "".join(f"  {line}\n" for line in lines)


def case(case_id, text, path, contains, line):
    return pytest.param(text, path, list(contains), line, id=case_id)


CATALOG_CASES = [
    case("wrong-kind", BASE.replace("RosModuleCatalog", "RosDeployment"), "kind", ["expected 'RosModuleCatalog'"], 2),
    case("wrong-api-version", BASE.replace("v1alpha1", "v1"), "apiVersion", ["expected 'kuberos.io/v1alpha1'"], 1),
    case("missing-kind", BASE.replace("kind: RosModuleCatalog\n", ""), "", ["missing required field 'kind'"], 1),
    case("top-level-list", "- a\n- b\n", "", ["(list) is not valid", "expected a mapping with apiVersion, kind and modules"], 1),
    case("modules-not-a-list", BASE.split("modules:")[0] + "modules: {}\n", "modules", ["expected a list of modules"], 3),
    case("module-without-versions", BASE + "- name: control\n", "modules[2]", ["missing required field 'versions'"], 14),
    case("empty-versions", BASE + "- name: control\n  versions: []\n", "modules[2].versions", ["expected a non-empty list"], 15),
    case("bad-module-name", BASE.replace("name: planner", "name: Planner_1"), "modules[1].name", ["'Planner_1' is not valid"], 9),
    case("unknown-field", planner("rosdistro: jazzy"), f"{PLANNER}.rosdistro", ["unknown field; did you mean 'rosDistro'?"], 14),
    case(
        "unknown-module-field",
        BASE.replace("- name: planner\n", "- name: planner\n  descripton: x\n"),
        "modules[1].descripton",
        ["did you mean 'description'?"],
        10,
    ),
    case("missing-image", BASE.replace("    image: registry/planner:1.0\n", ""), PLANNER, ["missing required field 'image'"], 11),
    case(
        "version-float",
        BASE.replace("version: 1.0.0", "version: 1.0"),
        f"{PLANNER}.version",
        ["1.0 (float) is not valid", "a semantic version string such as '0.2.0'"],
        11,
    ),
    case(
        "version-two-numbers",
        BASE.replace("version: 1.0.0", "version: '1.0'"),
        f"{PLANNER}.version",
        ["'1.0' is not MAJOR.MINOR.PATCH with three numbers"],
        11,
    ),
    case("version-with-v", BASE.replace("version: 1.0.0", "version: v1.0.0"), f"{PLANNER}.version", ["starts with 'v'"], 11),
    case("version-leading-zero", BASE.replace("version: 1.0.0", "version: 1.00.0"), f"{PLANNER}.version", ["leading zero"], 11),
    case(
        "duplicate-version",
        another_version("- version: 1.0.0", "  image: registry/planner:1.0.1", "  launch: run"),
        "modules[1].versions[1].version",
        ["1.0.0 is listed twice, first at line 11; expected each version once"],
        14,
    ),
    case(
        "same-precedence",
        another_version("- version: 1.0.0+rebuild", "  image: registry/planner:1.0.1", "  launch: run"),
        "modules[1].versions[1].version",
        ["1.0.0+rebuild has the same precedence as 1.0.0 (build metadata does not count)"],
        14,
    ),
    case(
        "image-with-digest",
        BASE.replace("registry/planner:1.0", f"registry/planner@{DIGEST}"),
        f"{PLANNER}.image",
        ["has a digest; put the digest (sha256:...) in 'digest'"],
        12,
    ),
    case(
        "image-uppercase",
        BASE.replace("registry/planner:1.0", "registry/Planner:1.0"),
        f"{PLANNER}.image",
        ["'registry/Planner:1.0' is not a valid image reference", "[registry/]path[:tag]"],
        12,
    ),
    case(
        "image-bad-tag",
        BASE.replace("registry/planner:1.0", "registry/planner:-1"),
        f"{PLANNER}.image",
        ["is not a valid image reference"],
        12,
    ),
    case(
        "image-with-space",
        BASE.replace("registry/planner:1.0", "'registry/planner 1.0'"),
        f"{PLANNER}.image",
        ["expected a container image reference without spaces"],
        12,
    ),
    case(
        "digest-short", planner("digest: sha256:abc"), f"{PLANNER}.digest", ["'sha256:abc' is not valid", "64 lowercase hex"], 14
    ),
    case("digest-uppercase", planner(f"digest: {DIGEST.upper()}"), f"{PLANNER}.digest", ["is not valid; expected a digest"], 14),
    case(
        "launch-unclosed-quote",
        BASE.replace("launch: ros2 launch planner planner.launch.py", 'launch: "ros2 run \'x"'),
        f"{PLANNER}.launch",
        ["is not a valid command line (No closing quotation)"],
        13,
    ),
    case(
        "launch-empty-list",
        BASE.replace("launch: ros2 launch planner planner.launch.py", "launch: []"),
        f"{PLANNER}.launch",
        ["expected a command line or a non-empty list"],
        13,
    ),
    case(
        "dependency-unknown",
        planner("dependencies: {perceptio: ^0.1}"),
        f"{PLANNER}.dependencies.perceptio",
        ["'perceptio' is not a module of the catalog; did you mean 'perception'?"],
        14,
    ),
    case(
        "dependency-on-itself",
        planner("dependencies: {planner: ^1}"),
        f"{PLANNER}.dependencies.planner",
        ["planner cannot depend on itself"],
        14,
    ),
    case(
        "dependency-bad-range",
        planner("dependencies: {perception: '>>0.1'}"),
        f"{PLANNER}.dependencies.perception",
        ["'>>0.1' is not a valid version range: '>>0.1' has two operators"],
        14,
    ),
    case(
        "dependency-unsatisfiable",
        planner("dependencies: {perception: ^1}"),
        f"{PLANNER}.dependencies.perception",
        ["no version of perception satisfies ^1 (versions: 0.1.0)"],
        14,
    ),
    case(
        "dependency-range-a-number",
        planner("dependencies: {perception: 1}"),
        f"{PLANNER}.dependencies.perception",
        ["1 (int) is not valid", "a version range string"],
        14,
    ),
    case(
        "dependency-bad-name",
        planner("dependencies: {Perception: ^0.1}"),
        f"{PLANNER}.dependencies.Perception",
        ["'Perception' is not a valid name; expected the name of a catalog module"],
        14,
    ),
    case(
        "interfaces-float",
        planner("interfaces: {pnp_msgs: 1.5}"),
        f"{PLANNER}.interfaces.pnp_msgs",
        ["1.5 (float) is not valid", "a whole number"],
        14,
    ),
    case(
        "interfaces-bad-name",
        planner("interfaces: {pnp-msgs: 1}"),
        f"{PLANNER}.interfaces.pnp-msgs",
        ["is not a valid name; expected an interface name"],
        14,
    ),
    case(
        "upgrade-unknown",
        planner("upgrade: rolling"),
        f"{PLANNER}.upgrade",
        ["'rolling' is not valid; expected surge or recreate"],
        14,
    ),
    case("ros-distro-bad", planner("rosDistro: Jazzy!"), f"{PLANNER}.rosDistro", ["expected a ROS 2 distribution"], 14),
    case("architectures-empty", planner("architectures: []"), f"{PLANNER}.architectures", ["a non-empty list of distinct"], 14),
    case(
        "architectures-repeated", planner("architectures: [amd64, amd64]"), f"{PLANNER}.architectures", ["repeated entries"], 14
    ),
    case(
        "arch-outside-architectures",
        planner("architectures: [arm64]", "requirements: {arch: amd64}"),
        f"{PLANNER}.requirements.arch",
        ["'amd64' shares no architecture with architectures (arm64)"],
        15,
    ),
    case(
        "cpu-bad",
        planner("resources: {cpu: lots}"),
        f"{PLANNER}.resources.cpu",
        ["'lots' is not valid; expected a CPU quantity"],
        14,
    ),
    case("memory-zero", planner("resources: {memory: 0}"), f"{PLANNER}.resources.memory", ["must be more than zero"], 14),
    case(
        "latency-bad",
        planner("requirements: {max_latency: 2 parsecs}"),
        f"{PLANNER}.requirements.max_latency",
        ["'2 parsecs' is not valid"],
        14,
    ),
    case("env-reserved", planner("env: {ROS_DOMAIN_ID: 3}"), f"{PLANNER}.env.ROS_DOMAIN_ID", ["is set by KubeROS"], 14),
    case("env-kuberos", planner("env: {KUBEROS_X: 3}"), f"{PLANNER}.env.KUBEROS_X", ["reserved for KubeROS"], 14),
    case(
        "preference-contradicts-onboard",
        planner("preference: cloud", "requirements: {onboard: true}"),
        f"{PLANNER}.preference",
        ["'cloud' contradicts requirements.onboard: true"],
        14,
    ),
    case("preference-unknown", planner("preference: sky"), f"{PLANNER}.preference", ["expected one of onboard, edge, cloud"], 14),
    case(
        "duplicate-key",
        planner("image: registry/other:1.0"),
        f"{PLANNER}.image",
        ["duplicate key (first written on line 12)"],
        14,
    ),
    case("not-yaml", BASE + "  - [unclosed\n", "", ["not valid YAML"], None),
    case("control-character", BASE + "x: \x1f\n", "x", ["control character U+001F in column 4"], 14),
    case("python-tag", BASE + "x: !!python/object/apply:os.system [echo]\n", "", ["not valid YAML"], 14),
]


@pytest.mark.parametrize(("text", "path", "contains", "line"), CATALOG_CASES)
def test_bad_catalog(tmp_path, text, path, contains, line):
    (tmp_path / "pnp.yml").write_text(text, encoding="utf-8")
    with pytest.raises(SpecError) as info:
        load_catalog(str(tmp_path), "site/catalog")
    assert info.value.title == "site/catalog is not a valid software catalog"
    assert_problem(info.value, "site/catalog/pnp.yml", path, contains, line)


def test_all_problems_of_all_files_at_once(tmp_path):
    (tmp_path / "a.yml").write_text(planner("upgrade: rolling", "digest: bad"), encoding="utf-8")
    (tmp_path / "b.yaml").write_text(
        BASE.replace("perception", "viz").replace("name: planner", "name: planner"), encoding="utf-8"
    )
    with pytest.raises(SpecError) as info:
        load_catalog(tmp_path, "cat")
    paths = {(p.source, p.path) for p in info.value.problems}
    assert ("cat/a.yml", f"{PLANNER}.upgrade") in paths and ("cat/a.yml", f"{PLANNER}.digest") in paths
    # planner is in both files
    assert_problem(
        info.value, "cat/b.yaml", "modules[1].name", ["'planner' is already a module of the catalog (at cat/a.yml:9)"], 9
    )


def test_a_broken_version_leaves_the_others_checked(tmp_path):
    text = planner("dependencies: {nothing: ^1}") + "  - version: 1.1.0\n    image: Bad\n    launch: run\n"
    (tmp_path / "a.yml").write_text(text, encoding="utf-8")
    with pytest.raises(SpecError) as info:
        load_catalog(tmp_path, "cat")
    assert {p.path for p in info.value.problems} == {
        "modules[1].versions[1].image",
        "modules[1].versions[0].dependencies.nothing",
    }


def test_dependency_on_a_module_whose_versions_are_broken_is_not_unknown(tmp_path):
    text = planner("dependencies: {perception: ^0.1}").replace("registry/perception:0.1", "Bad")
    (tmp_path / "a.yml").write_text(text, encoding="utf-8")
    with pytest.raises(SpecError) as info:
        load_catalog(tmp_path, "cat")
    assert [p.path for p in info.value.problems] == ["modules[0].versions[0].image"]


def test_multi_document_file_names_the_document(tmp_path):
    (tmp_path / "a.yml").write_text(BASE + "---\n" + planner("upgrade: x").replace("perception", "viz").replace("planner", "nav"))
    with pytest.raises(SpecError) as info:
        load_catalog(tmp_path, "cat")
    assert_problem(info.value, "cat/a.yml (document 2)", f"{PLANNER}.upgrade", ["expected surge or recreate"], 28)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"\xff\xfe" + "x: 1\n".encode("utf-16-le"), "not UTF-8 text (byte 0)"),
        (b"a: " + b"x" * (1024 * 1024), "file is larger than 1048576 bytes"),
        (b"x: [" * 200, "document too large"),
        (b"a: &a [1, 2]\nb: *a\nc: *a\na: 1\n", "duplicate key"),
    ],
)
def test_hostile_files(tmp_path, content, message):
    (tmp_path / "x.yml").write_bytes(content)
    with pytest.raises(SpecError) as info:
        load_catalog(tmp_path, "cat")
    assert message in str(info.value) and "cat/x.yml" in str(info.value)


def test_unreadable_file(tmp_path):
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling.yml")
    (tmp_path / "ok.yml").write_text(BASE)
    assert load_catalog(tmp_path).names() == ["perception", "planner"]  # a dangling link is not a file


# --------------------------------------------------------------------------------------------
# Specs that name catalog modules
# --------------------------------------------------------------------------------------------


def spec(*modules: str, fleet: str = "test-fleet", extra: str = "") -> str:
    """A spec whose modules are given as YAML text; the first module starts on line 5 (plus ``extra`` lines)."""
    head = f"metadata:\n  name: demo\n  targetFleet: {fleet}\n{extra}rosModules:\n"
    return head + "".join(modules)


def module(name: str, ref: str, *lines: str) -> str:
    return "- name: " + name + "\n  module: " + ref + "\n" + "".join(f"  {line}\n" for line in lines)


PNP_01 = (
    module("perception", "pnp-perception@^0.1"),
    module("planner", "pnp-planner@^0.1"),
    module("control", "pnp-control@^0.1"),
)


def test_spec_helper_layout():
    text = spec(*PNP_01)
    assert text.splitlines()[4:8] == [
        "- name: perception",
        "  module: pnp-perception@^0.1",
        "- name: planner",
        "  module: pnp-planner@^0.1",
    ]


def test_resolution_and_defaults(example):
    (dep,) = load_rosdeployments(spec(*PNP_01), "app.yml", catalog=example)
    perception, planner, control = dep.modules
    assert (planner.catalog_module, planner.version, planner.ros_distro) == ("pnp-planner", "0.1.0", "jazzy")
    assert planner.image == "ghcr.io/kuberos/pnp-planner:0.1" and planner.launch == ("python3 -m kuberos_pnp.planner",)
    assert planner.tiers == ("cloud", "edge", "onboard") and planner.requirements.max_latency_ms == 200.0
    assert planner.ros_parameters == {"planner": "RRTConnect", "planning_time": 2.0, "parallel_plans": 1}
    assert (planner.resources.cpu_millis, planner.resources.memory_bytes) == (2000, 2 * 1024**3)
    assert perception.tiers == ("edge", "cloud") and perception.requirements.arch == ("amd64",)
    assert control.tiers == ("onboard",) and control.requirements.devices == ("gripper",) and control.upgrade == "recreate"
    assert planner.upgrade == "surge"


def test_highest_version_without_a_range(example):
    refs = ("pnp-perception", "pnp-planner", "pnp-control")
    (dep,) = load_rosdeployments(spec(*(module(r.split("-")[1], r) for r in refs)), "app.yml", catalog=example)
    assert [m.version for m in dep.modules] == ["0.2.0", "0.2.0", "0.2.0"]
    assert dep.modules[1].requirements.arch == ("amd64", "arm64")
    assert dep.modules[1].image == "ghcr.io/kuberos/pnp-planner:0.2.0"


def test_spec_fields_override_the_catalog(data):
    text = spec(
        module(
            "arm",
            "arm-driver@~1.1",
            "launch: [ros2 launch arm_driver other.launch.py]",
            "requirements: {max_latency: 10 ms}",
            "resources: {cpu: 2}",
            "rosParameters: {driver: {limits: {speed: 0.5}}, extra: 1}",
            "env: {LOG_LEVEL: debug}",
            "upgrade: surge",
        ),
        module("nav", "nav", "preference: [edge]", "requirements: {arch: arm64}", "strategy: shared"),
    )
    (dep,) = load_rosdeployments(text, "app.yml", catalog=data)
    arm, nav = dep.modules
    assert arm.version == "1.1.0" and arm.launch == ("ros2 launch arm_driver other.launch.py",)
    assert arm.requirements.onboard and arm.requirements.devices == ("gripper",) and arm.requirements.max_latency_ms == 10
    assert (arm.resources.cpu_millis, arm.resources.memory_bytes) == (2000, 128 * 1024**2)
    assert arm.ros_parameters == {"driver": {"rate_hz": 100, "limits": {"speed": 0.5, "force": 20}}, "extra": 1}
    assert arm.env == (("LOG_LEVEL", "debug"), ("ARM_MODEL", "ur5"))
    assert arm.upgrade == "surge"  # the spec's, over the default for hardware
    assert nav.tiers == ("edge",) and nav.requirements.arch == ("arm64",) and nav.requirements.max_latency_ms == 100
    assert nav.strategy == "shared" and nav.upgrade == "surge"
    # the catalog entry itself is unchanged by the merge
    assert data.resolve("arm-driver", "~1.1").ros_parameters == {
        "driver": {"rate_hz": 100, "limits": {"speed": 1.0, "force": 20}}
    }


def test_upgrade_default_and_catalog_value(data):
    (dep,) = load_rosdeployments(spec(module("a", "arm-driver@^1"), module("b", "lidar")), "app.yml", catalog=data)
    assert [m.upgrade for m in dep.modules] == ["recreate", "surge"]  # devices -> recreate
    (dep,) = load_rosdeployments(spec(module("a", "arm-driver@^2")), "app.yml", catalog=data)
    assert dep.modules[0].upgrade == "surge"  # the catalog says so
    assert dep.modules[0].image.endswith("@" + DIGEST)
    (dep,) = load_rosdeployments(spec(module("a", "arm-driver@^2", "upgrade: recreate")), "app.yml", catalog=data)
    assert dep.modules[0].upgrade == "recreate"


def test_onboard_in_the_spec_drops_the_catalogs_preference(data):
    (dep,) = load_rosdeployments(spec(module("l", "lidar", "requirements: {onboard: true}")), "app.yml", catalog=data)
    assert dep.modules[0].tiers == ("onboard",)


def test_plain_modules_are_unchanged_and_mix_with_catalog_modules(example):
    plain = "- name: viewer\n  image: registry/viewer:1\n  launch: run\n  requirements: {devices: [camera]}\n"
    (dep,) = load_rosdeployments(spec(*PNP_01, plain), "app.yml", catalog=example)
    viewer = dep.modules[3]
    assert (viewer.version, viewer.catalog_module, viewer.ros_distro, viewer.upgrade) == ("", "", "", "recreate")
    assert (
        parse_rosdeployment(
            {"metadata": {"name": "a", "targetFleet": "f"}, "rosModules": [{"name": "m", "image": "i", "launch": "run"}]}
        )
        .modules[0]
        .upgrade
        == "surge"
    )


def test_service_passes_the_catalog(example, local_raw, tmp_path):
    path = tmp_path / "app.yml"
    path.write_text(spec(*PNP_01))
    (dep,) = service.load_specs(str(path), catalog=example)
    assert dep.modules[0].version == "0.1.0"
    data = {
        "metadata": {"name": "a", "targetFleet": "test-fleet"},
        "rosModules": [{"name": "p", "module": "pnp-perception@0.1.0"}],
    }
    assert service.load_specs(data, catalog=example)[0].modules[0].version == "0.1.0"
    assert service.load_specs([data], catalog=example)[0].modules[0].version == "0.1.0"
    deployments, placement = service.load_and_place(str(path), local_raw, catalog=example)
    assert deployments[0].name == "demo" and placement.instances
    with pytest.raises(SpecError, match="no catalog given"):
        service.load_specs(data)


def test_catalog_must_be_a_catalog(example):
    with pytest.raises(TypeError):
        load_rosdeployments(spec(*PNP_01), "app.yml", catalog=example.to_dict())


# Each case: spec text, path, substrings, line. The catalog is the example's, unless the id says "data".
SPEC_CASES = [
    case(
        "unknown-module",
        spec(module("p", "pnp-planer@^0.1")),
        "rosModules[0].module",
        [
            "'pnp-planer' is not a module of the catalog inventories/local/catalog; did you mean 'pnp-planner'?",
            "(modules: pnp-control, pnp-coordinator, pnp-perception, pnp-planner)",
        ],
        6,
    ),
    case(
        "malformed-reference",
        spec(module("p", "PnP-Planner@^0.1")),
        "rosModules[0].module",
        ["'PnP-Planner@^0.1' is not valid; expected a catalog module reference such as 'pnp-planner@^0.2'"],
        6,
    ),
    case("empty-range", spec(module("p", "'pnp-planner@'")), "rosModules[0].module", ["expected a catalog module reference"], 6),
    case(
        "malformed-range",
        spec(module("p", "'pnp-planner@>>0.1'")),
        "rosModules[0].module",
        ["invalid version range after 'pnp-planner@': '>>0.1' has two operators"],
        6,
    ),
    case(
        "no-version-satisfies",
        spec(module("p", "pnp-planner@^2")),
        "rosModules[0].module",
        ["no version of pnp-planner satisfies ^2 (versions: 0.1.0, 0.2.0)"],
        6,
    ),
    case(
        "dependency-missing",
        spec(module("p", "pnp-planner@^0.2")),
        "rosModules[0].module",
        ["pnp-planner 0.2.0 depends on pnp-perception ^0.2; the deployment has no module from pnp-perception"],
        6,
    ),
    case(
        "dependency-outside-range",
        spec(module("v", "pnp-perception@^0.2"), module("p", "pnp-planner@^0.1")),
        "rosModules[1].module",
        ["pnp-planner 0.1.0 depends on pnp-perception ^0.1; rosModules[0] (v) uses pnp-perception 0.2.0"],
        8,
    ),
    case(
        "interfaces-mismatch",
        spec(module("v", "pnp-perception@^0.2"), module("p", "pnp-planner@^0.1")),
        "rosModules[1].module",
        ["pnp-planner 0.1.0 speaks interface pnp_msgs version 1, but rosModules[0] (v: pnp-perception 0.2.0) speaks version 2"],
        8,
    ),
    case(
        "module-and-image",
        spec(module("p", "pnp-planner@^0.1", "image: registry/p:1")),
        "rosModules[0].module",
        ["give either module or image and launch, not both"],
        6,
    ),
    case("neither-module-nor-image", spec("- name: p\n  launch: run\n"), "rosModules[0]", ["missing required field 'image'"], 5),
    case("neither-module-nor-launch", spec("- name: p\n  image: i\n"), "rosModules[0]", ["missing required field 'launch'"], 5),
    case(
        "upgrade-unknown",
        spec(module("p", "pnp-perception", "upgrade: rolling")),
        "rosModules[0].upgrade",
        ["'rolling' is not valid; expected surge or recreate"],
        7,
    ),
    case(
        "arch-shares-nothing",
        spec(module("v", "pnp-perception@^0.1", "requirements: {arch: arm64}")),
        "rosModules[0].requirements.arch",
        ["'arm64' shares no architecture with pnp-perception 0.1.0, whose image is built for amd64"],
        7,
    ),
    case(
        "catalog-preference-contradicts-spec-onboard",
        spec(module("v", "pnp-perception@^0.1", "requirements: {onboard: true}", "preference: cloud")),
        "rosModules[0].preference",
        ["contradicts requirements.onboard: true"],
        8,
    ),
    case(
        "data-ros-distro",
        spec(module("a", "arm-driver@^2"), module("n", "nav")),
        "rosModules[1].module",
        [
            "nav 0.3.0 is built for ROS 2 humble, but rosModules[0] (a: arm-driver 2.0.0) is built for jazzy",
            "expected one rosDistro in a deployment",
        ],
        8,
    ),
    case(
        "data-dependency-outside-range",
        spec(module("a", "arm-driver@^2"), module("n", "nav")),
        "rosModules[1].module",
        ["nav 0.3.0 depends on arm-driver >=1.0.0 <2.0.0; rosModules[0] (a) uses arm-driver 2.0.0"],
        8,
    ),
    case(
        "data-interfaces",
        spec(module("a", "viz"), module("b", "viz-bridge")),
        "rosModules[1].module",
        ["viz-bridge 1.0.0 speaks interface viz_msgs version 2, but rosModules[0] (a: viz 1.0.0) speaks version 1"],
        8,
    ),
    case(
        "data-prerelease-not-chosen",
        spec(module("a", "arm-driver@>1.1.0 <2")),
        "rosModules[0].module",
        ["no version of arm-driver satisfies >1.1.0 <2"],
        6,
    ),
]


@pytest.mark.parametrize(("text", "path", "contains", "line"), SPEC_CASES)
def test_bad_spec_with_catalog(request, example, data, text, path, contains, line):
    catalog = data if request.node.callspec.id.startswith("data-") else example
    with pytest.raises(SpecError) as info:
        load_rosdeployments(text, "specs/app.yml", catalog=catalog)
    assert_problem(info.value, "specs/app.yml", path, contains, line)


def test_no_catalog_given():
    with pytest.raises(SpecError) as info:
        load_rosdeployments(spec(*PNP_01), "specs/app.yml")
    assert_problem(
        info.value,
        "specs/app.yml",
        "rosModules[1].module",
        ["'pnp-planner@^0.1' names a catalog module, but no catalog given; set kuberos_catalog"],
        8,
    )
    # one problem per module, no follow-up dependency problems
    assert len(info.value.problems) == 3


def test_no_catalog_at_the_path(tmp_path):
    catalog = load_catalog(tmp_path / "catalog", "inventories/site/catalog")
    with pytest.raises(SpecError) as info:
        load_rosdeployments(spec(module("p", "pnp-perception")), "specs/app.yml", catalog=catalog)
    assert_problem(
        info.value,
        "specs/app.yml",
        "rosModules[0].module",
        ["'pnp-perception' is not in the catalog: no catalog at inventories/site/catalog"],
        6,
    )


def test_an_unresolved_module_does_not_also_fail_its_dependents(example):
    text = spec(module("v", "pnp-perception@^9"), module("p", "pnp-planner@^0.1"))
    with pytest.raises(SpecError) as info:
        load_rosdeployments(text, "specs/app.yml", catalog=example)
    assert [p.path for p in info.value.problems] == ["rosModules[0].module"]


def test_all_problems_of_a_spec_at_once(example):
    text = spec(module("v", "pnp-perception@^0.2"), module("p", "pnp-planner@^0.1"), module("x", "nothing"))
    with pytest.raises(SpecError) as info:
        load_rosdeployments(text, "specs/app.yml", catalog=example)
    messages = [p.message for p in info.value.problems]
    assert any("depends on pnp-perception" in m for m in messages)
    assert any("speaks interface pnp_msgs" in m for m in messages)
    assert any("'nothing' is not a module" in m for m in messages)


# --------------------------------------------------------------------------------------------
# Architectures against the inventory
# --------------------------------------------------------------------------------------------


def test_example_matches_the_local_inventory(example, local_inventory):
    deployments = load_rosdeployment_file(os.path.join(ROOT, "examples", "pick-and-place-catalog.yml"), catalog=example)
    assert catalog_problems_against_inventory(deployments, local_inventory) == []


ARCH_CASES = [
    # lidar is built for arm64 only; in inventories/local only tiago-2 (warehouse-fleet, onboard) is arm64.
    pytest.param("test-fleet", "", [], "rosModules[0].module", id="edge-and-cloud-of-test-fleet"),
    pytest.param("warehouse-fleet", "", [], "rosModules[0].module", id="edge-and-cloud-of-warehouse-fleet"),
    pytest.param("warehouse-fleet", "", ["preference: [edge, onboard]"], None, id="onboard-tiago-2"),
    pytest.param("test-fleet", "", ["preference: [edge, onboard]"], "rosModules[0].module", id="onboard-fetch-is-amd64"),
    pytest.param(
        "warehouse-fleet",
        "  robotSelector: {robot: [tiago-1]}\n",
        ["preference: onboard"],
        "rosModules[0].module",
        id="only-tiago-1-selected",
    ),
]


@pytest.mark.parametrize(("fleet", "extra", "lines", "path"), ARCH_CASES)
def test_architectures_against_the_inventory(data, local_inventory, fleet, extra, lines, path):
    text = spec(module("lidar", "lidar", *lines), fleet=fleet, extra=extra)
    deployments = load_rosdeployments(text, "specs/app.yml", catalog=data)
    problems = catalog_problems_against_inventory(deployments, local_inventory)
    if path is None:
        assert problems == []
        return
    (problem,) = problems
    assert problem.path == path and problem.source == "specs/app.yml"
    assert problem.line == 5 + extra.count("\n") + 1
    assert problem.message.startswith("lidar 0.1.0 runs on arm64, but no ")
    assert f"node of fleet {fleet} has that architecture (nodes: amd64 (" in problem.message


def test_architecture_check_skips_what_it_cannot_judge(data, local_inventory, example):
    # plain modules (the scheduler checks their arch), unknown fleets (reported by the scheduler)
    plain = spec("- name: p\n  image: i\n  launch: run\n  requirements: {arch: sparc}\n")
    unknown_fleet = spec(module("lidar", "lidar"), fleet="nowhere")
    deployments = load_rosdeployments(plain, "a.yml") + load_rosdeployments(unknown_fleet, "b.yml", catalog=data)
    assert catalog_problems_against_inventory(deployments, local_inventory) == []


def test_catalog_entry_is_hashable_and_frozen(data):
    entry = data.resolve("lidar")
    assert hash(entry) == hash(dataclasses.replace(entry))
    with pytest.raises(dataclasses.FrozenInstanceError):
        entry.version = "9.9.9"
    assert isinstance(entry, CatalogEntry) and entry.label == "lidar 0.1.0"


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=60), st.sampled_from(["", "  launch: run\n", "  image: i\n", "  upgrade: recreate\n"]))
def test_hostile_module_references_only_raise_spec_error(reference, extra):
    text = (
        f"metadata: {{name: demo, targetFleet: test-fleet}}\nrosModules:\n- name: m\n  module: {json.dumps(reference)}\n{extra}"
    )
    try:
        load_rosdeployments(text, "app.yml", catalog=load_catalog(EXAMPLE_CATALOG))
    except SpecError:
        pass


@settings(max_examples=150, deadline=None)
@given(st.text(max_size=200))
def test_hostile_catalog_text_only_raises_spec_error(tmp_path_factory, text):
    folder = tmp_path_factory.mktemp("catalog")
    (folder / "x.yml").write_text(BASE + text, encoding="utf-8", errors="surrogatepass")
    try:
        load_catalog(folder)
    except SpecError:
        pass
