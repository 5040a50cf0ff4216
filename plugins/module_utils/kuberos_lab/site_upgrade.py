"""The site chain's Kubernetes upgrade on the lab site (``tests/site``): the site built at an older release
(``site_lab.KUBERNETES_VERSION_ENV``), then ``upgrade.yml`` to the pinned release with the app running, as an
engineer would: the new version and its programs written into the inventory (``group_vars/all/20-upgrade.yml``), the
playbook run. Sampled throughout: the API through the virtual IP (``site_operations.ApiSampler``, every 0.4 s), the
virtual IP's holders (``site_replace.VipSampler``, every 0.5 s), every placed pod's readiness (every 0.5 s), and pick
cycles run one after another on a robot. Every wait is bounded. Lab only: nothing in the collection imports it.
"""

from __future__ import annotations

import os
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import site_lab
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_operations import ApiSampler, longest_outage
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_replace import Sampler, VipSampler

INSTANCE = "kuberos.io/instance"
FIGURES = (
    "upgrade_from", "upgrade_to", "upgrade_s", "api_unavailable_max_s", "api_samples_during_upgrade", "app_downtime_max_s",
    "robot_downtime_max_s", "pick_cycles_during_upgrade", "onboard_pods_restarted_by_upgrade",
    "vip_holders_max_during_upgrade", "kubelets_after_upgrade",
)  # fmt: skip


class PodSampler(Sampler):
    """Every placed pod's readiness (label ``kuberos.io/instance``) every ``every`` seconds until stopped (at most
    ``limit`` s): per instance, (monotonic time, Ready) samples, and the node it last ran on."""

    def __init__(self, kube, every: float = 0.5, limit: float = 3600):
        super().__init__(every, limit)
        self.core = kube.clients["core"]
        self.samples: dict[str, list[tuple[float, bool]]] = {}
        self.nodes: dict[str, str] = {}  # instance -> the node it last ran on

    def sample(self, moment: float) -> None:
        try:
            pods = self.core.list_pod_for_all_namespaces(label_selector=INSTANCE, _request_timeout=2).items
        except Exception:  # pylint: disable=broad-exception-caught  # the API away: no sample, the ApiSampler counts it
            return
        ready: dict[str, bool] = {}
        for pod in pods:
            name = (pod.metadata.labels or {}).get(INSTANCE, "")
            statuses = pod.status.container_statuses or []
            up = pod.status.phase == "Running" and bool(statuses) and all(c.ready for c in statuses)
            ready[name] = ready.get(name, False) or up
            if pod.spec.node_name:
                self.nodes[name] = pod.spec.node_name
        for name, up in ready.items():
            self.samples.setdefault(name, []).append((moment, up))
        for name in set(self.samples) - set(ready):  # no pod at all: not Ready
            self.samples[name].append((moment, False))

    def longest_downtime(self, where) -> tuple[float, str]:
        """The longest time an instance whose node ``where(node)`` accepts was not Ready, and which."""
        found = (0.0, "")
        for name, samples in self.samples.items():
            if where(self.nodes.get(name, "")):
                found = max(found, (longest_outage(samples), name))
        return found


def kubelets(kube) -> dict[str, str]:
    """node -> its kubelet's version."""
    return {
        n["metadata"]["name"]: ((n.get("status") or {}).get("nodeInfo") or {}).get("kubeletVersion", "")
        for n in kube.list("Node")
    }


def cluster_version(kube) -> str:
    """The cluster's version as kubeadm keeps it (kubeadm-config's ClusterConfiguration)."""
    import yaml

    config = kube.get("ConfigMap", "kubeadm-config", namespace="kube-system") or {}
    cluster = yaml.safe_load((config.get("data") or {}).get("ClusterConfiguration") or "{}") or {}
    return str(cluster.get("kubernetesVersion", ""))


def robot_pods(core, robots: set[str]) -> dict[str, tuple[str, int]]:
    """Every placed pod on a robot's node (its onboard modules and discovery server; not the cluster's add-ons, which
    the upgrade replaces by design): name -> (uid, the sum of its containers' restarts)."""
    found = {}
    for pod in core.list_pod_for_all_namespaces(label_selector=INSTANCE, _request_timeout=30).items:
        if pod.spec.node_name in robots:
            restarts = sum(c.restart_count or 0 for c in pod.status.container_statuses or [])
            found[pod.metadata.name] = (pod.metadata.uid, restarts)
    return found


class PickCycles(threading.Thread):
    """Pick cycles on ``robot``, one after another until stopped: how many completed while it ran."""

    def __init__(self, chain, robot: str, fleet: str):
        super().__init__(daemon=True)
        self.chain, self.robot, self.fleet = chain, robot, fleet
        self.completed, self.runs, self.outputs = 0, 0, []
        self._stopping = threading.Event()

    def run(self) -> None:
        while not self._stopping.is_set() and self.runs < 500:
            done = self.chain.pick_cycles(self.robot, self.fleet, cycles=1, time_limit=300)
            self.runs += 1
            self.completed += sum(c.get("succeeded", 0) for c in done["summary"].get("cycles", {}).values())
            self.outputs.append(done["output"][-1500:])

    def stop(self, timeout: float = 420) -> None:
        self._stopping.set()
        self.join(timeout)


def write_target(chain, version: str, binaries: dict[str, str]) -> str:
    """The inventory change an engineer makes before upgrade.yml: the new version and, on the binaries path, its
    programs (``group_vars/all/20-upgrade.yml``, read after the lab's ``10-lab.yml``)."""
    import yaml

    path = chain.lab.path("inventory", "group_vars", "all", "20-upgrade.yml")
    with open(path, "w", encoding="utf-8") as handle:
        yaml.safe_dump({"kuberos_kubernetes_version": version, "node_prereqs_kubernetes_binaries": binaries}, handle)
    return path


def upgrade_site(chain, version: str, binaries: dict[str, str], robot: str, fleet: str, timeout: float = 3600) -> dict:
    """``upgrade.yml`` to ``version`` with the app running. Records ``upgrade_from``, ``upgrade_to``, ``upgrade_s``,
    ``api_unavailable_max_s``, ``api_samples_during_upgrade``, ``app_downtime_max_s`` (the edge's and cloud's placed
    instances), ``robot_downtime_max_s``, ``pick_cycles_during_upgrade``, ``onboard_pods_restarted_by_upgrade``
    and ``vip_holders_max_during_upgrade``. Returns the run and what was sampled."""
    robots = {
        name for name, node in site_lab.nodes(chain.kube).items() if node.get("labels", {}).get("kuberos.io/role") == "robot"
    }
    before_versions = kubelets(chain.kube)
    onboard_before = robot_pods(chain.core, robots)
    write_target(chain, version, binaries)
    pods = PodSampler(chain.kube)
    vip = VipSampler(chain.lab.machines)
    cycles = PickCycles(chain, robot, fleet)
    pods.start()
    vip.start()
    try:
        with ApiSampler(chain.kube) as api:
            cycles.start()
            time.sleep(5)  # the first cycle's pod under way before the upgrade starts
            result = chain._play("upgrade.yml", timeout=timeout)
    finally:
        pods.stop()
        vip.stop()
        cycles.stop()
    onboard_after = robot_pods(chain.core, robots)
    restarted = sorted(
        name for name, (uid, restarts) in onboard_before.items() if onboard_after.get(name, ("gone", 0)) != (uid, restarts)
    )
    app_down, app_which = pods.longest_downtime(lambda node: bool(node) and node not in robots)
    robot_down, robot_which = pods.longest_downtime(lambda node: node in robots)
    after_versions = kubelets(chain.kube)
    chain.figures.update({
        "upgrade_from": sorted(set(before_versions.values())),
        "upgrade_to": version,
        "upgrade_s": round(result.seconds, 1),
        "api_unavailable_max_s": round(api.longest_outage(), 1),
        "api_samples_during_upgrade": len(api.samples),
        "app_downtime_max_s": round(app_down, 1),
        "robot_downtime_max_s": round(robot_down, 1),
        "pick_cycles_during_upgrade": cycles.completed,
        "onboard_pods_restarted_by_upgrade": len(restarted),
        "vip_holders_max_during_upgrade": vip.holders_max,
        "kubelets_after_upgrade": sorted(set(after_versions.values())),
    })  # fmt: skip
    return {
        "result": result, "restarted": restarted, "app_down": (app_down, app_which), "robot_down": (robot_down, robot_which),
        "after": after_versions, "before": before_versions, "cycles": cycles, "vip": vip, "api_samples": len(api.samples),
    }  # fmt: skip


def binaries_path_exists(binaries: dict[str, str]) -> list[str]:
    """The programs of ``binaries`` that are missing here."""
    return sorted(name for name, path in binaries.items() if not os.path.exists(path))
