"""Files of a site or a render directory read back: a file that is not there yet is None, not an error."""

from __future__ import annotations


def text_or_none(path: str) -> str | None:
    """A text file's content, or None when there is no such file."""
    try:
        with open(path, encoding="utf-8") as handle:
            return handle.read()
    except FileNotFoundError:
        return None
