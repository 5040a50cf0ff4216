"""Strategies for YAML files a person or an attacker writes: valid files with one field replaced by a hostile value
(written as YAML text, so that anchors, aliases, tags, duplicate keys and special floats reach the loader as
written), a key removed, added or doubled; and raw text.

``mutated(texts)`` draws one of ``texts`` (valid files), loads it, draws a place in it (a mapping key or a list item,
at any depth) and a mutation, and writes the file again with ``yaml.safe_dump`` (block style) with the hostile text
in place.
"""

from __future__ import annotations

import json

import yaml
from hypothesis import strategies as st

PLACEHOLDER = "FUZZ-VALUE-8c1e"
KEY_PLACEHOLDER = "FUZZ-KEY-8c1e"


def _laughs(levels: int, width: int) -> str:
    """A flow list whose aliases stand for ``width ** levels`` nodes (the billion laughs)."""
    parts = [f"&l0 [{', '.join(['lol'] * width)}]"]
    for level in range(1, levels):
        parts.append(f"&l{level} [{', '.join([f'*l{level - 1}'] * width)}]")
    return "[" + ", ".join(parts) + "]"


# Hostile values as YAML text, each one line (so it fits after "key: " and after "- ").
HOSTILE_TEXT = [
    # numbers YAML reads as floats and integers out of any range
    ".nan", ".NaN", ".inf", "-.inf", "+.inf", "1e400", "-1e400", "1e-400", "!!float nan", "!!float .inf",
    "1" * 400, "-" + "9" * 400, "9" * 1001, "0x" + "f" * 300, "0o" + "7" * 300, "1_000_000", "-0", "0.0", "-1",
    "2147483648", "9223372036854775808", "18446744073709551616", "1e20", "3.0e+9", "0b101",
    # strings that look like something else, or end in a line break
    '"x\\n"', '"alice\\n"', '"edge\\n"', '"100m\\n"', '"2Gi\\n"', '"1.0.0\\n"', '"a\\r"', '"\\t"', '" "', '""', "''",
    '"\\x00"', '"\\e[31mred"', '"\\u202e"', '"\\u2028"', '"\\ud800"', '"\\U0001F600"', '"é"', '"\\uffff"', '"\\x85"',
    '"$(reboot)"', '"`id`"', '"a;b"', '"../../etc/passwd"', '"/etc/shadow"', '"{robot}"', '"/{robot}"', '"%s%n"',
    # other YAML types
    "true", "false", "null", "~", "yes", "no", "on", "off", "[]", "{}", "[null]", "{a: 1}", "[1, [2, [3]]]",
    "2001-12-14", "2001-12-14T21:59:43.10-05:00", "12:30:45", "!!binary aGVsbG8=", "!!set {a, b}", "!!omap [a: 1]",
    "!!str 1", "!!int 12", "!!timestamp 2001-12-14", "!!python/object/apply:os.system [id]", "!!python/name:os.system",
    "!custom x", "!!merge <<", "<<",
    # anchors and aliases
    "*undefined", "&a x", "&a [*a]", "&a {k: *a}", "[&a x, *a, *a]", _laughs(4, 4), _laughs(9, 9), _laughs(30, 2),
    # deep nesting, long text (the file's size bound is 1 MiB)
    "[" * 70 + "]" * 70, "[" * 1000 + "]" * 1000, "{a: " * 70 + "1" + "}" * 70, "a" * 70_000, "é" * 300_000,
    "a" * 1_100_000, '"' + "\\x41" * 50_000 + '"', "[" + ", ".join(["1"] * 60_000) + "]",
    # not YAML at all
    "{", "[", "}", "]", "'", '"', "&", "*", "!", "|", ">", "- ", "%YAML 1.1", "---", "...", "@x", "`x", "\t",
]  # fmt: skip


def _as_text(value) -> str:
    """``value`` (a Python value drawn by Hypothesis) as one line of YAML flow text."""
    return yaml.safe_dump(value, default_flow_style=True, width=10**9, allow_unicode=True).strip()


json_like = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=30)
    | st.sampled_from(["edge", "cloud", "onboard", "100m", "2Gi", "40 ms", "test-fleet", "1.0.0", "^0.1", "jazzy"]),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=12), children, max_size=4),
    max_leaves=20,
)
hostile_text = st.one_of(
    st.sampled_from(HOSTILE_TEXT),
    json_like.map(_as_text),
    st.text(max_size=40).map(json.dumps),  # any text as a double-quoted scalar (JSON's escapes are YAML's)
    st.text(alphabet=st.characters(codec="utf-8"), max_size=20),  # any characters, written plain
)


def places(data, path=()):
    """Every (path, is_key) in ``data``: a mapping's keys (by key) and a list's items (by index)."""
    found = []
    if isinstance(data, dict):
        for key, value in data.items():
            found.append(((*path, key), True))
            found.extend(places(value, (*path, key)))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            found.append(((*path, index), False))
            found.extend(places(value, (*path, index)))
    return found


def _parent(data, path):
    for part in path[:-1]:
        data = data[part]
    return data


def _dump(data) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False, width=10**9, allow_unicode=True)


class Bases(list):
    """Valid files to mutate, shown by name (Hypothesis shows a strategy's arguments)."""

    def __init__(self, name: str, texts):
        super().__init__(texts)
        self.name = name

    def __repr__(self) -> str:
        return f"<{len(self)} {self.name}>"


@st.composite
def mutated(draw, texts: Bases) -> str:
    """One of ``texts`` with one drawn place mutated (see the module's docstring)."""
    text = draw(st.sampled_from(list(texts)))
    documents = list(yaml.safe_load_all(text))
    index = draw(st.integers(0, len(documents) - 1))
    data = documents[index]
    spots = places(data)
    path, _is_key = draw(st.sampled_from(spots))
    parent = _parent(data, path)
    last = path[-1]
    mutation = draw(st.sampled_from(["value", "value", "value", "remove", "add", "duplicate", "rename"]))
    hostile = draw(hostile_text)
    if mutation == "value" or (mutation in ("add", "duplicate", "rename") and not isinstance(parent, dict)):
        parent[last] = PLACEHOLDER
    elif mutation == "remove":
        del parent[last]
    elif mutation == "add":
        parent[KEY_PLACEHOLDER] = PLACEHOLDER
    elif mutation == "duplicate":  # the same key again, with a hostile value
        parent[KEY_PLACEHOLDER] = PLACEHOLDER
    else:  # a key renamed to hostile text
        items = list(parent.items())
        parent.clear()
        parent.update((KEY_PLACEHOLDER if key == last else key, value) for key, value in items)
    documents[index] = data
    out = "---\n".join(_dump(doc) for doc in documents) if len(documents) > 1 else _dump(data)
    if mutation == "duplicate":
        out = out.replace(KEY_PLACEHOLDER, last if isinstance(last, str) else json.dumps(last), 1)
    elif mutation in ("add", "rename"):
        out = out.replace(KEY_PLACEHOLDER, draw(st.sampled_from(["x-extra", "name", "image", "$ref", '"a\\nb"', "1", "?"])), 1)
    return out.replace(PLACEHOLDER, hostile, 1)


yaml_tokens = st.sampled_from(
    [
        "metadata:", "rosModules:", "- name: m", "  image: i", "  launch: [x]", "name:", "targetFleet: f", "topics:",
        "publishes:", "- {name: a, type: b/msg/C}", "&a", "*a", "<<: *a", "---", "...", "%YAML 1.2", "!!str", "? ",
        ": ", "- ", "  ", "\n", "{", "}", "[", "]", ",", "'", '"', "#", "|", ">", "\t", ".nan", "1e400", "\\x00",
    ]
)  # fmt: skip
raw_yaml = st.one_of(
    st.lists(yaml_tokens, max_size=40).map("".join),
    st.text(max_size=200),
    st.binary(max_size=200).map(lambda b: b.decode("utf-8", "replace")),
)
