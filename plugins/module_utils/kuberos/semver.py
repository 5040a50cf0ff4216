"""Semantic versions (SemVer 2.0.0) and npm-style version ranges, for the software catalog.

``parse_version("1.2.3-rc.1+build.5")`` returns a ``Version``; versions order as the SemVer
specification says (a prerelease comes before its release; build metadata is ignored).

``parse_range(text)`` returns a ``Range``. The grammar is npm's (``docs/software.md``)::

    range-set  ::= range ( '||' range )*          # OR
    range      ::= hyphen | simple ( ' ' simple )*  # space = AND
    hyphen     ::= partial ' - ' partial           # 1.2.3 - 2.0.0 (inclusive)
    simple     ::= ( '<' | '>' | '>=' | '<=' | '=' | '~' | '^' )? partial
    partial    ::= xr ( '.' xr ( '.' xr prerelease? build? )? )?
    xr         ::= 'x' | 'X' | '*' | a number

``1.2.3`` and ``=1.2.3`` match exactly that version; ``1.2``, ``1.2.x`` and ``1`` are wildcards;
``*`` and ``x`` match every release. ``~1.2.3`` allows patch updates (>=1.2.3 <1.3.0), ``^1.2.3``
updates that keep the left-most non-zero number (>=1.2.3 <2.0.0; ``^0.2.3`` is >=0.2.3 <0.3.0;
``^0.0.3`` is exactly 0.0.3). A prerelease such as ``1.3.0-rc.1`` matches only a range that names
a prerelease of the same MAJOR.MINOR.PATCH (``>=1.3.0-rc.0``), as npm does.

Pure Python, standard library only.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import total_ordering

MAX_LENGTH = 256  # longest version or range text accepted

_NUMBER = r"0|[1-9][0-9]*"
_IDENT = r"[0-9A-Za-z-]+"
_VERSION = re.compile(
    rf"^(?P<major>[0-9]+)\.(?P<minor>[0-9]+)\.(?P<patch>[0-9]+)"
    rf"(?:-(?P<pre>{_IDENT}(?:\.{_IDENT})*))?(?:\+(?P<build>{_IDENT}(?:\.{_IDENT})*))?\Z"
)
_NUMERIC = re.compile(rf"^(?:{_NUMBER})\Z")
_PARTIAL = re.compile(
    r"^(?P<major>[0-9]+|[xX*])(?:\.(?P<minor>[0-9]+|[xX*])(?:\.(?P<patch>[0-9]+|[xX*])"
    rf"(?:-(?P<pre>{_IDENT}(?:\.{_IDENT})*))?(?:\+(?P<build>{_IDENT}(?:\.{_IDENT})*))?)?)?\Z"
)
_OPERATOR = re.compile(r"^(>=|<=|>|<|=|~>|~|\^)?(.*)\Z", re.S)
_WILD = ("x", "X", "*")


@total_ordering
@dataclass(frozen=True, eq=False)
class Version:
    """A SemVer 2.0.0 version. Equality and order ignore ``build``, as the specification says."""

    major: int
    minor: int
    patch: int
    prerelease: tuple = ()  # identifiers: ints for numeric ones, strings otherwise
    build: tuple[str, ...] = ()

    @property
    def core(self) -> tuple[int, int, int]:
        return (self.major, self.minor, self.patch)

    def _key(self):
        # A release sorts after all of its prereleases; numeric identifiers sort before alphanumeric ones.
        if not self.prerelease:
            return (self.core, 1, ())
        return (self.core, 0, tuple((0, p, "") if isinstance(p, int) else (1, 0, p) for p in self.prerelease))

    def __eq__(self, other):
        if not isinstance(other, Version):
            return NotImplemented
        return self._key() == other._key()

    def __lt__(self, other):
        if not isinstance(other, Version):
            return NotImplemented
        return self._key() < other._key()

    def __hash__(self):
        return hash(self._key())

    def __str__(self) -> str:
        text = f"{self.major}.{self.minor}.{self.patch}"
        if self.prerelease:
            text += "-" + ".".join(str(p) for p in self.prerelease)
        if self.build:
            text += "+" + ".".join(self.build)
        return text

    def __repr__(self) -> str:
        return f"Version('{self}')"


def _prerelease(text: str | None, whole: str) -> tuple:
    if not text:
        return ()
    out = []
    for ident in text.split("."):
        if ident.isdigit():
            if not _NUMERIC.match(ident):
                raise ValueError(f"{whole!r} has a leading zero in the prerelease identifier '{ident}'")
            out.append(int(ident))
        else:
            out.append(ident)
    return tuple(out)


def _number(text: str, what: str, whole: str) -> int:
    if not _NUMERIC.match(text):
        raise ValueError(f"{whole!r} has a leading zero in its {what} number '{text}'")
    return int(text)


def _explain(text: str) -> str:
    """Why ``text`` is not MAJOR.MINOR.PATCH[-prerelease][+build]."""
    if text[:1] in ("v", "V", "=") and _VERSION.match(text[1:]):
        return f"{text!r} starts with '{text[0]}'; write the version without it ({text[1:]})"
    if any(c.isspace() for c in text):
        return f"{text!r} contains white space"
    core = re.split(r"[-+]", text, maxsplit=1)[0]
    parts = core.split(".")
    if len(parts) != 3 or not all(re.fullmatch("[0-9]+", p) for p in parts):
        return f"{text!r} is not MAJOR.MINOR.PATCH with three numbers"
    rest = text[len(core) :]
    pre, _sep, build = rest[1:].partition("+") if rest.startswith("-") else ("", "", rest[1:])
    if rest.startswith("-") and not pre:
        return f"{text!r} has an empty prerelease after '-'"
    if "+" in rest and not build:
        return f"{text!r} has empty build metadata after '+'"
    if "+" in build:
        return f"{text!r} has more than one '+'"
    if (pre and "" in pre.split(".")) or (build and "" in build.split(".")):
        return f"{text!r} has an empty identifier between dots"
    return f"{text!r} has characters other than letters, digits, '-' and '.' in its prerelease or build"


def parse_version(text) -> Version:
    """A SemVer 2.0.0 version from its text; ``ValueError`` saying why when ``text`` is not one."""
    if not isinstance(text, str):
        raise ValueError(f"{text!r} ({type(text).__name__}) is not a version string such as '1.2.3' (quote it)")
    if not text:
        raise ValueError("the version is empty; expected MAJOR.MINOR.PATCH such as 1.2.3")
    if len(text) > MAX_LENGTH:
        raise ValueError(f"the version is longer than {MAX_LENGTH} characters")
    match = _VERSION.match(text)
    if not match:
        raise ValueError(_explain(text) + "; expected MAJOR.MINOR.PATCH[-prerelease][+build] such as 1.2.3 or 1.3.0-rc.1")
    return Version(
        _number(match["major"], "major", text),
        _number(match["minor"], "minor", text),
        _number(match["patch"], "patch", text),
        _prerelease(match["pre"], text),
        tuple(match["build"].split(".")) if match["build"] else (),
    )


# --------------------------------------------------------------------------------------------
# Ranges
# --------------------------------------------------------------------------------------------

_ANY = ((">=", Version(0, 0, 0)),)
_NONE = (("<", Version(0, 0, 0, (0,))),)


@dataclass(frozen=True)
class _Partial:
    major: int | None
    minor: int | None = None
    patch: int | None = None
    prerelease: tuple = ()

    def floor(self) -> Version:
        return Version(self.major or 0, self.minor or 0, self.patch or 0, self.prerelease)

    @property
    def complete(self) -> bool:
        return self.patch is not None


def _where(part: str, whole: str) -> str:
    return repr(part) if part == whole.strip() else f"{part!r} in {whole!r}"


def _partial(text: str, whole: str) -> _Partial:
    match = _PARTIAL.match(text)
    if not match:
        if not text:
            raise ValueError(f"{whole!r} has an operator without a version after it")
        raise ValueError(
            f"{_where(text, whole)} is not a version or wildcard; expected e.g. 1.2.3, 1.2, 1.x or *"
            + (" (leave out the leading 'v')" if text[:1] in "vV" and _PARTIAL.match(text[1:]) else "")
        )
    numbers: list[int | None] = []
    for what in ("major", "minor", "patch"):
        value = match[what]
        if value is None or value in _WILD or (numbers and numbers[-1] is None):
            if value is not None and value not in _WILD:
                raise ValueError(f"{_where(text, whole)} has a number after a wildcard; expected e.g. 1.x or 1.2.x")
            numbers.append(None)
        else:
            numbers.append(_number(value, what, text))
    if match["pre"] and numbers[2] is None:
        raise ValueError(f"{_where(text, whole)} has a prerelease but not MAJOR.MINOR.PATCH")
    return _Partial(numbers[0], numbers[1], numbers[2], _prerelease(match["pre"], text))


def _bump(partial: _Partial) -> Version:
    """The first version past the wildcard part of ``partial`` (as ``-0`` so that prereleases stay out)."""
    if partial.minor is None:
        return Version(partial.major + 1, 0, 0, (0,))
    return Version(partial.major, partial.minor + 1, 0, (0,))


def _comparators(operator: str, p: _Partial) -> tuple:
    """One ``simple`` as comparators (op, version), all of which must hold."""
    if p.major is None:  # '*' and friends
        return _NONE if operator in (">", "<") else _ANY
    if operator in ("", "="):
        if p.complete:
            return (("=", p.floor()),)
        return ((">=", p.floor()), ("<", _bump(p)))
    if operator in ("~", "~>"):
        upper = Version(p.major + 1, 0, 0, (0,)) if p.minor is None else Version(p.major, p.minor + 1, 0, (0,))
        return ((">=", p.floor()), ("<", upper))
    if operator == "^":
        if p.major != 0 or p.minor is None:
            upper = Version(p.major + 1, 0, 0, (0,))
        elif p.minor != 0 or p.patch is None:
            upper = Version(0, p.minor + 1, 0, (0,))
        else:
            upper = Version(0, 0, p.patch + 1, (0,))
        return ((">=", p.floor()), ("<", upper))
    if p.complete:
        return ((operator, p.floor()),)
    if operator == ">":
        return ((">=", Version(*_bump(p).core)),)
    if operator == ">=":
        return ((">=", p.floor()),)
    if operator == "<":
        return (("<", Version(*p.floor().core, (0,))),)
    return (("<", _bump(p)),)  # '<=' with a wildcard: everything up to the wildcard's end


def _hyphen(low: _Partial, high: _Partial) -> tuple:
    lower = _ANY if low.major is None else ((">=", low.floor()),)
    if high.major is None:
        return lower
    upper = (("<=", high.floor()),) if high.complete else (("<", _bump(high)),)
    return lower + upper


_HYPHEN = re.compile(r"^(\S+) +- +(\S+)\Z")


def _comparator_set(text: str, whole: str) -> tuple:
    text = text.strip()
    if not text:
        raise ValueError(f"{whole!r} has an empty alternative around '||'" if "||" in whole else "the range is empty")
    hyphen = _HYPHEN.match(text)
    if hyphen:
        return _hyphen(_partial(hyphen[1], whole), _partial(hyphen[2], whole))
    # '>= 1.2.3' is '>=1.2.3'
    text = re.sub(r"(>=|<=|~>|>|<|=|~|\^)\s+", r"\1", text)
    out: list = []
    for token in text.split():
        if token == "-":
            raise ValueError(f"{whole!r} has a '-' that is not between two versions; expected e.g. '1.2.3 - 2.0.0'")
        match = _OPERATOR.match(token)
        operator, rest = match[1] or "", match[2]
        if rest[:1] in "<>=~^" and rest:
            raise ValueError(f"{_where(token, whole)} has two operators; expected one of >=, <=, >, <, =, ~, ^")
        out.extend(_comparators(operator, _partial(rest, whole)))
    return tuple(out)


def _holds(op: str, version: Version, bound: Version) -> bool:
    if op == "=":
        return version == bound
    if op == ">=":
        return version >= bound
    if op == ">":
        return version > bound
    if op == "<=":
        return version <= bound
    return version < bound


@dataclass(frozen=True)
class Range:
    """A set of versions: alternatives (``||``) of comparator sets (all must hold)."""

    text: str
    alternatives: tuple = field(compare=False, repr=False)

    def __str__(self) -> str:
        return self.text

    def matches(self, version) -> bool:
        """Whether ``version`` (a ``Version`` or its text) is in the range."""
        if isinstance(version, str):
            version = parse_version(version)
        for comparators in self.alternatives:
            if not all(_holds(op, version, bound) for op, bound in comparators):
                continue
            # A prerelease matches only if a comparator names a prerelease of the same MAJOR.MINOR.PATCH.
            if version.prerelease and not any(bound.prerelease and bound.core == version.core for _op, bound in comparators):
                continue
            return True
        return False

    def best(self, versions):
        """The highest of ``versions`` (``Version`` objects or their texts) in the range, or None."""
        found, found_version = None, None
        for item in versions:
            try:
                version = parse_version(item) if isinstance(item, str) else item
            except ValueError:
                continue
            if self.matches(version) and (found_version is None or version > found_version):
                found, found_version = item, version
        return found


def parse_range(text) -> Range:
    """A version range from its text (grammar above); ``ValueError`` saying why when it is not one."""
    if not isinstance(text, str):
        raise ValueError(f"{text!r} ({type(text).__name__}) is not a version range such as '^1.2' (quote it)")
    if len(text) > MAX_LENGTH:
        raise ValueError(f"the range is longer than {MAX_LENGTH} characters")
    if not text.strip():
        raise ValueError("the range is empty; expected e.g. '^1.2', '>=1.0.0 <2.0.0' or '*'")
    if any(c.isspace() and c != " " for c in text):
        raise ValueError(f"{text!r} contains tabs or line breaks; separate comparators with spaces")
    alternatives = tuple(_comparator_set(part, text) for part in text.split("||"))
    return Range(text, alternatives)


__all__ = ["MAX_LENGTH", "Range", "Version", "parse_range", "parse_version"]
