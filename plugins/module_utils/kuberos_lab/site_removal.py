"""The site chain's removal steps on the lab site (``tests/site``): a node removed with ``remove_node.yml`` and
forgotten by the inventory as its last message asks, the whole site reset with ``reset.yml``, and what a machine
still holds of the site afterwards (``leftovers``: empty when it was cleaned)."""

from __future__ import annotations

import glob
import os
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_lab import MACHINES, SiteChain, nodes

# What a reset leaves on none of its machines: kubeadm's files, the pod network's, its interfaces and chains.
NODE_FILES = ("/etc/kubernetes/kubelet.conf", "/etc/kubernetes/admin.conf", "/etc/kubernetes/manifests/etcd.yaml",
              "/var/lib/kubelet/config.yaml", "/etc/cni/net.d/05-cilium.conflist", "/var/lib/etcd/member")  # fmt: skip
INTERFACES = ("cilium_host", "cilium_net", "cilium_vxlan", "wg-kuberos")
CHAINS = ("KUBE-", "CILIUM")


def _drop(group: dict, host: str) -> bool:
    """Take ``host`` out of an inventory group and its children, in place; True when it was there."""
    found = False
    hosts = group.get("hosts") or {}
    if host in hosts:
        del hosts[host]
        found = True
    for child in (group.get("children") or {}).values():
        if isinstance(child, dict):
            found = _drop(child, host) or found
    return found


def forget(inventory: str, host: str) -> list[str]:
    """Do what remove_node.yml asks of the inventory: ``host`` out of every inventory file of the directory and its
    host_vars file removed. Returns the files changed."""
    import yaml

    changed = []
    for path in sorted(glob.glob(os.path.join(inventory, "*.yml")) + glob.glob(os.path.join(inventory, "*.yaml"))):
        with open(path, encoding="utf-8") as handle:
            data = yaml.safe_load(handle)
        if isinstance(data, dict) and any(isinstance(g, dict) and _drop(g, host) for g in data.values()):
            with open(path, "w", encoding="utf-8") as handle:
                yaml.safe_dump(data, handle, sort_keys=False)
            changed.append(path)
    for path in (os.path.join(inventory, "host_vars", f"{host}.{ext}") for ext in ("yml", "yaml")):
        if os.path.exists(path):
            os.remove(path)
            changed.append(path)
    return changed


def leftovers(machines, name: str) -> list[str]:
    """What machine ``name`` still holds of the site: a kubelet running or starting at boot, containers of the
    kubelet, kubeadm's and the pod network's files, its interfaces, netfilter chains of kube-proxy and the CNI."""
    found = []

    def run(*argv: str) -> str:
        return machines.exec(name, *argv, check=False).stdout

    if run("systemctl", "is-active", "kubelet").strip() == "active":
        found.append("the kubelet runs")
    if run("systemctl", "is-enabled", "kubelet").strip() == "enabled":
        found.append("the kubelet starts at boot")
    found += [f"{path} is there" for path in NODE_FILES if os.path.lexists(machines.rootfs(name) + path)]
    tasks = [line for line in run("ctr", "-n", "k8s.io", "tasks", "ls").splitlines()[1:] if "RUNNING" in line]
    if tasks:
        found.append(f"{len(tasks)} containers of the kubelet run")
    links = run("ip", "-o", "link", "show")
    found += [f"interface {link}" for link in INTERFACES if f": {link}:" in links or f": {link}@" in links]
    for tool in ("iptables-save", "iptables-legacy-save", "ip6tables-save"):
        rules = run(tool)
        declared = [line[1:].split()[0] for line in rules.splitlines() if line.startswith(":")]
        chains = sorted({chain for chain in declared if chain.startswith(CHAINS)})
        if chains:
            found.append(f"{tool}: chains {', '.join(chains[:5])}{' ...' if len(chains) > 5 else ''}")
    return found


def remove_node(chain: SiteChain, host: str, machine: str) -> dict:
    """remove_node.yml for ``host`` (the lab's ``machine``), then the inventory forgets it. Records
    ``remove_<machine>_s``; returns the run, the lines it said, the node's presence after it and the machine's
    leftovers."""
    started = time.monotonic()
    # The deployments' passes are rollouts: their gates check the ROS graph, whose external topics come from the
    # robots' simulated hardware, not running between pick cycles (the chain's deploy leaves the check out too).
    result = chain._play("remove_node.yml", "-e", f"node={host}", "-e", "rosdeployment_graph_check=false")
    seconds = round(time.monotonic() - started, 1)
    chain.figures[f"remove_{machine.replace('-', '_')}_s"] = seconds
    said = result.stdout[result.stdout.rfind("TASK [Say it]") :][:3000] if "TASK [Say it]" in result.stdout else ""
    said = " ".join(said.split())  # the callback folds a long message over lines wherever its width ends
    forgotten = forget(chain.lab.inventory, host) if result.returncode == 0 else []
    left = leftovers(chain.lab.machines, machine) if result.returncode == 0 else ["remove_node.yml failed"]
    node_left = machine in nodes(chain.kube)
    clean = result.returncode == 0 and not node_left and not left and bool(forgotten)
    chain.figures["node_removed_clean"] = chain.figures.get("node_removed_clean", True) and clean
    return {"result": result, "said": said, "forgotten": forgotten, "node_left": node_left, "leftovers": left}


def inventory_name(machine: str) -> str:
    """The sample inventory's name of a lab machine."""
    return next(host for host, (name, _networks, _cpu) in MACHINES.items() if name == machine)


def reset_site(chain: SiteChain, first_control_plane: str, machines: list[str]) -> dict:
    """reset.yml with its confirmation (``first_control_plane``: its inventory name); returns the run and each
    running machine's leftovers (those of ``machines`` that are powered off are left out). Records ``site_reset_s``
    and ``site_reset_clean``."""
    result = chain._play("reset.yml", "-e", f"reset_site={first_control_plane}")
    running = [m for m in machines if chain.lab.machines.exec(m, "true", check=False).returncode == 0]
    left = {m: leftovers(chain.lab.machines, m) for m in running}
    chain.figures["site_reset_s"] = round(result.seconds, 1)
    chain.figures["site_reset_clean"] = result.returncode == 0 and not any(left.values())
    return {"result": result, "running": running, "leftovers": left, "kubeconfig_left": os.path.exists(chain.lab.kubeconfig)}
