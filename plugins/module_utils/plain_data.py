"""Ansible's values as builtin types: filters return these, so the result serialises anywhere."""

from __future__ import annotations


def plain(value):
    """Builtin types only (Ansible hands over tagged subclasses of str, int, dict..., which YAML cannot represent)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, bool) or value is None:
        return value
    for kind in (int, float, str):
        if isinstance(value, kind):
            return kind(value)
    return str(value)
