"""Patterns end where the text ends (issue 44): Python's ``$`` also matches before a final line feed, so that
``'alice\\n'`` passed ``^[A-Za-z0-9]...$`` wherever a pattern was matched with ``re`` (the pool's owner is checked
with the schema's DEVELOPER). Every pattern of the RosDeployment schema is tried programmatically, so that a new
pattern ending in a bare ``$`` fails here; the schema stays ECMA-262 (what JSON Schema's editors read), so it ends
patterns with ``$(?!\\n)``, not Python's ``\\Z``.
"""

from __future__ import annotations

import importlib
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import catalog, schema
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.validation import strict_validator

PACKAGE = "ansible_collections.kuberos.platform.plugins.module_utils"


def _patterns(node):
    """Every ``pattern`` of a JSON Schema, wherever it is nested."""
    if isinstance(node, dict):
        if isinstance(node.get("pattern"), str):
            yield node["pattern"]
        for value in node.values():
            yield from _patterns(value)
    elif isinstance(node, list):
        for value in node:
            yield from _patterns(value)


SCHEMA_PATTERNS = sorted(set(_patterns(schema.SCHEMA)))


def test_the_schema_has_the_patterns_this_file_tries():
    assert len(SCHEMA_PATTERNS) >= 15
    assert schema.DEVELOPER in SCHEMA_PATTERNS and schema.DECLARED_TOPIC in SCHEMA_PATTERNS


@pytest.mark.parametrize("pattern", SCHEMA_PATTERNS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data())
def test_every_schema_pattern_refuses_its_own_match_with_a_trailing_line_break(pattern, data):
    text = data.draw(st.from_regex(pattern, fullmatch=True))
    assert re.search(pattern, text), (pattern, text)
    assert not re.search(pattern, text + "\n"), f"{pattern!r} takes {text + chr(10)!r}"
    validator = strict_validator({"type": "string", "pattern": pattern})
    assert validator.is_valid(text) and not validator.is_valid(text + "\n")


@pytest.mark.parametrize("pattern", SCHEMA_PATTERNS)
def test_schema_patterns_are_ecma_262_too(pattern):
    """The editors that read docs/rosdeployment.schema.json use ECMA-262, which has no \\A or \\Z."""
    assert "\\Z" not in pattern and "\\A" not in pattern and "\\z" not in pattern


@pytest.mark.parametrize(
    ("pattern", "text"),
    [
        (schema.DEVELOPER, "alice"),
        (schema.DNS_LABEL, "planner"),
        (schema.INVENTORY_NAME, "fetch-1"),
        (schema.LATENCY, "200 ms"),
        (schema.ABSOLUTE_PATH, "/workspace/install"),
        (schema.MODULE_REF, "pnp-planner@^0.2"),
    ],
)
def test_a_name_with_a_line_break_is_refused_where_the_code_matches_the_constant_itself(pattern, text):
    assert re.match(pattern, text)
    assert not re.match(pattern, text + "\n")
    assert not re.match(pattern, text + "\r\n")


CATALOG_PATTERNS = sorted(set(_patterns(catalog.CATALOG_SCHEMA)) - set(SCHEMA_PATTERNS))


@pytest.mark.parametrize("pattern", CATALOG_PATTERNS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data())
def test_the_catalogs_own_patterns_end_at_the_end_of_the_text_in_its_validator(pattern, data):
    """The catalog's schema is not published; its validator reads a final '$' as the end of the text."""
    text = data.draw(st.from_regex(pattern, fullmatch=True))
    validator = strict_validator({"type": "string", "pattern": pattern})
    assert validator.is_valid(text) and not validator.is_valid(text + "\n"), (pattern, text)


# Modules that match input with module-level compiled patterns; each pattern either ends with \Z, is used with
# fullmatch (no anchor), or reads many lines on purpose (re.M).
MODULES = [
    "kuberos.spec_model",
    "kuberos_deploy.ros_graph_probe",
    "kuberos_bridge.topics",
    "kuberos_cluster.calico",
    "kuberos_cluster.cilium",
    "kuberos_cluster.cloud",
    "kuberos_cluster.cni",
    "kuberos_cluster.kubeadm_config",
    "kuberos_cluster.real_node_config",
    "kuberos_cluster.vpn",
]


@pytest.mark.parametrize("name", MODULES)
def test_no_compiled_pattern_ends_with_a_bare_dollar(name):
    module = importlib.import_module(f"{PACKAGE}.{name}")
    for attribute, value in vars(module).items():
        if isinstance(value, re.Pattern) and not value.flags & re.M:
            assert not value.pattern.endswith("$"), f"{name}.{attribute} ends with '$'; end it with \\Z"


@pytest.mark.parametrize(
    ("name", "attribute", "text"),
    [
        ("kuberos_cluster.vpn", "INTERFACE_NAME", "wg0"),
        ("kuberos_cluster.vpn", "PUBLIC_KEY", "A" * 42 + "E="),
        ("kuberos_cluster.kubeadm_config", "_VERSION", "v1.31.2"),
        ("kuberos_cluster.kubeadm_config", "_IMAGE_TAG", "v1.31.2"),
        ("kuberos_cluster.kubeadm_config", "_LABEL_NAME", "zone"),
        ("kuberos_cluster.calico", "_IMAGE", "quay.io/calico/node:v3.28.0"),
        ("kuberos_bridge.topics", "TOPIC_RE", "/planning/request"),
        ("kuberos_bridge.topics", "TYPE_RE", "std_msgs/msg/String"),
        ("kuberos_deploy.ros_graph_probe", "_ROS_NAME", "/fetch_1/detections"),
    ],
)
def test_python_patterns_refuse_a_trailing_line_break(name, attribute, text):
    pattern = getattr(importlib.import_module(f"{PACKAGE}.{name}"), attribute)
    assert pattern.match(text)
    assert not pattern.match(text + "\n")
