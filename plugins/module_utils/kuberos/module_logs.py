"""A module's output without kubectl: which pod serves a module of a robot, and its log made safe to show.

``instance_for`` finds the rendered Deployment of a (deployment, module, robot) among a fleet's Deployments: a
dedicated instance carries the robot's label, a shared one lists its robots in an annotation. ``secret_refs`` names
the Secrets a pod's containers can read (environment and volumes); ``redact`` takes their values out of a log, and
with them what looks like a private key or a bearer token whatever its source. ``labelled`` prefixes each line of a
module with several containers with the container's name. Pure: the I/O is ``kuberos_deploy/module_log_reader.py``
and the dashboard's.
"""

from __future__ import annotations

import base64
import re

from . import labels

REDACTED = "[redacted: {}]"
MIN_SECRET = 4  # shorter values are not taken out (they would blank ordinary words)
MAX_LINES = 10000
_PRIVATE_KEY = re.compile(r"-----BEGIN [A-Z ]*PRIVATE KEY-----.*?(-----END [A-Z ]*PRIVATE KEY-----|\Z)", re.S)
_JWT = re.compile(r"\beyJ[A-Za-z0-9_-]{8,}\.[A-Za-z0-9_-]{8,}\.[A-Za-z0-9_-]{8,}")
_BEARER = re.compile(r"(?i)(authorization:\s*bearer\s+|bearer\s+)[A-Za-z0-9._~+/=-]{8,}")


def serves(deployment: dict, robot: str) -> bool:
    meta = deployment.get("metadata") or {}
    if (meta.get("labels") or {}).get(labels.ROBOT) == robot:
        return True
    robots = (meta.get("annotations") or {}).get(labels.ROBOTS_ANNOTATION, "")
    return robot in [r.strip() for r in robots.split(",")]


def instance_for(deployments: list[dict], deployment: str, module: str, robot: str) -> dict | None:
    """The module Deployment of ``deployment`` that runs ``module`` for ``robot``, or None."""
    for obj in sorted(deployments, key=lambda d: d["metadata"]["name"]):
        found = obj["metadata"].get("labels") or {}
        if found.get(labels.DEPLOYMENT) == deployment and found.get(labels.MODULE) == module and serves(obj, robot):
            return obj
    return None


def robots_of(deployments: list[dict], deployment: str, module: str) -> list[str]:
    """Every robot some instance of ``module`` serves (to say which exist when a robot is not one of them)."""
    robots = set()
    for obj in deployments:
        meta = obj["metadata"]
        found = meta.get("labels") or {}
        if found.get(labels.DEPLOYMENT) == deployment and found.get(labels.MODULE) == module:
            robots |= {r for r in (meta.get("annotations") or {}).get(labels.ROBOTS_ANNOTATION, "").split(",") if r}
            if found.get(labels.ROBOT):
                robots.add(found[labels.ROBOT])
    return sorted(robots)


def newest_pod(pods: list[dict]) -> dict | None:
    """The newest of an instance's pods that is not being deleted (a rollout's surge runs two for a while)."""
    alive = [p for p in pods if not p["metadata"].get("deletionTimestamp")]
    return max(alive, key=lambda p: p["metadata"].get("creationTimestamp", "")) if alive else None


def secret_refs(pod_spec: dict) -> list[tuple[str, str]]:
    """(Secret, key) pairs the pod's containers can read; key '' for all of a Secret's keys."""
    refs = set()
    for container in (*(pod_spec.get("initContainers") or ()), *(pod_spec.get("containers") or ())):
        for env in container.get("env") or ():
            ref = (env.get("valueFrom") or {}).get("secretKeyRef")
            if ref:
                refs.add((ref["name"], ref.get("key", "")))
        for source in container.get("envFrom") or ():
            if source.get("secretRef"):
                refs.add((source["secretRef"]["name"], ""))
    for volume in pod_spec.get("volumes") or ():
        if volume.get("secret"):
            refs.add((volume["secret"]["secretName"], ""))
        for source in (volume.get("projected") or {}).get("sources") or ():
            if source.get("secret"):
                refs.add((source["secret"]["name"], ""))
    return sorted(refs)


def secret_values(secret: dict, key: str = "") -> dict[str, str]:
    """``{'<secret>/<key>': value}`` of a Secret object's data (base64) and stringData, one key or all."""
    name = secret["metadata"]["name"]
    values = {}
    for field, encoded in (secret.get("data") or {}).items():
        if key in ("", field):
            try:
                values[f"{name}/{field}"] = base64.b64decode(encoded).decode("utf-8", errors="replace")
            except ValueError:
                continue
    for field, value in (secret.get("stringData") or {}).items():
        if key in ("", field):
            values[f"{name}/{field}"] = str(value)
    return values


def redact(text: str, secrets: dict[str, str]) -> str:
    """``text`` without the values of ``secrets`` (each line of a multi-line value too), private keys and tokens."""
    pieces = []
    for label, value in secrets.items():
        for piece in {value, value.strip(), *value.splitlines()}:
            if len(piece.strip()) >= MIN_SECRET:
                pieces.append((piece.strip(), label))
    for piece, label in sorted(pieces, key=lambda p: -len(p[0])):
        text = text.replace(piece, REDACTED.format(label))
    text = _PRIVATE_KEY.sub(REDACTED.format("private key"), text)
    text = _JWT.sub(REDACTED.format("token"), text)
    return _BEARER.sub(lambda m: m.group(1) + REDACTED.format("token"), text)


def labelled(container: str, text: str, several: bool) -> list[str]:
    """The log's lines, each prefixed with ``[container]`` when the module has several containers."""
    lines = text.splitlines()[-MAX_LINES:]
    return [f"[{container}] {line}" for line in lines] if several else lines
