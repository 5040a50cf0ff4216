"""What KubeROS applied to an object, kept on the object: the ``kuberos.io/applied`` annotation holds a digest of the
configuration every server-side apply sends (``stamped``). A deploy that renders the same configuration again, on an
object that still holds every field of it (``holds``: nobody changed or removed one since) and whose fields KubeROS
owns, would change nothing with an apply: ``unchanged`` says so without asking the API server for a dry run."""

from __future__ import annotations

import hashlib
import json

APPLIED = "kuberos.io/applied"


def applied_hash(obj: dict) -> str:
    """A digest of an object's configuration, its own ``kuberos.io/applied`` annotation left out."""
    annotations = (obj.get("metadata") or {}).get("annotations") or {}
    if APPLIED in annotations:
        meta = {**obj["metadata"], "annotations": {k: v for k, v in annotations.items() if k != APPLIED}}
        if not meta["annotations"]:
            del meta["annotations"]  # as the configuration was before it was stamped
        obj = {**obj, "metadata": meta}
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def stamped(obj: dict) -> dict:
    """A copy of ``obj`` as plain JSON data (what a client sends), carrying the digest of its configuration."""
    out = json.loads(json.dumps(obj))
    out.setdefault("metadata", {}).setdefault("annotations", {})[APPLIED] = applied_hash(obj)
    return out


def applied_of(obj: dict) -> str | None:
    """The digest an object was last applied with (None: applied before it was stamped, or never)."""
    return ((obj.get("metadata") or {}).get("annotations") or {}).get(APPLIED)


def owns(live: dict, field_manager: str) -> bool:
    """Whether ``field_manager`` holds fields of ``live`` by server-side apply."""
    managers = (live.get("metadata") or {}).get("managedFields") or []
    return any(m.get("manager") == field_manager and m.get("operation") == "Apply" for m in managers)


def holds(live, config) -> bool:
    """Whether ``live`` holds every field ``config`` sets, with the same value (lists item by item, in order; the
    server's defaults and other owners' extra fields do not count; anything unsure is a no)."""
    if isinstance(config, dict):
        return isinstance(live, dict) and all(key in live and holds(live[key], value) for key, value in config.items())
    if isinstance(config, list):
        return isinstance(live, list) and len(live) == len(config) and all(map(holds, live, config))
    return type(live) is type(config) and live == config


def unchanged(config: dict, live: dict | None, field_manager: str) -> bool:
    """Whether a server-side apply of ``config`` by ``field_manager`` would leave ``live`` as it is: the last apply
    sent this configuration (its digest), every field of it is still there with its value, and ``field_manager`` holds
    its fields (an apply otherwise takes them over)."""
    if live is None or applied_of(live) != applied_hash(config):
        return False
    return owns(live, field_manager) and holds(live, config)
