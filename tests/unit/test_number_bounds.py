"""Numbers in a spec are finite and bounded (issue 44): NaN, infinities and out-of-range values of every number field
are refused with file:line:field and the bound, never accepted (a NaN rate went into the probe's environment as
invalid JSON) and never a traceback (a 400-digit deadline was "inf ms"; as a number it raised OverflowError).

One row per field and value: the module's extra lines (from line 8 of tests/helpers.SPEC_BASE), the field path, the
line, and fragments of the reason.
"""

from __future__ import annotations

import json

import pytest
from helpers import CATALOG_BASE, SPEC_BASE

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import catalog, errors, spec, yaml_source
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.schema import SCHEMA
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import Expectation, expectations

SOURCE = "specs/numbers.yml"
BIG = "9" * 400


def module(*lines: str) -> str:
    return SPEC_BASE + "".join(f"  {line}\n" for line in lines)


def top(*lines: str) -> str:
    return SPEC_BASE + "".join(f"{line}\n" for line in lines)


def published(fields: str) -> str:
    """A module publishing one topic with ``fields`` (line 10)."""
    return module("topics:", "  publishes:", f"  - {{name: a, type: x/msg/A, {fields}}}")


TOPIC = "rosModules[0].topics.publishes[0]"
NOT_FINITE = "not a finite number"
CASES = [
    # rates: NaN passed every comparison, so the schema's minimum and maximum let it through
    (published("rate: {max: .nan}"), f"{TOPIC}.rate.max", 10, ["nan (float) is not valid", NOT_FINITE, "a rate in Hz"]),
    (published("rate: {min: .nan}"), f"{TOPIC}.rate.min", 10, ["nan (float)", NOT_FINITE]),
    (published("rate: {min: .inf}"), f"{TOPIC}.rate.min", 10, ["inf (float)", NOT_FINITE]),
    (published(f"rate: {{max: {BIG}}}"), f"{TOPIC}.rate.max", 10, ["must be at most 100000"]),
    # QoS durations: a string of 400 digits was inf ms, a number of 400 digits an OverflowError
    (published(f"qos: {{deadline: '{BIG} ms'}}"), f"{TOPIC}.qos.deadline", 10, ["'9999", "must be at most 86400 s"]),
    (published(f"qos: {{deadline: {BIG}}}"), f"{TOPIC}.qos.deadline", 10, ["9999", "must be at most 86400 s"]),
    (published("qos: {deadline: .inf}"), f"{TOPIC}.qos.deadline", 10, ["inf (float)", NOT_FINITE]),
    (published("qos: {deadline: 25 h}"), f"{TOPIC}.qos.deadline", 10, ["'25 h' is not valid", "a duration"]),
    (published("qos: {deadline: 86401 s}"), f"{TOPIC}.qos.deadline", 10, ["must be at most 86400 s"]),
    (published(f"qos: {{lease_duration: '{BIG} s'}}"), f"{TOPIC}.qos.lease_duration", 10, ["must be at most 86400 s"]),
    (published(f"qos: {{depth: {BIG}}}"), f"{TOPIC}.qos.depth", 10, ["must be at most 100000"]),
    # requirements and resources
    (module(f"requirements: {{max_latency: {BIG}}}"), "rosModules[0].requirements.max_latency", 8, ["must be at most 60 s"]),
    (module(f"requirements: {{max_latency: '{BIG} s'}}"), "rosModules[0].requirements.max_latency", 8, ["at most 60 s"]),
    (module("requirements: {max_latency: -.inf}"), "rosModules[0].requirements.max_latency", 8, [NOT_FINITE]),
    (module(f"resources: {{cpu: {BIG}}}"), "rosModules[0].resources.cpu", 8, ["must be at most 1024 CPUs"]),
    (module(f"resources: {{cpu: '{BIG}m'}}"), "rosModules[0].resources.cpu", 8, ["must be at most 1024 CPUs"]),
    (module("resources: {cpu: .nan}"), "rosModules[0].resources.cpu", 8, [NOT_FINITE]),
    (module(f"resources: {{memory: {BIG}}}"), "rosModules[0].resources.memory", 8, ["must be at most 64Ti"]),
    (module(f"resources: {{memory: '{BIG}Gi'}}"), "rosModules[0].resources.memory", 8, ["must be at most 64Ti"]),
    (module(f"resources: {{gpu: {BIG}}}"), "rosModules[0].resources.gpu", 8, ["must be at most 16"]),
    # scaling
    (module("strategy: shared", "scaling: {maxInstances: 2, target: .nan}"), "rosModules[0].scaling.target", 9, [NOT_FINITE]),
    (module("strategy: shared", f"scaling: {{maxInstances: {BIG}}}"), "rosModules[0].scaling.maxInstances", 9, ["at most 1000"]),
    (module("strategy: shared", f"scaling: {{maxInstances: 2, drainTime: {BIG}}}"), "rosModules[0].scaling.drainTime", 9,
     ["must be at most 3600 s"]),
    (module("strategy: shared", "scaling: {maxInstances: 2, scaleDownWindow: 2 h}"), "rosModules[0].scaling.scaleDownWindow",
     9, ["'2 h' is not valid"]),
    (module("strategy: shared", "scaling: {maxInstances: 2, scaleUpWindow: 3601 s}"), "rosModules[0].scaling.scaleUpWindow",
     9, ["must be at most 3600 s"]),
    (module(f"robotsPerInstance: {BIG}", "strategy: shared"), "rosModules[0].robotsPerInstance", 8, ["must be at most 1000"]),
    (module(f"user: {BIG}"), "rosModules[0].user", 8, ["must be at most 2147483647"]),
    # values written into the container: a NaN in an environment variable or a launch argument
    (module("env: {RATIO: .nan}"), "rosModules[0].env.RATIO", 8, [NOT_FINITE]),
    (module("launchArguments: {ratio: -.inf}"), "rosModules[0].launchArguments.ratio", 8, [NOT_FINITE]),
    # the deployment's own numbers
    (top(f"rosDomainId: {BIG}"), "rosDomainId", 8, ["must be at most 232"]),
    (top(f"discovery: {{port: {BIG}}}"), "discovery.port", 8, ["must be at most 65535"]),
    (top("discovery: {servers: .inf}"), "discovery.servers", 8, [NOT_FINITE]),
]  # fmt: skip


@pytest.mark.parametrize(("text", "path", "line", "contains"), CASES, ids=[f"{c[1]}-{i}" for i, c in enumerate(CASES)])
def test_a_number_out_of_range_is_refused_at_its_field_with_the_bound(text, path, line, contains):
    with pytest.raises(errors.SpecError) as caught:
        spec.load_rosdeployments(text, SOURCE)
    rendered = [str(p) for p in caught.value.problems]
    assert len(rendered) == 1, rendered
    assert rendered[0].startswith(f"{SOURCE}:{line}: {path}: "), rendered
    for fragment in contains:
        assert fragment in rendered[0], rendered


@pytest.mark.parametrize(
    "text",
    [
        published("rate: {min: 100000, max: 100000}, qos: {deadline: 86400 s, lease_duration: 86400000, depth: 100000}"),
        module("requirements: {max_latency: 60 s}", "resources: {cpu: 1024, memory: 64Ti, gpu: 16}"),
        module("resources: {cpu: 1024000m, memory: 70368744177664}"),
        module("strategy: shared", "scaling: {maxInstances: 1000, drainTime: 3600 s, scaleUpWindow: 3600000}"),
    ],
    ids=["topic", "resources", "resources-in-units", "scaling"],
)
def test_the_bounds_themselves_are_accepted(text):
    (deployment,) = spec.load_rosdeployments(text, SOURCE)
    assert deployment.modules[0].name == "planner"


def test_an_integer_longer_than_python_reads_is_refused_where_it_is_written():
    """int() refuses more than 4300 decimal digits: the YAML reader raised ValueError with a traceback."""
    with pytest.raises(errors.SpecError) as caught:
        spec.load_rosdeployments(module(f"env: {{X: {'9' * 5000}}}"), SOURCE)
    (problem,) = caught.value.problems
    assert str(problem) == (
        f"{SOURCE}:8: rosModules[0].env.X: an integer of 5000 characters; expected at most "
        f"{yaml_source.MAX_INTEGER_DIGITS} digits"
    )


def test_the_catalog_refuses_them_too(tmp_path):
    path = tmp_path / "catalog.yml"
    path.write_text(
        CATALOG_BASE
        + f"    resources: {{cpu: '{BIG}'}}\n    topics:\n      publishes: [{{name: a, type: x/msg/A, rate: {{max: .nan}}}}]\n"
    )
    with pytest.raises(errors.SpecError) as caught:
        catalog.load_catalog(str(path), "catalog.yml")
    rendered = sorted(str(p) for p in caught.value.problems)
    assert len(rendered) == 2, rendered
    assert rendered[0].startswith("catalog.yml:14: modules[1].versions[0].resources.cpu: ") and "at most 1024" in rendered[0]
    assert rendered[1].startswith("catalog.yml:16: modules[1].versions[0].topics.publishes[0].rate.max: "), rendered
    assert NOT_FINITE in rendered[1]


def test_what_the_probe_receives_is_valid_json():
    text = published("rate: {min: 0.5, max: 100000}, qos: {deadline: 86400 s}")
    (deployment,) = spec.load_rosdeployments(text, SOURCE)
    wanted = [e.to_dict() for e in expectations(deployment.modules)]
    assert json.loads(json.dumps(wanted, allow_nan=False)) == wanted


def _number_fields(node, path=()):
    """(path, schema) of every schema in ``node`` that admits a number."""
    if isinstance(node, dict):
        kinds = node.get("type")
        kinds = kinds if isinstance(kinds, list) else [kinds]
        if "number" in kinds or "integer" in kinds:
            yield path, node
        for key, value in node.items():
            yield from _number_fields(value, (*path, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _number_fields(value, (*path, index))


# Numbers written as text into the container (an environment variable's value, a launch argument): any finite number
# is text there, so they have no range; NaN and infinities are refused like everywhere else.
UNBOUNDED = {"env", "launchArguments"}


def test_every_number_field_of_the_schema_has_a_maximum():
    fields = list(_number_fields(SCHEMA))
    assert len(fields) > 20
    for path, schema in fields:
        if UNBOUNDED & set(path):
            continue
        assert "maximum" in schema or "exclusiveMaximum" in schema, path
        if "string" in (schema["type"] if isinstance(schema["type"], list) else [schema["type"]]):
            assert "x-maximum" in schema, f"{path}: a quantity written as text needs its bound as text too"


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_the_probe_refuses_an_expectation_whose_rate_is_not_finite(value):
    """Python's json reads NaN and Infinity; the probe takes no such bound however the expectation was made."""
    with pytest.raises(ValueError, match=r"rate_max .* is not a finite number"):
        Expectation.from_dict({"name": "/{robot}/a", "type": "x/msg/A", "rate_max": value})
