"""A Kubernetes upgrade's plan: from the cluster as it is to the version the inventory names, one minor at a time.

kubeadm upgrades a cluster one minor version at a time: ``kubeadm upgrade apply`` on one control plane moves the
cluster's configuration (kubeadm-config's ``kubernetesVersion``) and that control plane's static pods, ``kubeadm
upgrade node`` the others and every worker's kubelet configuration; each node's kubelet follows. This module reads
where each node stands and says what a run does to it, or why the run refuses, naming both versions:

- ``upgrade``: the node's kubelet is older than the target (a control plane's static pods come first);
- ``done``: already at the target (a run cut off half-way is finished by the next);
- ``pending``: a robot that does not answer (powered off): left alone, reported, finished by the next run;
- ``behind``: a node more than one minor below the target (a robot offline through an earlier upgrade): kubeadm
  cannot take it two minors at once; it keeps running (a kubelet may be three minors older than the API server)
  until a run at the minor it missed;
- ``not_joined``: an inventory host without a Node (site.yml joins it, at the target).

Refused: a version that is not one, a downgrade, a skip of a minor, a node newer than the target, a control plane
or a worker that does not answer (they are the site: a run leaves none behind), and a target more than three minors
above a kubelet that would stay behind.
"""

from __future__ import annotations

import re

VERSION = re.compile(r"\Av(\d{1,3})\.(\d{1,3})\.(\d{1,4})\Z")
KUBELET_SKEW = 3  # a kubelet may be up to three minor versions older than the API server (Kubernetes 1.28 and later)
KINDS = ("control_plane", "worker", "robot")


def parse_version(text) -> tuple[int, int, int] | None:
    """``v1.34.4`` -> (1, 34, 4); anything else (a build suffix, no ``v``) -> None."""
    found = VERSION.match(str(text or "").strip())
    return tuple(int(n) for n in found.groups()) if found else None  # type: ignore[return-value]


def _minor(version: tuple[int, int, int]) -> str:
    return f"v{version[0]}.{version[1]}"


def _node_versions(nodes) -> dict[str, str]:
    """Node name -> its kubelet's version, from Node objects (``status.nodeInfo.kubeletVersion``)."""
    found = {}
    for node in nodes or ():
        if not isinstance(node, dict):
            continue
        name = str((node.get("metadata") or {}).get("name") or "")
        if name:
            found[name] = str(((node.get("status") or {}).get("nodeInfo") or {}).get("kubeletVersion") or "")
    return found


def upgrade_plan(target: str, cluster_version: str, nodes, hosts) -> dict:
    """The run's plan.

    ``target``: the version to reach (``kuberos_kubernetes_version``). ``cluster_version``: the cluster's, as kubeadm
    keeps it (kubeadm-config's ``kubernetesVersion``). ``nodes``: the Node objects. ``hosts``: the inventory's
    machines in the order they are upgraded, each ``{host, node, kind, reached}`` (``kind`` one of control_plane,
    worker, robot). Returns ``refusal`` (empty when the run may go on), ``from``, ``to``, ``apply`` (the cluster's
    configuration still has to move: ``kubeadm upgrade apply`` on ``apply_host``), ``hosts`` (host -> node, kind,
    kubelet, action, why), the lists per action and ``lines`` (what the run does, for people)."""
    wanted, current = parse_version(target), parse_version(cluster_version)
    plan: dict = {"refusal": "", "from": str(cluster_version or ""), "to": str(target or ""), "apply": False,
                  "apply_host": "", "hosts": {}, "upgrade": [], "done": [], "pending": [], "behind": [],
                  "not_joined": [], "lines": []}  # fmt: skip
    if wanted is None:
        plan["refusal"] = f"kuberos_kubernetes_version: {str(target)[:40]!r} is not a Kubernetes version such as v1.34.4"
        return plan
    if current is None:
        plan["refusal"] = (f"the cluster's version (kubeadm-config's kubernetesVersion) is {str(cluster_version)[:40]!r}, "
                           "not a version such as v1.33.7: is this a kubeadm cluster?")  # fmt: skip
        return plan
    if wanted[0] != current[0]:
        plan["refusal"] = f"kuberos_kubernetes_version {target} changes the major version of the cluster's {cluster_version}"
    elif wanted < current:
        plan["refusal"] = (f"kuberos_kubernetes_version {target} is older than the cluster's {cluster_version}: "
                           "kubeadm does not downgrade a cluster (restore an etcd snapshot taken before the upgrade "
                           "instead)")  # fmt: skip
    elif wanted[1] > current[1] + 1:
        plan["refusal"] = (f"kuberos_kubernetes_version {target} is {wanted[1] - current[1]} minor versions above the "
                           f"cluster's {cluster_version}: upgrade one minor version at a time (first to a "
                           f"v{current[0]}.{current[1] + 1} release)")  # fmt: skip
    if plan["refusal"]:
        return plan
    plan["apply"] = wanted > current
    kubelets = _node_versions(nodes)
    problems = []
    for entry in hosts or ():
        host, node = str(entry.get("host") or ""), str(entry.get("node") or entry.get("host") or "")
        kind, reached = str(entry.get("kind") or ""), bool(entry.get("reached"))
        if kind not in KINDS:
            problems.append(f"{host}: kind {kind!r} is not one of {', '.join(KINDS)}")
            continue
        kubelet = kubelets.get(node, "")
        version = parse_version(kubelet)
        row = {"node": node, "kind": kind, "kubelet": kubelet, "action": "", "why": ""}
        if node not in kubelets:
            row["action"], row["why"] = "not_joined", "no Node (site.yml joins it, at the target)"
        elif version is None:
            problems.append(f"{host} (node {node}): its kubelet's version {kubelet[:40]!r} is not a version such as v1.33.7")
            continue
        elif version > wanted:
            problems.append(f"{host} (node {node}) runs kubelet {kubelet}, newer than kuberos_kubernetes_version {target}")
            continue
        elif version == wanted:
            row["action"] = "done"
        elif not reached and kind == "robot":
            row["action"], row["why"] = "pending", "does not answer (powered off?): the next run upgrades it"
        elif not reached:
            problems.append(f"{host} (a {kind.replace('_', ' ')}) does not answer: control planes and workers are "
                            "upgraded in every run; bring it back, or remove it (remove_node.yml)")  # fmt: skip
            continue
        elif version[:2] < (wanted[0], wanted[1] - 1):
            row["action"] = "behind"
            row["why"] = (f"kubelet {kubelet} is more than one minor below {target}: upgrade it with a "
                          f"{_minor((wanted[0], wanted[1] - 1, 0))} release first")  # fmt: skip
        else:
            row["action"] = "upgrade"
        if row["action"] in ("behind", "pending") and version and wanted[1] - version[1] > KUBELET_SKEW:
            problems.append(f"{host} (node {node}) would stay at kubelet {kubelet}, more than {KUBELET_SKEW} minor "
                            f"versions below {target}, which the API server does not support")  # fmt: skip
            continue
        plan["hosts"][host] = row
        plan[row["action"]].append(host)
    if problems:
        plan["refusal"] = "; ".join(problems)
        return plan
    control_planes = [h for h, row in plan["hosts"].items() if row["kind"] == "control_plane"]
    if plan["apply"]:
        if not control_planes:
            plan["refusal"] = "no control plane in the inventory (group control_plane) to run kubeadm upgrade apply on"
            return plan
        plan["apply_host"] = control_planes[0]
    plan["lines"] = _lines(plan)
    return plan


def _lines(plan: dict) -> list[str]:
    lines = [
        f"Kubernetes {plan['from']} -> {plan['to']}"
        + ("" if plan["apply"] else " (the cluster's configuration is there already)")
    ]
    if plan["apply"]:
        lines.append(f"kubeadm upgrade apply {plan['to']} on {plan['apply_host']}, then kubeadm upgrade node on each other node")
    for action, title in (("upgrade", "to upgrade, one at a time (control planes, workers; robots in place)"),
                          ("done", "already at the target"), ("pending", "left pending (offline)"),
                          ("behind", "left behind (more than one minor below the target)"),
                          ("not_joined", "not joined (site.yml joins them)")):  # fmt: skip
        if plan[action]:
            lines.append(f"{title}: {', '.join(plan[action])}")
    if not plan["apply"] and not plan["upgrade"]:
        lines.append("nothing to do")
    return lines
