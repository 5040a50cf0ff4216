"""What a deploy changes in the cluster, for ``--check --diff``: per object and, first, per module of each robot.

Pure: plain dicts in, plain dicts and text out. The I/O (reading live objects, the server-side dry runs) is in the
``rosdeployment_diff`` module. Three steps:

- ``clean_object``: an object as people compare it, like ``kubectl diff`` shows it: without ``status``,
  ``metadata.managedFields`` and the server's bookkeeping (resourceVersion, generation, uid, creationTimestamp),
  encoded blobs (``binaryData``, Secret data) as a size and a digest, and the spec text a revision keeps as one line;
- ``object_diff``: one entry of Ansible's diff list (``before``/``after`` as YAML) for an object that changes, is
  new or would be removed;
- ``change_summary`` and ``summary_text``: which modules of which robots move (node A -> B), start, stop or change
  (version, image, launch, env, parameters, resources), from the placement the live record holds and the new
  placement, and from the module Deployments and parameter ConfigMaps as they are and as they would be.
"""

from __future__ import annotations

import base64
import binascii
import hashlib

from .applied import APPLIED
from .errors import SpecError
from .labels import VERSION
from .manifest_yaml import dump_object
from .manifests import params_configmap_name
from .naming import object_label
from .placement import Placement
from .record import RECORD_LABEL, REVISION_LABEL, record_placement
from .third_party import yaml

SERVER_FIELDS = ("managedFields", "resourceVersion", "generation", "uid", "creationTimestamp", "selfLink")
LAST_APPLIED = "kubectl.kubernetes.io/last-applied-configuration"
# Environment a module's container gets from KubeROS that says where and for whom it runs: a move shows as a move.
PLACEMENT_ENV = ("KUBEROS_NODE_NAME",)


def _digest(raw: bytes) -> str:
    return f"sha256:{hashlib.sha256(raw).hexdigest()[:12]}"


def _blob(text) -> str:
    """A binaryData or Secret value as its size and digest: its bytes say nothing to a reader, a change still shows."""
    try:
        raw = base64.b64decode(str(text), validate=True)
    except (binascii.Error, ValueError):
        raw = str(text).encode()
    return f"<{len(raw)} bytes, {_digest(raw)}>"


def clean_object(obj: dict) -> dict:
    """The object without what the server keeps for itself and without encoded blobs (see the module docstring)."""
    out = {k: v for k, v in obj.items() if k != "status"}
    meta = {k: v for k, v in (obj.get("metadata") or {}).items() if k not in SERVER_FIELDS}
    if {LAST_APPLIED, APPLIED} & set(meta.get("annotations") or {}):
        meta["annotations"] = {k: v for k, v in meta["annotations"].items() if k not in (LAST_APPLIED, APPLIED)}
        if not meta["annotations"]:
            del meta["annotations"]
    out["metadata"] = meta
    if out.get("binaryData"):
        out["binaryData"] = {k: _blob(v) for k, v in sorted(out["binaryData"].items())}
    if obj.get("kind") == "Secret":
        out["data"] = {k: _blob(v) for k, v in sorted((obj.get("data") or {}).items())}
        out.pop("stringData", None)
    labels = meta.get("labels") or {}
    if obj.get("kind") == "ConfigMap" and labels.get(REVISION_LABEL) and "spec.yaml" in (out.get("data") or {}):
        # A revision keeps the spec the record holds too: the record's diff shows the edit once.
        text = out["data"]["spec.yaml"]
        out["data"] = {**out["data"], "spec.yaml": f"<the spec, {len(text.splitlines())} lines, {_digest(text.encode())}>"}
    return out


def object_diff(before: dict | None, after: dict | None) -> dict | None:
    """One entry of Ansible's diff list for one object (cleaned first), or None when nothing differs.
    ``before`` is the live object (None: new, and ``after`` is shown as rendered); ``after`` what the cluster would
    hold (None: removed)."""
    cleaned_before = clean_object(before) if before is not None else None
    cleaned_after = clean_object(after) if after is not None else None
    if cleaned_before == cleaned_after:
        return None  # compared as data: an unchanged object is never dumped (a re-run compares hundreds)
    old = dump_object(cleaned_before) if cleaned_before is not None else ""
    new = dump_object(cleaned_after) if cleaned_after is not None else ""
    if old == new:
        return None
    label = object_label(after if after is not None else before)
    return {
        "before_header": f"{label} (live)" if before is not None else f"{label} (absent)",
        "after_header": f"{label} (removed)"
        if after is None
        else f"{label} (new)"
        if before is None
        else f"{label} (server dry run)",
        "before": old,
        "after": new,
    }


# -- the summary ---------------------------------------------------------------------------------------------------
def _container(obj: dict | None) -> dict:
    containers = (((obj or {}).get("spec") or {}).get("template") or {}).get("spec", {}).get("containers") or [{}]
    return containers[0]


def _env(obj: dict | None) -> dict[str, str]:
    out = {}
    for item in _container(obj).get("env") or []:
        value = item["value"] if "value" in item else yaml.safe_dump(item.get("valueFrom"), default_flow_style=True).strip()
        out[item["name"]] = value
    return out


def _short(value, limit: int = 60) -> str:
    text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def deployment_changes(before: dict | None, after: dict | None) -> list[str]:
    """What changes in a module's Deployment other than its node, in a few words each."""
    if before is None or after is None:
        return []
    parts = []
    old_v = (before["metadata"].get("labels") or {}).get(VERSION)
    new_v = (after["metadata"].get("labels") or {}).get(VERSION)
    if old_v != new_v:
        parts.append(f"version {old_v or '-'} -> {new_v or '-'}")
    old_c, new_c = _container(before), _container(after)
    if old_c.get("image") != new_c.get("image"):
        parts.append(f"image {old_c.get('image')} -> {new_c.get('image')}")
    if old_c.get("args") != new_c.get("args") or old_c.get("command") != new_c.get("command"):
        parts.append("launch changed")
    old_env, new_env = _env(before), _env(after)
    for name in sorted(set(old_env) | set(new_env)):
        if name in PLACEMENT_ENV or old_env.get(name) == new_env.get(name):
            continue
        if name not in old_env:
            parts.append(f"env +{name}={_short(new_env[name])}")
        elif name not in new_env:
            parts.append(f"env -{name}")
        else:
            parts.append(f"env {name} {_short(old_env[name])} -> {_short(new_env[name])}")
    old_r, new_r = old_c.get("resources") or {}, new_c.get("resources") or {}
    for what in ("cpu", "memory", "nvidia.com/gpu"):
        a, b = (old_r.get("requests") or {}).get(what), (new_r.get("requests") or {}).get(what)
        if a != b:
            parts.append(f"{what} {a or '-'} -> {b or '-'}")
    if (before.get("spec") or {}).get("strategy") != (after.get("spec") or {}).get("strategy"):
        parts.append("upgrade strategy changed")
    if old_c.get("volumeMounts") != new_c.get("volumeMounts"):
        parts.append("parameter file " + ("mounted" if new_c.get("volumeMounts") else "removed"))
    return parts


def _parameters(obj: dict | None) -> dict:
    text = ((obj or {}).get("data") or {}).get("params.yaml") or ""
    try:
        document = yaml.safe_load(text) or {}
    except yaml.YAMLError:
        return {"<unreadable>": text}
    found = (document.get("/**") or {}).get("ros__parameters") if isinstance(document, dict) else None
    return found if isinstance(found, dict) else {}


def parameter_changes(before: dict | None, after: dict | None) -> list[str]:
    """What changes in a module's ROS parameters (its parameter ConfigMap), parameter by parameter."""
    if before == after:
        return []
    old, new = _parameters(before), _parameters(after)
    parts = []
    for name in sorted(set(old) | set(new), key=str):
        if name not in old:
            parts.append(f"+{name}={_short(new[name], 40)}")
        elif name not in new:
            parts.append(f"-{name}")
        elif old[name] != new[name]:
            parts.append(f"{name} {_short(old[name], 40)} -> {_short(new[name], 40)}")
    return [f"parameters {', '.join(parts)}"] if parts else []


def _by_robot(placement: Placement | None) -> dict[tuple[str, str, str], object]:
    out = {}
    for inst in placement.instances if placement else ():
        for robot in inst.robots:
            out[(inst.deployment, inst.module, robot)] = inst
    return out


def change_summary(previous: dict[str, Placement | None], placement: Placement, pairs: dict) -> list[dict]:
    """One row per module of each robot that moves, starts, stops or changes, and per discovery server that does.

    ``previous`` maps each deployment to the placement its live record holds (None: not deployed); ``pairs`` maps
    ``object_key`` to ``(live, would_be)`` (None for absent) for every object the deploy applies."""
    names = [d["name"] for d in placement.deployments]
    old_all = Placement()
    for name in names:
        prev = previous.get(name)
        if prev is not None:
            old_all.instances.extend(i for i in prev.instances if i.deployment == name)
            for fleet, servers in prev.discovery.items():
                old_all.discovery.setdefault(fleet, servers)
    old, new = _by_robot(old_all), _by_robot(placement)
    rows = []
    for key in sorted(set(old) | set(new)):
        deployment, module, robot = key
        a, b = old.get(key), new.get(key)
        row = {"deployment": deployment, "module": module, "robot": robot, "from": getattr(a, "node", ""), "to": ""}
        if b is None:
            rows.append({**row, "action": "stop", "details": []})
            continue
        row["to"] = b.node
        before, after = pairs.get(("Deployment", b.namespace, b.name), (None, None))
        params = pairs.get(("ConfigMap", b.namespace, params_configmap_name(deployment, module)), (None, None))
        details = deployment_changes(before, after) + parameter_changes(*params)
        if a is None:
            rows.append({**row, "action": "start", "details": []})
        elif a.node != b.node:
            rows.append({**row, "action": "move", "details": details})
        elif details:
            rows.append({**row, "action": "change", "details": details})
    for fleet, servers in sorted(placement.discovery.items()):
        was = {s.server_id: s for s in old_all.discovery.get(fleet, [])}
        now = {s.server_id: s for s in servers}
        if not was:
            continue  # a new fleet's discovery servers start with it; the objects say so
        for server_id in sorted(set(was) | set(now)):
            a, b = was.get(server_id), now.get(server_id)
            action = "start" if a is None else "stop" if b is None else "move" if a.node != b.node else ""
            if action:
                rows.append(
                    {
                        "deployment": "",
                        "module": (b or a).name,
                        "robot": f"fleet {fleet}",
                        "from": a.node if a else "",
                        "to": b.node if b else "",
                        "action": action,
                        "details": [],
                    }
                )
    return rows


def record_changes(pairs: dict) -> list[str]:
    """Per record ConfigMap that changes: how many of its placement's instances change (read with
    ``record.record_placement``, so that the record's format stays that module's business)."""
    lines = []
    for (kind, namespace, name), (before, after) in sorted(pairs.items()):
        if kind != "ConfigMap" or after is None or (after["metadata"].get("labels") or {}).get(RECORD_LABEL) != "true":
            continue
        if before is not None and clean_object(before) == clean_object(after):
            continue
        try:
            old = {i.name: (i.node, i.robots) for i in record_placement(before).instances} if before is not None else {}
            new = {i.name: (i.node, i.robots) for i in record_placement(after).instances}
        except SpecError:  # a record this version cannot read: say so, the object diff shows the rest
            lines.append(f"record {namespace}/{name}: changed (its placement could not be read)")
            continue
        count = sum(1 for n in set(old) | set(new) if old.get(n) != new.get(n))
        instances = f"{count} instance{'s' if count != 1 else ''}"
        if before is None:
            lines.append(f"record {namespace}/{name}: new, placement of {instances}")
        else:
            lines.append(
                f"record {namespace}/{name}: updated, "
                + (f"placement of {instances} changed" if count else "placement unchanged")
            )
    return lines


def _describe(row: dict) -> str:
    if row["action"] == "move":
        text = f"moves {row['from']} -> {row['to']}"
    elif row["action"] == "start":
        text = f"starts on {row['to']}"
    elif row["action"] == "stop":
        text = f"stops on {row['from']}"
    else:
        text = "changes"
    return text + (": " + "; ".join(row["details"]) if row["details"] else "")


def summary_text(rows: list[dict], records: list[str], counts: dict, check_mode: bool, refused: dict | None = None) -> str:
    """The summary people read first: one line per module of each robot (robots that change alike share a line),
    the records, how many objects change, and the objects whose dry run the cluster refused (``refused``: object ->
    what it said)."""
    head = "What the deploy would change (check mode: nothing written)" if check_mode else "What the deploy changes"
    lines = [f"{head}:"]
    grouped: dict[tuple, list[str]] = {}
    for row in rows:
        text = _describe(row)
        if row["action"] == "move" or row["robot"].startswith("fleet "):
            grouped[(row["deployment"], row["module"], row["robot"], text)] = [row["robot"]]
        else:
            grouped.setdefault((row["deployment"], row["module"], "", text), []).append(row["robot"])
    for (deployment, module, _robot, text), robots in grouped.items():
        who = robots[0] if robots[0].startswith("fleet ") else ", ".join(robots)
        where = f"{deployment}/{module}" if deployment else module
        lines.append(f"  {where} ({who}): {text}")
    if not rows:
        lines.append("  no module moves, starts, stops or changes")
    lines.extend(f"  {line}" for line in records)
    lines.append(
        f"  objects: {counts.get('changed', 0)} changed, {counts.get('new', 0)} new, {counts.get('removed', 0)} removed, "
        f"{counts.get('unchanged', 0)} unchanged"
    )
    for what, why in sorted((refused or {}).items()):
        lines.append(f"  refused by the cluster's dry run: {what}: {why}")
    return "\n".join(lines)
