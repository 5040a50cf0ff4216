"""Checks shared by the RosDeployment spec and the software catalog.

``schema_problems(validator, doc)`` turns every JSON Schema error of a loaded YAML document into a
``Problem`` naming the file, the line, the field path, the value and what was expected (the
schema's ``x-expected`` phrase; ``x-message`` replaces the whole message of a ``not``, reported at the
field ``x-field``).
"""

from __future__ import annotations

import shlex

import jsonschema

from .errors import Problem, describe, did_you_mean
from .yaml_source import Document, format_path

RESERVED_ENV = ("ROS_DISCOVERY_SERVER", "RMW_IMPLEMENTATION", "ROS_DOMAIN_ID")


def path_parts(data, parts) -> tuple:
    """Path parts with list positions as ints and mapping keys as strings (``1: x`` is field '1')."""
    out, node = [], data
    for part in parts:
        if isinstance(node, list) and isinstance(part, int):
            out.append(part)
            node = node[part] if 0 <= part < len(node) else None
        else:
            out.append(str(part))
            node = node.get(part) if isinstance(node, dict) else None
    return tuple(out)


def problem(doc: Document, parts: tuple, message: str) -> Problem:
    return Problem(doc.source, format_path(parts), message, doc.line_of(parts))


def _problems_of(error: jsonschema.ValidationError, doc: Document) -> list[Problem]:
    parts = path_parts(doc.data, error.absolute_path)
    schema = error.schema if isinstance(error.schema, dict) else {}
    expected = schema.get("x-expected", "")
    value = error.instance
    if error.validator == "not" and "x-message" in schema:
        field = schema.get("x-field")
        return [problem(doc, (*parts, field) if field else parts, schema["x-message"])]
    if "propertyNames" in error.absolute_schema_path:
        return [problem(doc, (*parts, str(value)), f"{describe(value)} is not a valid name; expected {expected}")]
    if error.validator == "additionalProperties" and isinstance(value, dict):
        allowed = sorted(schema.get("properties", {}))
        extras = sorted((k for k in value if k not in allowed), key=str)
        return [
            problem(doc, (*parts, str(key)), f"unknown field{did_you_mean(key, allowed)} (allowed here: {', '.join(allowed)})")
            for key in extras
        ]
    if error.validator == "required":
        missing = error.message.split("'")[1] if "'" in error.message else error.message
        return [problem(doc, parts, f"missing required field '{missing}'")]
    if error.validator == "uniqueItems":
        return [problem(doc, parts, f"has repeated entries; expected {expected}")]
    return [problem(doc, parts, f"{describe(value)} is not valid; expected {expected or error.message}")]


def schema_problems(validator: jsonschema.protocols.Validator, doc: Document) -> list[Problem]:
    """Every schema error of ``doc`` as a located ``Problem``, each field reported once."""
    problems = []
    seen = set()
    errors = sorted(validator.iter_errors(doc.data), key=lambda e: ([str(p) for p in e.absolute_path], e.validator))
    for error in errors:
        for found in _problems_of(error, doc):
            # A value that is both of the wrong type and fails a pattern is reported once.
            if found.path in seen and error.validator in ("pattern", "minimum", "type"):
                continue
            if (found.path, found.message) not in seen:
                problems.append(found)
                seen.update([(found.path, found.message), found.path])
    return problems


def as_tuple(value) -> tuple:
    if value is None:
        return ()
    if isinstance(value, (list, tuple)):
        return tuple(value)
    return (value,)


def launch_problems(launch, doc: Document, base: tuple) -> list[Problem]:
    """Each command line of ``launch`` (a string or a list) that shell-style splitting rejects."""
    problems = []
    for number, line in enumerate(as_tuple(launch)):
        path = (*base, "launch") + ((number,) if isinstance(launch, list) else ())
        try:
            if not shlex.split(line):
                raise ValueError("empty command")
        except ValueError as exc:
            problems.append(
                problem(
                    doc,
                    path,
                    f"{describe(line)} is not a valid command line ({exc}); expected e.g. 'ros2 launch pkg file.launch.py'",
                )
            )
    return problems


def env_name_problem(name) -> str | None:
    """Why ``name`` may not be set in a module's ``env``, or None."""
    if not isinstance(name, str):
        return f"{describe(name)} is not a valid name; expected a string of letters, digits and '_'"
    if name in RESERVED_ENV:
        return "is set by KubeROS (use rosDomainId and discovery instead); remove it"
    if name.startswith("KUBEROS_"):
        return "names starting with KUBEROS_ are reserved for KubeROS; rename it"
    return None
