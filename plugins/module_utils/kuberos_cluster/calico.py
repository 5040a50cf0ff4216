"""Calico, the cluster's CNI, from its published release: the objects of Calico's own ``calico-vxlan.yaml`` (the
manifest install with the Kubernetes datastore and a VXLAN pool), adapted to the site.

``calico_objects`` takes the objects of that manifest as Calico publishes it for ``version`` and returns them in
apply order (the CustomResourceDefinitions first), changed only where a site's choices go:

- every Calico image (``calico/node``, ``calico/cni``, ``calico/kube-controllers``) from the site's registry or mirror
  (``image_registry``), at the release's tag; the manifest must be that release's;
- the ``calico-config`` ConfigMap's ``veth_mtu``: the pods' and the VXLAN tunnel's MTU, the network's less the
  encapsulation's 50 bytes, less WireGuard's when pod traffic crosses the site's VPN (``pod_mtu``);
- calico-node's pool settings: ``CALICO_IPV4POOL_CIDR`` (the site's pod network, kubeadm's podSubnet), the block size,
  VXLAN ``Always`` or ``CrossSubnet`` (IP-in-IP never), NAT outgoing, and how it finds each node's address
  (``IP_AUTODETECTION_METHOD``); its CPU request; a hash of the ConfigMap in its pod template, so that an MTU change
  rolls it.

Nothing else of the release is changed: its CRDs (with Calico's own schemas), RBAC, calico-node's tolerations (every
taint, the robots' included) and calico-kube-controllers stay as published. A manifest without the objects this needs
(the ``calico-config`` ConfigMap, the ``calico-node`` DaemonSet and its container) is refused, naming what is missing.
"""

from __future__ import annotations

import copy
import hashlib
import ipaddress
import json
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe, did_you_mean
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.cni import (
    BASE_MTU_RANGE,
    DEFAULT_VPN_MTU,
    MIN_POD_MTU,
    _integer,
    check_cpu_request,
    check_image_registry,
    settings_of,
)

NODE = "calico-node"
KUBE_CONTROLLERS = "calico-kube-controllers"
CONFIG = "calico-config"
NAMESPACE = "kube-system"  # where the published manifest puts Calico's workloads
CONFIG_HASH_ANNOTATION = "kuberos.io/calico-config-hash"
IMAGES = ("node", "cni", "kube-controllers")  # calico/<name>:<release>, as the manifest names them
ENCAPSULATION_MODES = ("Always", "CrossSubnet")
VXLAN_OVERHEAD = 50  # outer IPv4 + UDP + VXLAN headers and the inner Ethernet header
BLOCK_SIZE_RANGE = (20, 32)
AUTODETECTION_VALUES = ("first-found", "kubernetes-internal-ip")
AUTODETECTION_PREFIXES = ("can-reach=", "interface=", "skip-interface=", "cidr=")
_IMAGE = re.compile(r"^(?:[^/]+/)*calico/(?P<name>[a-z-]+):(?P<tag>[^@\s]+)(?:@sha256:[0-9a-f]{64})?\Z")


@dataclass(frozen=True)
class CalicoSettings:
    """What a site chooses about Calico; ``calico_objects`` validates it first."""

    pod_cidr: str
    version: str = "v3.31.3"
    image_registry: str = "quay.io/calico"
    block_size: int = 26
    encapsulation_mode: str = "Always"
    base_mtu: int = 1500
    vpn: bool = False
    vpn_mtu: int = DEFAULT_VPN_MTU  # the WireGuard interface's MTU, which the VPN's traffic must fit
    ip_autodetection_method: str = "first-found"
    nat_outgoing: bool = True
    node_cpu_request: str = "250m"  # calico-node's CPU request, upstream's; "0" for none


def settings_from(pod_cidr, options: dict, prefix: str = "calico_") -> CalicoSettings:
    """Settings from keyword options, an unknown one reported with the closest known name."""
    return settings_of(CalicoSettings, "calico", pod_cidr, options, prefix)


def pod_mtu(base_mtu: int, vpn: bool, vpn_mtu: int = DEFAULT_VPN_MTU) -> int:
    """MTU of the pods' interfaces and Calico's VXLAN tunnel: the smallest MTU on the way (the network's, or the
    WireGuard interface's when pod traffic crosses the VPN) less the encapsulation's headers."""
    return (min(base_mtu, vpn_mtu) if vpn else base_mtu) - VXLAN_OVERHEAD


def check_settings(settings: CalicoSettings, prefix: str = "calico_") -> dict:
    """Every problem with the settings at once, each naming the variable (``prefix`` + field), value and reason.
    Returns the derived values: ``network``, ``block_size`` and ``veth_mtu``."""
    problems: list[Problem] = []

    def problem(field: str, message: str) -> None:
        problems.append(Problem("calico", prefix + field, message))

    s = settings
    if not isinstance(s.version, str) or not re.fullmatch(r"v3\.\d+\.\d+", s.version):
        problem("version", f"{describe(s.version)} is not a Calico release tag such as 'v3.31.3'")
    check_image_registry(s.image_registry, "quay.io/calico", problem)

    network = None
    if not isinstance(s.pod_cidr, str):
        problem("pod_cidr", f"{describe(s.pod_cidr)} is not a network in CIDR notation such as '10.244.0.0/16'")
    elif "/" not in s.pod_cidr:
        problem("pod_cidr", f"{s.pod_cidr!r} has no prefix length; write a network such as '10.244.0.0/16'")
    else:
        try:
            network = ipaddress.ip_network(s.pod_cidr.strip(), strict=True)
        except ValueError as exc:
            hint = ""
            try:
                hint = f"; did you mean '{ipaddress.ip_network(s.pod_cidr.strip(), strict=False)}'?"
            except ValueError:
                pass
            problem("pod_cidr", f"{s.pod_cidr!r} is not an IPv4 or IPv6 network: {exc}{hint}")
        else:
            if network.version != 4:
                problem("pod_cidr", f"{network} is IPv6: Calico's published VXLAN manifest sets up an IPv4 pool")
                network = None

    block_size = _integer(s.block_size)
    low, high = BLOCK_SIZE_RANGE
    if block_size is None or not low <= block_size <= high:
        problem("block_size", f"{describe(s.block_size)} is not a block size for IPv4: an integer from {low} to {high}")
        block_size = None
    elif network is not None and block_size < network.prefixlen:
        problem(
            "block_size",
            f"{block_size} makes blocks larger than the pod CIDR {network} (/{network.prefixlen}); "
            f"use a block size of at least {network.prefixlen}",
        )

    if s.encapsulation_mode not in ENCAPSULATION_MODES:
        problem(
            "encapsulation_mode",
            f"{describe(s.encapsulation_mode)} is not one of {', '.join(ENCAPSULATION_MODES)}"
            f"{did_you_mean(s.encapsulation_mode, ENCAPSULATION_MODES)}",
        )

    base_mtu, vpn_mtu, veth_mtu = _integer(s.base_mtu), _integer(s.vpn_mtu), 0
    if base_mtu is None or not BASE_MTU_RANGE[0] <= base_mtu <= BASE_MTU_RANGE[1]:
        problem("base_mtu", f"{describe(s.base_mtu)} is not an MTU: an integer from {BASE_MTU_RANGE[0]} to {BASE_MTU_RANGE[1]}")
    elif vpn_mtu is None or not 1280 <= vpn_mtu <= 9000:
        problem("vpn_mtu", f"{describe(s.vpn_mtu)} is not the VPN interface's MTU: an integer from 1280 to 9000")
    elif isinstance(s.vpn, bool):
        veth_mtu = pod_mtu(base_mtu, s.vpn, vpn_mtu)
        if veth_mtu < MIN_POD_MTU[4]:
            problem(
                "base_mtu",
                f"{base_mtu} leaves pods an MTU of {veth_mtu} after VXLAN encapsulation"
                f"{' and the WireGuard VPN' if s.vpn else ''}, below IPv4's minimum of {MIN_POD_MTU[4]}",
            )

    for field in ("vpn", "nat_outgoing"):
        if not isinstance(getattr(s, field), bool):
            problem(field, f"{describe(getattr(s, field))} is not a boolean (true or false)")
    _check_autodetection(s.ip_autodetection_method, problem)
    check_cpu_request("node_cpu_request", s.node_cpu_request, "250m", problem)

    if problems:
        raise SpecError(problems, title="invalid Calico settings")
    return {"network": network, "block_size": block_size, "veth_mtu": veth_mtu}


def _check_autodetection(method, problem) -> None:
    known = (
        "first-found, kubernetes-internal-ip, can-reach=<address or name>, interface=<regex>, skip-interface=<regex>, cidr=<cidr>"
    )
    if not isinstance(method, str) or not method:
        problem("ip_autodetection_method", f"{describe(method)} is not an IP autodetection method ({known})")
        return
    if method in AUTODETECTION_VALUES:
        return
    prefix = next((p for p in AUTODETECTION_PREFIXES if method.startswith(p)), None)
    if prefix is None or not method[len(prefix) :].strip():
        problem("ip_autodetection_method", f"{method!r} is not an IP autodetection method ({known})")
        return
    if prefix == "cidr=":
        for part in method[len(prefix) :].split(","):
            try:
                ipaddress.ip_network(part.strip(), strict=False)
            except ValueError as exc:
                problem("ip_autodetection_method", f"{method!r}: {part.strip()!r} is not a network: {exc}")


def calico_objects(published: list, settings: CalicoSettings, source: str = "the manifest", prefix: str = "calico_") -> list:
    """The objects of Calico's published ``calico-vxlan.yaml`` (``published``, read from ``source``) for the site's
    ``settings``, CRDs first. Every problem with the settings or the manifest is reported at once."""
    checked = check_settings(settings, prefix)
    objects = [copy.deepcopy(o) for o in published or [] if isinstance(o, dict) and o]
    problems: list[Problem] = []

    def problem(message: str) -> None:
        problems.append(Problem("calico", source, message))

    if not objects:
        problem("holds no Kubernetes objects: give Calico's published manifests/calico-vxlan.yaml")
        raise SpecError(problems, title="unusable Calico manifest")
    config = _find(objects, "ConfigMap", CONFIG)
    node = _find(objects, "DaemonSet", NODE)
    container = None
    if config is None:
        problem(f"has no ConfigMap {CONFIG} (where the pods' MTU goes): is it Calico's calico-vxlan.yaml?")
    if node is None:
        problem(f"has no DaemonSet {NODE}: is it Calico's calico-vxlan.yaml?")
    else:
        containers = ((node.get("spec") or {}).get("template") or {}).get("spec", {}).get("containers") or []
        container = next((c for c in containers if isinstance(c, dict) and c.get("name") == NODE), None)
        if container is None:
            problem(f"DaemonSet {NODE} has no container {NODE}")
    tags = sorted({match["tag"] for match in _images(objects)})
    if not tags:
        problem("names no calico/node, calico/cni or calico/kube-controllers image")
    elif tags != [settings.version]:
        problem(
            f"is Calico {', '.join(tags)}'s manifest, not {settings.version}'s ({prefix}version): "
            f"give the manifest of the release the images are pulled at"
        )
    if problems:
        raise SpecError(problems, title="unusable Calico manifest")

    for obj in objects:
        for spec in _pod_specs(obj):
            for item in spec.get("initContainers", []) + spec.get("containers", []):
                found = _IMAGE.match(str(item.get("image", "")))
                if found and found["name"] in IMAGES:
                    item["image"] = f"{settings.image_registry}/{found['name']}:{settings.version}"
    config.setdefault("data", {})["veth_mtu"] = str(checked["veth_mtu"])
    _set_env(
        container,
        {
            "CALICO_IPV4POOL_CIDR": str(checked["network"]),
            "CALICO_IPV4POOL_BLOCK_SIZE": str(checked["block_size"]),
            "CALICO_IPV4POOL_VXLAN": settings.encapsulation_mode,
            "CALICO_IPV4POOL_IPIP": "Never",
            "CALICO_IPV4POOL_NAT_OUTGOING": "true" if settings.nat_outgoing else "false",
            "IP_AUTODETECTION_METHOD": settings.ip_autodetection_method,
        },
    )
    requests = container.setdefault("resources", {}).setdefault("requests", {})
    if settings.node_cpu_request == "0":
        requests.pop("cpu", None)
    else:
        requests["cpu"] = settings.node_cpu_request
    template = node["spec"]["template"].setdefault("metadata", {})
    template.setdefault("annotations", {})[CONFIG_HASH_ANNOTATION] = hashlib.sha256(
        json.dumps(config["data"], sort_keys=True).encode()
    ).hexdigest()[:16]
    return [o for o in objects if o.get("kind") == "CustomResourceDefinition"] + [
        o for o in objects if o.get("kind") != "CustomResourceDefinition"
    ]


def _find(objects: list, kind: str, name: str) -> dict | None:
    return next((o for o in objects if o.get("kind") == kind and (o.get("metadata") or {}).get("name") == name), None)


def _pod_specs(obj: dict) -> list:
    spec = obj.get("spec") if isinstance(obj.get("spec"), dict) else {}
    template = spec.get("template") if isinstance(spec.get("template"), dict) else {}
    pod = template.get("spec")
    return [pod] if isinstance(pod, dict) else []


def _images(objects: list) -> list:
    found = []
    for obj in objects:
        for spec in _pod_specs(obj):
            for item in (spec.get("initContainers") or []) + (spec.get("containers") or []):
                match = _IMAGE.match(str(item.get("image", ""))) if isinstance(item, dict) else None
                if match and match["name"] in IMAGES:
                    found.append(match)
    return found


def _set_env(container: dict, values: dict) -> None:
    """Set each variable in the container's environment, in place where it is (upstream leaves some commented out)."""
    env = container.setdefault("env", [])
    for name, value in values.items():
        entry = next((e for e in env if e.get("name") == name), None)
        if entry is None:
            env.append({"name": name, "value": value})
        else:
            entry.pop("valueFrom", None)
            entry["value"] = value
