"""Problems found in user input, reported all at once.

Every problem names where it was found (a file or an inventory), the path to the field
(``rosModules[1].requirements.max_latency``), the offending value and what was expected.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass


@dataclass(frozen=True)
class Problem:
    """One thing wrong with the input."""

    source: str
    path: str
    message: str
    line: int | None = None

    def __str__(self) -> str:
        where = self.source if self.line is None else f"{self.source}:{self.line}"
        if self.path:
            return printable(f"{where}: {self.path}: {self.message}")
        return printable(f"{where}: {self.message}")


# Line breaks and other controls that a file name, a key or a message may hold, shown escaped so that a problem
# stays one line of plain text (yaml_source.CONTROL_CHARACTERS, with line breaks and tab).
_UNPRINTABLE = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069\ufffe\uffff]")


def printable(text: str) -> str:
    """``text`` with its control characters escaped (``\\n``, ``\\x00``, ``\\u202e``)."""
    return _UNPRINTABLE.sub(lambda match: ascii(match.group())[1:-1], text)


class KuberosError(Exception):
    """Base class of the errors this collection raises for bad input or impossible requests."""


class SpecError(KuberosError):
    """The input is invalid; ``problems`` lists every problem found, not only the first."""

    def __init__(self, problems: list[Problem], title: str = "invalid input"):
        self.problems = list(problems)
        self.title = title
        super().__init__(self.render())

    def render(self) -> str:
        count = len(self.problems)
        noun = "problem" if count == 1 else "problems"
        lines = [f"{self.title} ({count} {noun}):"]
        lines.extend(f"  - {problem}" for problem in self.problems)
        return "\n".join(lines)


class PlacementError(KuberosError):
    """At least one module instance has no feasible node; ``failures`` explains each one."""

    def __init__(self, failures: list[str], limit: int = 20):
        self.failures = list(failures)
        shown = self.failures[:limit]
        lines = [f"cannot place {len(self.failures)} module instance(s):"]
        lines.extend(shown)
        if len(self.failures) > limit:
            lines.append(f"... and {len(self.failures) - limit} more like these")
        super().__init__("\n".join(lines))


def did_you_mean(word: str, choices) -> str:
    """A ``; did you mean 'x'?`` hint, or an empty string when nothing is close."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    if not close:
        lowered = {str(c).lower().replace("_", "").replace("-", ""): str(c) for c in choices}
        key = str(word).lower().replace("_", "").replace("-", "")
        if key in lowered:
            close = [lowered[key]]
    return f"; did you mean '{close[0]}'?" if close else ""


def describe(value) -> str:
    """A short, safe rendering of a user value for messages."""
    text = repr(value)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{text} ({type(value).__name__})" if not isinstance(value, str) else text
