"""Hosts as network namespaces: one per node, a TUN ``eth0`` each, names resolved by /etc/netns/<ns>/hosts.

A host's ``eth0`` is a TUN device in an address range that exists only inside the run's namespaces; the
fabric (fabric.py) carries its packets. Multicast is routed to ``eth0`` too, so that the fabric sees (and
drops) it rather than the kernel refusing to send. IPv6 is off. ``ip netns exec`` bind-mounts the files of
``/etc/netns/<ns>/`` over ``/etc``, so ``hosts`` there resolves the cluster's Service names.
"""

from __future__ import annotations

import ipaddress
import os
import shutil
import subprocess

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.background_process import run_checked

ETC_NETNS = "/etc/netns"
TUN = "eth0"
FIRST_HOST = 9  # hosts get the subnet's 10th address and on; the first nine are left free


class CommandError(RuntimeError):
    """A command the runtime ran failed."""


def run(*command: str, check: bool = True, timeout: float = 30) -> subprocess.CompletedProcess:
    """Run a command; ``CommandError`` with its output when it fails and ``check`` is set."""
    return run_checked(command, CommandError, check, timeout)


def netns_problem() -> str | None:
    """Why network namespaces with TUN devices cannot be made here (None if they can)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if not shutil.which("ip"):
        return "`ip` (iproute2) is not installed"
    if run("ip", "netns", "list", check=False).returncode != 0:
        return "`ip netns` is not usable"
    if not os.path.exists("/dev/net/tun"):
        return "/dev/net/tun is missing (no TUN support)"
    return None


def host_addresses(subnet: str, nodes: list[str]) -> dict[str, str]:
    """Node -> address: the subnet's 10th, 11th, ... address, in the given order."""
    network = ipaddress.ip_network(subnet)
    hosts = list(network.hosts())
    if len(nodes) > len(hosts) - FIRST_HOST:
        raise ValueError(f"{len(nodes)} hosts do not fit in {subnet}")
    return {node: str(hosts[FIRST_HOST + index]) for index, node in enumerate(nodes)}


def free_address(subnet: str, used) -> str:
    """The lowest of the subnet's 10th, 11th, ... addresses not in ``used``: for a host added while others run,
    whose addresses stay as they are."""
    taken = set(used)
    for address in list(ipaddress.ip_network(subnet).hosts())[FIRST_HOST:]:
        if str(address) not in taken:
            return str(address)
    raise ValueError(f"no address of {subnet} is free")


def create_host(namespace: str, address: str, prefix_len: int, mtu: int) -> None:
    """The namespace with lo up, a TUN eth0 holding ``address`` (unicast and multicast routed to it), no IPv6."""
    run("ip", "netns", "add", namespace)
    run("ip", "-n", namespace, "link", "set", "lo", "up")
    run("ip", "-n", namespace, "tuntap", "add", "dev", TUN, "mode", "tun")
    run("ip", "-n", namespace, "link", "set", TUN, "mtu", str(mtu), "txqueuelen", "4096")
    run(
        "ip",
        "netns",
        "exec",
        namespace,
        "sysctl",
        "-qw",
        "net.ipv6.conf.all.disable_ipv6=1",
        "net.ipv6.conf.default.disable_ipv6=1",
    )
    run("ip", "-n", namespace, "addr", "add", f"{address}/{prefix_len}", "dev", TUN)
    run("ip", "-n", namespace, "link", "set", TUN, "up")
    run("ip", "-n", namespace, "route", "add", "224.0.0.0/4", "dev", TUN)


def delete_host(namespace: str) -> list[str]:
    """Remove the namespace (and its TUN) and its /etc/netns directory; problems as text."""
    problems = []
    if os.path.exists(f"/var/run/netns/{namespace}"):
        done = run("ip", "netns", "delete", namespace, check=False)
        if done.returncode != 0:
            problems.append(f"ip netns delete {namespace}: {(done.stderr or done.stdout).strip()}")
    shutil.rmtree(os.path.join(ETC_NETNS, namespace), ignore_errors=True)
    return problems


def hosts_file(names: dict[str, str]) -> str:
    """An /etc/hosts: localhost, then each address with its names (name -> address)."""
    by_address: dict[str, list[str]] = {}
    for name, address in names.items():
        by_address.setdefault(address, []).append(name)
    lines = ["127.0.0.1 localhost", "::1 localhost ip6-localhost"]
    lines += [f"{address} {' '.join(sorted(hostnames))}" for address, hostnames in sorted(by_address.items())]
    return "\n".join(lines) + "\n"


def write_hosts(namespace: str, text: str) -> bool:
    """Write /etc/netns/<namespace>/hosts; True when this call created /etc/netns itself."""
    created = not os.path.isdir(ETC_NETNS)
    os.makedirs(os.path.join(ETC_NETNS, namespace), exist_ok=True)
    with open(os.path.join(ETC_NETNS, namespace, "hosts"), "w", encoding="utf-8") as handle:
        handle.write(text)
    return created


def service_names(service: str, namespace: str, cluster_domain: str) -> list[str]:
    """The DNS names a pod resolves a Service by: ``<svc>.<ns>.svc.<domain>``, ``<svc>.<ns>.svc``, ``<svc>.<ns>``."""
    return [f"{service}.{namespace}.svc.{cluster_domain}", f"{service}.{namespace}.svc", f"{service}.{namespace}"]
