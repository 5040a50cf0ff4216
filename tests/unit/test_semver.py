"""Semantic versions and version ranges: SemVer 2.0.0 order and npm range semantics, as tables."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.semver import (
    Range,
    Version,
    parse_range,
    parse_version,
)

# --------------------------------------------------------------------------------------------
# Versions
# --------------------------------------------------------------------------------------------

PARSE = [
    ("0.0.0", (0, 0, 0, (), ())),
    ("1.2.3", (1, 2, 3, (), ())),
    ("10.20.30", (10, 20, 30, (), ())),
    ("1.0.0-alpha", (1, 0, 0, ("alpha",), ())),
    ("1.0.0-alpha.1", (1, 0, 0, ("alpha", 1), ())),
    ("1.0.0-0.3.7", (1, 0, 0, (0, 3, 7), ())),
    ("1.0.0-x.7.z.92", (1, 0, 0, ("x", 7, "z", 92), ())),
    ("1.0.0-x-y-z.--", (1, 0, 0, ("x-y-z", "--"), ())),
    ("1.0.0-alpha+001", (1, 0, 0, ("alpha",), ("001",))),
    ("1.0.0+20130313144700", (1, 0, 0, (), ("20130313144700",))),
    ("1.0.0-beta+exp.sha.5114f85", (1, 0, 0, ("beta",), ("exp", "sha", "5114f85"))),
    ("1.0.0-rc.1+build.1", (1, 0, 0, ("rc", 1), ("build", "1"))),
    ("99999999999999999999.0.0", (99999999999999999999, 0, 0, (), ())),
]


@pytest.mark.parametrize(("text", "parts"), PARSE)
def test_parse_version(text, parts):
    version = parse_version(text)
    assert (version.major, version.minor, version.patch, version.prerelease, version.build) == parts
    assert str(version) == text


INVALID_VERSIONS = [
    ("", "empty"),
    ("1", "not MAJOR.MINOR.PATCH"),
    ("1.2", "not MAJOR.MINOR.PATCH"),
    ("1.2.3.4", "not MAJOR.MINOR.PATCH"),
    ("1.2.x", "not MAJOR.MINOR.PATCH"),
    ("a.b.c", "not MAJOR.MINOR.PATCH"),
    ("v1.2.3", "starts with 'v'; write the version without it (1.2.3)"),
    ("=1.2.3", "starts with '='"),
    ("01.2.3", "leading zero in its major number '01'"),
    ("1.02.3", "leading zero in its minor number '02'"),
    ("1.2.03", "leading zero in its patch number '03'"),
    ("1.2.3-01", "leading zero in the prerelease identifier '01'"),
    ("1.2.3-", "empty prerelease after '-'"),
    ("1.2.3+", "empty build metadata after '+'"),
    ("1.2.3-a..b", "empty identifier between dots"),
    ("1.2.3+a..b", "empty identifier between dots"),
    ("1.2.3+a+b", "more than one '+'"),
    ("1.2.3-rc_1", "characters other than letters, digits, '-' and '.'"),
    ("1.2.3-é", "characters other than letters"),
    (" 1.2.3", "white space"),
    ("1.2.3\n", "white space"),
    ("1.2.3 ", "white space"),
    ("1" * 300 + ".0.0", "longer than 256 characters"),
    (1.2, "(float) is not a version string"),
    (None, "(NoneType) is not a version string"),
]


@pytest.mark.parametrize(("text", "reason"), INVALID_VERSIONS)
def test_invalid_version_says_why(text, reason):
    with pytest.raises(ValueError, match=None) as info:
        parse_version(text)
    assert reason in str(info.value)


# From the SemVer 2.0.0 specification, item 11, in ascending order.
ORDERED = [
    "1.0.0-alpha",
    "1.0.0-alpha.1",
    "1.0.0-alpha.beta",
    "1.0.0-beta",
    "1.0.0-beta.2",
    "1.0.0-beta.11",
    "1.0.0-rc.1",
    "1.0.0",
    "1.0.1",
    "1.1.0-0",
    "1.1.0",
    "1.10.0",
    "2.0.0",
    "10.0.0",
]


def test_ordering_follows_the_specification():
    versions = [parse_version(v) for v in ORDERED]
    assert sorted(reversed(versions)) == versions
    for low, high in itertools.pairwise(versions):
        assert low < high and high > low and low != high and low <= high


def test_build_metadata_is_ignored_for_order_and_equality():
    assert parse_version("1.0.0+a") == parse_version("1.0.0+b") == parse_version("1.0.0")
    assert hash(parse_version("1.0.0+a")) == hash(parse_version("1.0.0"))
    assert not parse_version("1.0.0+a") < parse_version("1.0.0+b")
    assert str(parse_version("1.0.0+a")) == "1.0.0+a"
    assert max([parse_version("1.0.0-rc.1"), parse_version("0.9.9")]) == parse_version("1.0.0-rc.1")


# --------------------------------------------------------------------------------------------
# Ranges: (range, versions that match, versions that do not)
# --------------------------------------------------------------------------------------------

RANGES = [
    # exact
    ("1.2.3", ["1.2.3", "1.2.3+build"], ["1.2.4", "1.2.2", "1.2.3-rc.1"]),
    ("=1.2.3", ["1.2.3"], ["1.2.4"]),
    ("1.2.3-rc.1", ["1.2.3-rc.1"], ["1.2.3", "1.2.3-rc.2"]),
    # caret
    ("^1.2.3", ["1.2.3", "1.9.9", "1.2.4"], ["2.0.0", "1.2.2", "2.0.0-rc.1", "1.3.0-rc.1"]),
    ("^0.2.3", ["0.2.3", "0.2.9"], ["0.3.0", "0.2.2", "1.0.0"]),
    ("^0.0.3", ["0.0.3"], ["0.0.4", "0.0.2", "0.1.0"]),
    ("^1.2", ["1.2.0", "1.99.0"], ["1.1.9", "2.0.0"]),
    ("^0.2", ["0.2.0", "0.2.5"], ["0.3.0", "0.1.9"]),
    ("^0.1", ["0.1.0"], ["0.2.0"]),
    ("^0.0", ["0.0.0", "0.0.9"], ["0.1.0"]),
    ("^1", ["1.0.0", "1.5.5"], ["2.0.0", "0.9.0"]),
    ("^0", ["0.0.1", "0.9.9"], ["1.0.0"]),
    ("^1.x", ["1.0.0", "1.9.0"], ["2.0.0"]),
    ("^0.0.x", ["0.0.0", "0.0.5"], ["0.1.0"]),
    ("^1.2.3-beta.2", ["1.2.3-beta.2", "1.2.3-beta.4", "1.2.3", "1.9.0"], ["1.2.3-beta.1", "1.2.4-beta.1", "2.0.0"]),
    ("^ 1.2.3", ["1.5.0"], ["2.0.0"]),
    # tilde
    ("~1.2.3", ["1.2.3", "1.2.9"], ["1.3.0", "1.2.2"]),
    ("~1.2", ["1.2.0", "1.2.9"], ["1.3.0", "1.1.0"]),
    ("~1", ["1.0.0", "1.9.9"], ["2.0.0"]),
    ("~0.2.3", ["0.2.3", "0.2.4"], ["0.3.0"]),
    ("~>1.2", ["1.2.5"], ["1.3.0"]),
    ("~1.2.3-beta.2", ["1.2.3-beta.2", "1.2.3", "1.2.4"], ["1.2.3-beta.1", "1.2.4-beta.1", "1.3.0"]),
    # wildcards
    ("*", ["0.0.0", "1.0.0", "99.0.0"], ["1.0.0-rc.1"]),
    ("x", ["0.1.0", "3.0.0"], ["3.0.0-alpha"]),
    ("1.x", ["1.0.0", "1.99.99"], ["2.0.0", "0.9.0", "2.0.0-0"]),
    ("1.X", ["1.2.0"], ["2.0.0"]),
    ("1.*", ["1.2.0"], ["2.0.0"]),
    ("1.2.x", ["1.2.0", "1.2.99"], ["1.3.0", "1.1.0"]),
    ("1.2.*", ["1.2.5"], ["1.3.0"]),
    ("1.2", ["1.2.0", "1.2.99"], ["1.3.0"]),
    ("1", ["1.0.0", "1.9.0"], ["2.0.0"]),
    ("1.x.x", ["1.5.5"], ["2.0.0"]),
    # comparators, space = AND
    (">=1.0.0 <2.0.0", ["1.0.0", "1.9.9"], ["2.0.0", "0.9.9", "2.0.0-rc.1", "1.5.0-rc.1"]),
    (">1.0.0", ["1.0.1"], ["1.0.0"]),
    ("<1.0.0", ["0.9.9"], ["1.0.0", "1.0.0-rc.1"]),
    ("<=1.0.0", ["1.0.0", "0.1.0"], ["1.0.1"]),
    (">= 1.0.0 < 2.0.0", ["1.5.0"], ["2.0.0"]),
    (">=0.1 <1", ["0.1.0", "0.9.9"], ["1.0.0", "0.0.9"]),
    (">1", ["2.0.0"], ["1.9.9"]),
    (">1.2", ["1.3.0"], ["1.2.9"]),
    (">=1.2", ["1.2.0"], ["1.1.9"]),
    ("<1.2", ["1.1.9"], ["1.2.0", "1.2.0-rc.1"]),
    ("<=1.2", ["1.2.9"], ["1.3.0"]),
    ("<=1", ["1.9.9"], ["2.0.0"]),
    (">*", [], ["0.0.0", "1.0.0"]),
    ("<*", [], ["0.0.0"]),
    (">=*", ["0.0.0", "5.0.0"], []),
    # OR
    ("1.2.3 || 2.x", ["1.2.3", "2.5.0"], ["1.2.4", "3.0.0"]),
    ("<1.0.0 || >=2.0.0", ["0.5.0", "2.0.0"], ["1.5.0"]),
    ("^0.1||^0.2", ["0.1.5", "0.2.5"], ["0.3.0"]),
    # hyphen ranges (inclusive)
    ("1.2.3 - 2.3.4", ["1.2.3", "2.3.4"], ["2.3.5", "1.2.2"]),
    ("1.2 - 2.3.4", ["1.2.0"], ["1.1.9", "2.3.5"]),
    ("1.2.3 - 2.3", ["2.3.9"], ["2.4.0"]),
    ("1.2.3 - 2", ["2.9.9"], ["3.0.0"]),
    ("* - 2", ["0.0.0", "2.5.0"], ["3.0.0"]),
    # prereleases match only when the range names one of the same MAJOR.MINOR.PATCH
    (">=1.3.0-rc.0", ["1.3.0-rc.2", "1.3.0", "2.0.0"], ["1.4.0-rc.1", "1.3.0-0"]),
    (">1.2.3-alpha.3", ["1.2.3-alpha.7", "3.4.5"], ["3.4.5-alpha.9", "1.2.3-alpha.3"]),
    (">=1.0.0-0 <1.0.1", ["1.0.0-0", "1.0.0-rc.1", "1.0.0"], ["1.0.1-rc.1"]),
]


@pytest.mark.parametrize(("text", "yes", "no"), RANGES)
def test_range(text, yes, no):
    wanted = parse_range(text)
    assert str(wanted) == text
    for version in yes:
        assert wanted.matches(version), f"{text} should match {version}"
        assert wanted.matches(parse_version(version))
    for version in no:
        assert not wanted.matches(version), f"{text} should not match {version}"


INVALID_RANGES = [
    ("", "the range is empty"),
    ("   ", "the range is empty"),
    ("||", "empty alternative around '||'"),
    ("1.0.0 ||", "empty alternative"),
    ("|| 1.0.0", "empty alternative"),
    (">=", "operator without a version"),
    (">>1", "two operators"),
    (">=<1", "two operators"),
    ("1.2.3 -", "'-' that is not between two versions"),
    ("- 1.2.3", "'-' that is not between two versions"),
    ("v1.2.3", "(leave out the leading 'v')"),
    ("1.x.3", "number after a wildcard"),
    ("1.2-rc.1", "is not a version or wildcard"),
    ("1.x-rc.1", "is not a version or wildcard"),
    ("abc", "'abc' is not a version or wildcard"),
    (">=1.0.0 abc", "'abc' in '>=1.0.0 abc' is not a version or wildcard"),
    ("01.2.3", "leading zero"),
    ("^1.2.3-01", "leading zero in the prerelease identifier"),
    ("^1\t2", "tabs or line breaks"),
    ("1.0.0\n|| 2.0.0", "tabs or line breaks"),
    ("1.0.0 " * 60, "longer than 256 characters"),
    (1, "(int) is not a version range"),
    (None, "(NoneType) is not a version range"),
]


@pytest.mark.parametrize(("text", "reason"), INVALID_RANGES)
def test_invalid_range_says_why(text, reason):
    with pytest.raises(ValueError) as info:
        parse_range(text)
    assert reason in str(info.value)


def test_best_is_the_highest_match():
    versions = ["0.1.0", "0.2.0", "0.2.5", "0.3.0-rc.1", "1.0.0"]
    assert parse_range("^0.2").best(versions) == "0.2.5"
    assert parse_range("*").best(versions) == "1.0.0"
    assert parse_range(">=0.3.0-rc.0 <1.0.0").best(versions) == "0.3.0-rc.1"
    assert parse_range("^2").best(versions) is None
    assert parse_range("^0.1").best([]) is None
    assert parse_range("*").best(["bad", "0.1.0"]) == "0.1.0"  # unparseable texts are skipped
    parsed = [parse_version(v) for v in versions]
    assert parse_range("~0.2.0").best(parsed) is parsed[2]


def test_range_equality_is_by_text():
    assert parse_range("^1.2") == parse_range("^1.2")
    assert parse_range("^1.2") != parse_range(">=1.2.0 <2.0.0-0")
    assert isinstance(parse_range("*"), Range)
    assert repr(parse_version("1.0.0-rc.1")) == "Version('1.0.0-rc.1')"
    assert Version(1, 2, 3) == parse_version("1.2.3")


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=40))
def test_any_text_is_a_range_or_a_value_error(text):
    try:
        wanted = parse_range(text)
    except ValueError:
        return
    wanted.matches("1.0.0")


@settings(max_examples=300, deadline=None)
@given(st.from_regex(r"[0-9]{1,3}\.[0-9]{1,3}\.[0-9]{1,3}(-[0-9A-Za-z.-]{1,8})?(\+[0-9A-Za-z.-]{1,8})?", fullmatch=True))
def test_any_version_like_text_parses_or_says_why(text):
    try:
        version = parse_version(text)
    except ValueError as exc:
        assert str(exc)
        return
    assert parse_version(str(version)) == version
    assert parse_range(str(version).split("+")[0]).matches(version)
