"""What the pod networks' objects share (``calico.py``, ``cilium.py``): the MTU limits, settings read from keyword
options, RBAC rules, integers as Ansible passes them, and Kubernetes' toleration rules."""

from __future__ import annotations

import re

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe, did_you_mean

RBAC_API = "rbac.authorization.k8s.io/v1"
# WireGuard over an IPv4 underlay: outer IPv4 (20) + UDP (8) + WireGuard header and tag (32).
DEFAULT_VPN_MTU = 1420  # the wireguard role's wireguard_mtu (wg-quick's default)
BASE_MTU_RANGE = (576, 9216)
MIN_POD_MTU = {4: 576, 6: 1280}


def settings_of(cls, what: str, pod_cidr, options: dict, prefix: str):
    """``cls(pod_cidr=..., **options)``, an unknown option reported with the closest known name (``what``: the CNI)."""
    known = [f for f in cls.__dataclass_fields__ if f != "pod_cidr"]
    unknown = [
        Problem(what, prefix + str(name), f"unknown setting{did_you_mean(name, known)} (known: {', '.join(known)})")
        for name in options
        if name not in known
    ]
    if unknown:
        raise SpecError(unknown, title=f"invalid {what.capitalize()} settings")
    return cls(pod_cidr=pod_cidr, **options)


def _integer(value) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str) and value.strip().isdigit():
        return int(value.strip())
    return None


def _rule(group: str, resources: list[str], verbs: list[str], names: list[str] | None = None) -> dict:
    rule = {"apiGroups": [group], "resources": resources, "verbs": verbs}
    if names:
        rule["resourceNames"] = names
    return rule


def tolerates(pod_spec: dict, taint: dict) -> bool:
    """Whether a pod spec's tolerations let it run on a node with this taint (Kubernetes' matching rules)."""
    for toleration in pod_spec.get("tolerations", []):
        if toleration.get("effect") and toleration["effect"] != taint["effect"]:
            continue
        key = toleration.get("key")
        if toleration.get("operator") == "Exists":
            if not key or key == taint["key"]:
                return True
        elif key == taint["key"] and toleration.get("value", "") == taint.get("value", ""):
            return True
    return False


def check_image_registry(value, example: str, problem) -> None:
    """``problem("image_registry", ...)`` unless ``value`` is a registry path such as ``example``."""
    if not isinstance(value, str) or not re.fullmatch(r"[a-z0-9]([a-z0-9._:/-]*[a-z0-9])?", value or ""):
        problem("image_registry", f"{describe(value)} is not an image registry path such as '{example}'")


def check_cpu_request(field: str, value, example: str, problem) -> None:
    """``problem(field, ...)`` unless ``value`` is a CPU quantity (``0`` for none)."""
    if not isinstance(value, str) or not re.fullmatch(r"(0|[1-9][0-9]*m|[0-9]+(\.[0-9]+)?)", value):
        problem(field, f"{describe(value)} is not a CPU quantity such as {example}, 1 or 0")
