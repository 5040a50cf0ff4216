"""Read what one module prints on one robot: the pod that serves it, each container's recent log, and optionally
what it prints next for a while (``follow``), with the values of the Secrets the pod can read taken out, and keys,
passwords and tokens whatever their source. Each container's log is redacted as one stream (a ``Redactor`` each): a
key whose BEGIN line came in the tail or an earlier poll stays hidden in the next poll.

Used by the ``rosdeployment_logs`` module (``playbooks/logs.yml``). The choices are ``kuberos.module_logs``'s.
"""

from __future__ import annotations

import re
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import (
    Redactor,
    instance_for,
    labelled,
    newest_pod,
    robots_of,
    secret_refs,
    secret_values,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube

MAX_FOLLOW_S = 600
# What deployment, module, robot, fleet and container names may be: Kubernetes label values (they go into label
# selectors, so nothing else: a ',' or '=' would change what is selected).
_NAME = re.compile(r"[A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?")


class LogNotFound(KuberosError):
    """No such deployment, module, robot or container, or no pod of it yet."""


def _deployments(kube: Kube, deployment: str, fleet: str) -> tuple[list[dict], str]:
    selector = f"{labels.DEPLOYMENT}={deployment},{labels.COMPONENT}=ros-module"
    found = kube.list("Deployment", fleet_namespace(fleet) if fleet else "", selector=selector)
    namespaces = sorted({d["metadata"]["namespace"] for d in found})
    if not found:
        where = f"fleet {fleet} ({fleet_namespace(fleet)})" if fleet else "any fleet"
        raise LogNotFound(f"deployment {deployment} has no module running in {where}")
    if len(namespaces) > 1:
        raise LogNotFound(f"deployment {deployment} runs in several fleets' namespaces ({', '.join(namespaces)}); name the fleet")
    return found, namespaces[0]


def find_pod(kube: Kube, deployment: str, module: str, robot: str, fleet: str = "") -> tuple[dict, dict]:
    """(the module Deployment serving ``robot``, its newest pod that is not being deleted)."""
    found, namespace = _deployments(kube, deployment, fleet)
    modules = sorted({(d["metadata"].get("labels") or {}).get(labels.MODULE, "") for d in found})
    if module not in modules:
        raise LogNotFound(f"deployment {deployment} has no module {module}; its modules: {', '.join(modules)}")
    instance = instance_for(found, deployment, module, robot)
    if instance is None:
        served = robots_of(found, deployment, module)
        raise LogNotFound(f"module {module} of {deployment} runs for no robot {robot}; it runs for: {', '.join(served)}")
    name = instance["metadata"]["name"]
    pod = newest_pod(kube.list("Pod", namespace, selector=f"{labels.INSTANCE}={name}"))
    if pod is None:
        raise LogNotFound(f"{robot}/{module} ({name}) has no pod yet")
    return instance, pod


def secrets_of(kube: Kube, pod: dict) -> dict[str, str]:
    """The values of the Secrets the pod's containers can read; a Secret that cannot be read stops the reading (its
    values could not be kept out of the log)."""
    namespace = pod["metadata"]["namespace"]
    values = {}
    for name, key in secret_refs(pod["spec"]):
        try:
            secret = kube.get("Secret", name, namespace)
        except Exception as exc:
            raise KuberosError(f"cannot read Secret {name}, which {pod['metadata']['name']} mounts, to keep its values "
                               f"out of the log: {exc.__class__.__name__}") from None  # fmt: skip
        if secret is not None:
            values.update(secret_values(secret, key))
    return values


def read_module_log(kube: Kube, deployment: str, module: str, robot: str, fleet: str = "", container: str = "",
                    lines: int = 100, follow_s: float = 0.0, previous: bool = False, clock=time.monotonic,
                    sleep=time.sleep) -> dict:  # fmt: skip
    """The module's recent output on ``robot`` (every container, or ``container``), then ``follow_s`` seconds more."""
    if not 0 <= follow_s <= MAX_FOLLOW_S:
        raise KuberosError(f"follow must be from 0 to {MAX_FOLLOW_S} seconds")
    if not 1 <= lines <= 10000:
        raise KuberosError("lines must be from 1 to 10000")
    given = {"deployment": deployment, "module": module, "robot": robot, "fleet": fleet, "container": container}
    for option, value in given.items():
        if (value or option in ("deployment", "module", "robot")) and not _NAME.fullmatch(str(value)):
            raise KuberosError(
                f"{option}: {str(value)[:80]!a} is not a name (letters, digits, '-', '_' and '.', at most 63, "
                "starting and ending with a letter or digit)"
            )
    instance, pod = find_pod(kube, deployment, module, robot, fleet)
    meta = pod["metadata"]
    names = [c["name"] for c in pod["spec"].get("containers") or ()]
    if container and container not in names:
        raise LogNotFound(f"{meta['name']} has no container {container}; its containers: {', '.join(names)}")
    chosen = [container] if container else names
    secrets = secrets_of(kube, pod)
    redactors = {name: Redactor(secrets) for name in chosen}
    several = len(chosen) > 1
    out: list[str] = []
    last: dict[str, str] = {}
    for name in chosen:
        text = kube.log(meta["name"], meta["namespace"], container=name, tail_lines=lines, timestamps=True, previous=previous)
        stamped = text.splitlines()
        if stamped:
            last[name] = _stamp(stamped[-1])
        out += labelled(name, redactors[name].redact(_without_stamps(stamped)), several)
    end = clock() + follow_s
    started = clock()
    while follow_s and not previous and clock() < end:
        sleep(1.0)
        for name in chosen:
            since = int(clock() - started) + 5
            stamped = kube.log(meta["name"], meta["namespace"], container=name, since_seconds=since, timestamps=True).splitlines()
            fresh = [line for line in stamped if _stamp(line) > last.get(name, "")]
            if fresh:
                last[name] = _stamp(fresh[-1])
                out += labelled(name, redactors[name].redact(_without_stamps(fresh)), several)
    return {
        "pod": meta["name"],
        "namespace": meta["namespace"],
        "node": pod["spec"].get("nodeName", ""),
        "instance": instance["metadata"]["name"],
        "containers": chosen,
        "lines": out,
        "redacted": sorted(secrets),
    }


def _stamp(line: str) -> str:
    """A line's RFC 3339 time in a form that sorts (the kubelet trims the fraction's trailing zeros)."""
    stamp = line.split(" ", 1)[0].rstrip("Z")
    whole, _dot, fraction = stamp.partition(".")
    return f"{whole}.{fraction.ljust(9, '0')}"


def _without_stamps(stamped: list[str]) -> str:
    return "\n".join(line.split(" ", 1)[1] if " " in line else "" for line in stamped)
