"""Checks shared by the RosDeployment spec and the software catalog.

``schema_problems(validator, doc)`` turns every JSON Schema error of a loaded YAML document into a
``Problem`` naming the file, the line, the field path, the value and what was expected (the
schema's ``x-expected`` phrase; ``x-message`` replaces the whole message of a ``not``, reported at the
field ``x-field``).
"""

from __future__ import annotations

import datetime
import functools
import math
import re
import shlex

from . import quantities
from .errors import Problem, describe, did_you_mean
from .third_party import jsonschema, require
from .yaml_source import Document, format_path

RESERVED_ENV = ("ROS_DISCOVERY_SERVER", "RMW_IMPLEMENTATION", "ROS_DOMAIN_ID")


@functools.lru_cache(maxsize=256)
def _anchored(pattern: str) -> re.Pattern:
    """``pattern`` with a final ``$`` meaning the end of the text, as in JSON Schema (ECMA-262), not before a final
    line feed as in Python: ``'demo\\n'`` does not match ``^[a-z]+$``."""
    if pattern.endswith("$") and not pattern.endswith("\\$"):
        pattern = pattern[:-1] + "\\Z"
    return re.compile(pattern)


def _pattern(validator, pattern, instance, schema):
    if validator.is_type(instance, "string") and not _anchored(pattern).search(instance):
        yield jsonschema.ValidationError(f"{instance!r} does not match {pattern!r}")


def _finite_number(checker, instance) -> bool:
    """JSON's numbers: NaN and the infinities (YAML's ``.nan``, ``.inf``) are none; Python's float takes them."""
    return jsonschema.Draft202012Validator.TYPE_CHECKER.is_type(instance, "number") and (
        not isinstance(instance, float) or math.isfinite(instance)
    )


_QUANTITIES = {"latency": quantities.parse_latency_ms, "cpu": quantities.parse_cpu, "memory": quantities.parse_memory}


def _maximum_quantity(validator, bound, instance, schema):
    """``x-maximum``: a quantity (a number or text such as '30 s', '500m', '2Gi') at most ``bound['value']`` in the
    unit ``quantities`` parses it to. Text the pattern refuses is left to the pattern; 400 digits are too large (as
    text they parse to infinity, as a number they overflow the float)."""
    try:
        amount = _QUANTITIES[bound["quantity"]](instance)
    except OverflowError:
        amount = math.inf
    except ValueError:
        return
    if not amount <= bound["value"]:
        yield jsonschema.ValidationError(f"{instance!r} is more than {bound['shown']}")


def strict_validator(schema: dict) -> jsonschema.protocols.Validator:
    """A Draft 2020-12 validator of ``schema`` whose patterns end where the text ends (see ``_anchored``), whose
    numbers are finite (``_finite_number``) and whose quantities are bounded also when written as text
    (``x-maximum``)."""
    require("jsonschema")
    base = jsonschema.Draft202012Validator
    cls = jsonschema.validators.extend(
        base,
        {"pattern": _pattern, "x-maximum": _maximum_quantity},
        type_checker=base.TYPE_CHECKER.redefine("number", _finite_number),
    )
    return cls(schema)


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
    if isinstance(value, float) and not math.isfinite(value):
        return [problem(doc, parts, f"{describe(value)} is not valid: not a finite number; expected {expected}")]
    bound = _bound(error.validator, schema)
    if bound:
        return [problem(doc, parts, f"{describe(value)} is not valid: it must be {bound}; expected {expected}")]
    return [problem(doc, parts, f"{describe(value)} is not valid; expected {expected or error.message}")]


def _bound(keyword: str, schema: dict) -> str:
    """The upper bound a value broke (``at most 232``, ``below 100``, ``at most 86400 s``), or ''."""
    if keyword in ("maximum", "x-maximum") and "x-maximum" in schema:
        return f"at most {schema['x-maximum']['shown']}"
    if keyword == "maximum":
        return f"at most {schema['maximum']}"
    if keyword == "exclusiveMaximum":
        return f"below {schema['exclusiveMaximum']}"
    return ""


def schema_problems(validator: jsonschema.protocols.Validator, doc: Document) -> list[Problem]:
    """Every schema error of ``doc`` as a located ``Problem``, each field reported once."""
    problems = []
    seen = set()
    errors = sorted(validator.iter_errors(doc.data), key=lambda e: ([str(p) for p in e.absolute_path], e.validator))
    for error in errors:
        for found in _problems_of(error, doc):
            # A value that is both of the wrong type and fails a pattern is reported once.
            if found.path in seen and error.validator in ("pattern", "minimum", "type", "maximum", "x-maximum"):
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


# --------------------------------------------------------------------------------------------
# Container image references (github.com/distribution/reference)
# --------------------------------------------------------------------------------------------

_DOMAIN_COMPONENT = r"(?:[A-Za-z0-9]|[A-Za-z0-9][A-Za-z0-9-]*[A-Za-z0-9])"
_HOST = rf"(?:{_DOMAIN_COMPONENT}(?:\.{_DOMAIN_COMPONENT})*|\[[0-9A-Fa-f:.]+\])"
_DOMAIN = re.compile(rf"{_HOST}(?::[0-9]+)?")
_PATH_COMPONENT = re.compile(r"[a-z0-9]+(?:(?:[_.]|__|-+)[a-z0-9]+)*")
_TAG = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
_DIGEST_HEX = {"sha256": 64, "sha384": 96, "sha512": 128}
MAX_IMAGE_NAME = 255
IMAGE_EXPECTED = (
    "expected [registry/]path[:tag][@digest] with a lowercase path (a registry may have a :port; a digest is "
    "sha256: and 64 hex digits), such as 'ghcr.io/example/planner:1.0'"
)


def split_image(image: str) -> tuple[str, str, str | None, str]:
    """``[domain/]path[:tag][@digest]`` -> (domain, path, tag, digest); the tag is None without a ':'."""
    name, _sep, digest = image.partition("@")
    domain, path = "", name
    first, slash, rest = name.partition("/")
    # The first component is a registry when it looks like a host: a dot, a port, 'localhost' or capitals.
    if slash and ("." in first or ":" in first or first == "localhost" or first != first.lower()):
        domain, path = first, rest
    tag = None
    if ":" in path.rsplit("/", 1)[-1]:
        path, _sep, tag = path.rpartition(":")
    return domain, path, tag, digest


def _image_reason(image: str, digest_allowed: bool) -> str | None:
    if any(character.isspace() for character in image):
        return "white space"
    if image.count("@") > 1:
        return "more than one '@'"
    domain, path, tag, digest = split_image(image)
    if domain and not _DOMAIN.fullmatch(domain):
        return f"the registry {describe(domain)} is not a host name or address with an optional :port"
    for component in path.split("/"):
        if not _PATH_COMPONENT.fullmatch(component):
            return (
                f"the path component {describe(component)} is not lowercase letters and digits separated by '.', '_', '__' or '-'"
            )
    if len(domain) + 1 + len(path) > MAX_IMAGE_NAME:
        return f"the name is longer than {MAX_IMAGE_NAME} characters"
    if tag is not None and not _TAG.fullmatch(tag):
        return f"the tag {describe(tag)} is not 1 to 128 letters, digits, '_', '.' and '-' starting with a letter, digit or '_'"
    if "@" in image and digest_allowed:
        algorithm, _sep, encoded = digest.partition(":")
        length = _DIGEST_HEX.get(algorithm)
        if length is None:
            return f"the digest algorithm {describe(algorithm)} is not sha256, sha384 or sha512"
        if len(encoded) != length or not re.fullmatch(r"[0-9a-f]+", encoded):
            return f"the {algorithm} digest is not {length} lowercase hex digits"
    return None


def image_reference_problem(image, digest_allowed: bool = True) -> str | None:
    """Why ``image`` is not a valid container image reference (the distribution/reference grammar), or None.

    With ``digest_allowed`` false, a digest is not judged (the caller says where a digest goes instead).
    """
    if not isinstance(image, str) or not image:
        return None  # the schema reports the type
    reason = _image_reason(image, digest_allowed)
    return f"{describe(image)} is not a valid image reference ({reason}); {IMAGE_EXPECTED}" if reason else None


# --------------------------------------------------------------------------------------------
# ROS 2 parameters
# --------------------------------------------------------------------------------------------

INT64 = (-(2**63), 2**63 - 1)
_ROS_SCALARS = {bool: "a bool", int: "an integer", float: "a double", str: "a string"}
ROS_TYPES = "bool, integer (64-bit), double, string, or a non-empty list of one of these"


def _ros_scalar_problem(value) -> str | None:
    kind = type(value)
    if kind is bool or kind is float or kind is str:
        return None
    if kind is int:
        if not INT64[0] <= value <= INT64[1]:
            return f"{describe(value)} does not fit a 64-bit integer; expected an integer from {INT64[0]} to {INT64[1]}"
        return None
    if value is None:
        return "has no value; ROS 2 parameters have no null (give a value or leave the parameter out)"
    if isinstance(value, (datetime.date, datetime.datetime)):
        return f"is a YAML timestamp ({value.isoformat()}); ROS 2 has no date type; quote it to make it a string"
    if isinstance(value, (bytes, bytearray)):
        return "is a YAML !!binary value; ROS 2 parameters have no binary type; expected a list of integers or a string"
    if isinstance(value, (set, frozenset)):
        return "is a YAML !!set; ROS 2 parameters have no set type; expected a list"
    return f"{describe(value)} has no ROS 2 parameter type; expected {ROS_TYPES}"


def ros_parameter_problems(value, doc: Document, base: tuple, limit: int = 20) -> list[Problem]:
    """Each value of a ``rosParameters`` mapping that ROS 2's parameter file parser cannot read, at its path.

    Mappings are namespaces (string keys); values are bool, 64-bit integer, double, string, or a non-empty
    list of one of these (all of the same type; ROS 2 has no mixed, nested or empty arrays: an empty list has
    no type). ``!!binary``, ``!!set``, timestamps, nulls and non-string keys have no ROS 2 counterpart.
    """
    problems: list[Problem] = []
    stack = [(value, base)]
    while stack and len(problems) < limit:
        node, parts = stack.pop()
        if isinstance(node, dict):
            for key in reversed(list(node)):
                if not isinstance(key, str):
                    problems.append(
                        problem(doc, (*parts, str(key)), f"{describe(key)} is not a valid parameter name; expected a string")
                    )
                elif not key or any(character.isspace() for character in key):
                    problems.append(
                        problem(
                            doc, (*parts, key), f"{describe(key)} is not a valid parameter name; expected a name without spaces"
                        )
                    )
                else:
                    stack.append((node[key], (*parts, key)))
            continue
        if isinstance(node, list):
            problems.extend(_ros_array_problems(node, doc, parts))
            continue
        why = _ros_scalar_problem(node)
        if why:
            problems.append(problem(doc, parts, why))
    return problems[:limit]


def _ros_array_problems(items: list, doc: Document, parts: tuple) -> list[Problem]:
    if not items:
        why = "is an empty list, which has no ROS 2 type (bool, integer, double or string array)"
        return [problem(doc, parts, f"{why}; give at least one value or leave the parameter out")]
    first = type(items[0])
    for position, item in enumerate(items):
        if isinstance(item, (dict, list)):
            kind = "mapping" if isinstance(item, dict) else "list"
            return [
                problem(
                    doc,
                    (*parts, position),
                    f"is a {kind} inside a list; ROS 2 arrays hold bool, integer, double or string values only",
                )
            ]
        why = _ros_scalar_problem(item)
        if why:
            return [problem(doc, (*parts, position), why)]
        if type(item) is not first:  # pylint: disable=unidiomatic-typecheck  # exact types: a bool is an int to isinstance
            hint = "; write 1.0 for a double" if {first, type(item)} == {int, float} else ""
            return [
                problem(
                    doc,
                    (*parts, position),
                    f"{describe(item)} is {_ROS_SCALARS[type(item)]}, but {format_path(parts)}[0] is {_ROS_SCALARS[first]}; "
                    f"ROS 2 arrays hold values of one type{hint}",
                )
            ]
    return []


# --------------------------------------------------------------------------------------------
# Labels
# --------------------------------------------------------------------------------------------

OWNED_LABEL_DOMAIN = "kuberos.io"
OWNED_LABELS = ("app.kubernetes.io/managed-by",)
MAX_LABEL_PREFIX = 253


def label_key_problem(key) -> str | None:
    """Why a spec may not set the label ``key`` (its syntax is the schema's), or None."""
    if not isinstance(key, str):
        return None
    prefix, slash, _name = key.rpartition("/")
    if slash and len(prefix) > MAX_LABEL_PREFIX:
        return f"has a prefix longer than {MAX_LABEL_PREFIX} characters; expected a DNS subdomain before the '/'"
    if key in OWNED_LABELS or (slash and (prefix == OWNED_LABEL_DOMAIN or prefix.endswith("." + OWNED_LABEL_DOMAIN))):
        return (
            "is a label KubeROS sets itself (kuberos.io/..., *.kuberos.io/... and app.kubernetes.io/managed-by are "
            "KubeROS's); expected a label of your own, such as 'example.com/team'"
        )
    return None
