"""Hostile Python values: what Ansible may hand a module or a filter (a host variable, an option, a ConfigMap's
data) once YAML, Jinja or ``-e`` have read it: special floats, integers and text out of any range, text that ends in
a line break or holds controls, digits Python reads differently, wrong types, deep nesting."""

from __future__ import annotations

from hypothesis import strategies as st

NESTED = [[[[[[[[[[[[[[[[[[[[["deep"]]]]]]]]]]]]]]]]]]]]]


def _deep(depth: int):
    value: object = "x"
    for _ in range(depth):
        value = [value]
    return value


HOSTILE = [
    float("nan"), float("inf"), float("-inf"), -0.0, 1e308, 5e-324, 10**400, -(10**400), 2**63, -1, 0, 1, True, False,
    None, "", " ", "x\n", "edge\n", "4\n", "8Gi\n", "\n", "\t", "a\x00b", "\x1b[2J", "\u202e", "\u2028", "\x85",
    "nan", "NaN", "inf", "-inf", "1e400", "1e-400", "9" * 400, "-1", "0", "0x10", "1_000", "+5",
    "²", "①", "٣", "Ⅻ", "\uff11\uff12", "4.5.6", "100m\n", "2Gi ", "1Ti", "999999999999999999999999Gi", "1e309m", "0.0000001m",
    "40 ms", "1 h", "-5 ms", "inf ms", "nan ms", "1e400 ms", "100 Mbit", "5 %", "101%", "-1%",
    "é" * 100, "a" * 70_000, "a" * 2_000_000, "$(reboot)", "../../etc", "{{ lookup('pipe', 'id') }}",
    [], {}, [None], ["x\n"], [1, 2], ["a", "a"], [[]], {"": 1}, {1: 2}, {None: 1}, {"a\n": 1}, {"k": float("nan")},
    ("a", "b"), {"a", "b"}, b"bytes", NESTED, _deep(500),
]  # fmt: skip

hostile_value = st.one_of(
    st.sampled_from(HOSTILE),
    st.integers(),
    st.floats(),
    st.text(max_size=30),
    st.lists(st.text(max_size=8), max_size=4),
    st.dictionaries(st.text(max_size=8), st.one_of(st.none(), st.integers(), st.floats(), st.text(max_size=8)), max_size=3),
)


def mostly(valid, hostile):
    """``valid`` two times in three, else ``hostile``: with several options drawn, a case where all are valid (and the
    surface goes on to do its work) stays common."""
    return st.sampled_from([True, True, False]).flatmap(lambda ok: valid if ok else hostile)
