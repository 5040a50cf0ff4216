"""The controller's Prometheus metrics (``prometheus_client``), served on ``/metrics`` beside the dashboard.

``prometheus_client`` is imported only when a controller builds its metrics (ansible-test's import check runs without
it). Gauges are read at scrape time from the dashboard's latest ``View`` (the same numbers the pages show); counters
and the histogram are kept by the controller as it acts. Names and labels are listed in docs/monitoring.md:

- ``kuberos_module_instances{namespace, deployment, module, tier, phase}``
- ``kuberos_module_moves_total{reason}`` (node_failure, pod_failure, latency, other; only the leader moves)
- ``kuberos_module_stranded{namespace, deployment, module}``
- ``kuberos_robot_online{robot, fleet, node}``
- ``kuberos_node_allocatable{node, resource}``, ``kuberos_node_allocated{node, resource}`` (cpu in cores,
  memory in bytes, gpu, pods; allocated is what KubeROS pods request), ``kuberos_node_ready{node, tier}``
- ``kuberos_node_rtt_ms{node, peer}``, ``kuberos_module_rtt_ms{namespace, deployment, module, robot, node}``,
  ``kuberos_module_max_latency_ms{namespace, deployment, module}``
- ``kuberos_reconcile_duration_seconds`` (histogram), ``kuberos_controller_leader{identity}``
- ``kuberos_module_scaling_total{deployment, module, reason}``: scaling steps (docs/scaling.md)
- ``kuberos_apiserver_certificate_expiry_seconds{endpoint}``: what the API server's serving certificate has left
  (``certificates.py``)
"""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import RESOURCES, View, instance_counts

MOVE_REASONS = ("node_failure", "pod_failure", "latency", "other")
PHASES = ("Running", "Pending", "Stranded", "Missing", "Moving", "Remote", "Offline")


def move_reason(why: str) -> str:
    """The reason label of a move, from the fault the controller saw (``reconcile``'s wording)."""
    text = why.lower()
    if text.startswith("node "):
        return "node_failure"
    if text.startswith("pod "):
        return "pod_failure"
    if text.startswith("measured rtt"):
        return "latency"
    return "other"


class ViewCollector:
    """Gauges from the latest view; ``view_of`` returns it (built at most a moment ago)."""

    def __init__(self, view_of, leader_of):
        self.view_of = view_of
        self.leader_of = leader_of  # () -> (identity, leading)

    def describe(self):
        return []  # collected at scrape time only: the families depend on what runs

    def collect(self):
        from prometheus_client.core import GaugeMetricFamily

        view: View = self.view_of()
        instances = GaugeMetricFamily(
            "kuberos_module_instances",
            "Module instances by deployment, module, tier and phase (a shared instance counts once).",
            labels=("namespace", "deployment", "module", "tier", "phase"),
        )
        counts = instance_counts(view)
        modules = sorted({key[:4] for key in counts})
        for module in modules:
            for phase in PHASES:
                instances.add_metric((*module, phase), counts.get((*module, phase), 0))
        yield instances

        stranded = GaugeMetricFamily(
            "kuberos_module_stranded",
            "Instances that should move (their node failed, their pod keeps failing, their link is too slow) but have "
            "no feasible node.",
            labels=("namespace", "deployment", "module"),
        )
        per_module: dict[tuple, int] = {}
        for (namespace, deployment, module, _tier, phase), count in counts.items():
            key = (namespace, deployment, module)
            per_module[key] = per_module.get(key, 0) + (count if phase == "Stranded" else 0)
        for key, count in sorted(per_module.items()):
            stranded.add_metric(key, count)
        yield stranded

        allocatable = GaugeMetricFamily(
            "kuberos_node_allocatable", "What a node offers: cpu (cores), memory (bytes), gpu, pods.", labels=("node", "resource")
        )
        allocated = GaugeMetricFamily(
            "kuberos_node_allocated", "What the KubeROS pods on a node request: cpu (cores), memory (bytes), gpu, pods.",
            labels=("node", "resource"),
        )  # fmt: skip
        ready = GaugeMetricFamily("kuberos_node_ready", "1 while the node is Ready.", labels=("node", "tier"))
        rtt = GaugeMetricFamily(
            "kuberos_node_rtt_ms", "Measured round-trip time from a robot's node to a peer node, in milliseconds.",
            labels=("node", "peer"),
        )  # fmt: skip
        for row in view.resources:
            for resource in RESOURCES:
                allocatable.add_metric((row["name"], resource), row["allocatable"][resource])
                allocated.add_metric((row["name"], resource), row["allocated"][resource])
            ready.add_metric((row["name"], row["tier"]), 1 if row["ready"] else 0)
            for peer, ms in sorted(row["rtt_ms"].items()):
                rtt.add_metric((row["name"], peer), ms)
        yield from (allocatable, allocated, ready, rtt)

        online = GaugeMetricFamily(
            "kuberos_robot_online",
            "1 while the robot's computer is Ready, 0 while it is offline (its onboard modules stay and run there).",
            labels=("robot", "fleet", "node"),
        )
        for row in view.resources:
            if row["tier"] == "onboard":
                online.add_metric((row["robot"] or row["name"], row["fleet"], row["name"]), 1 if row["ready"] else 0)
        yield online

        module_rtt = GaugeMetricFamily(
            "kuberos_module_rtt_ms",
            "Measured round-trip time from a robot to the node running one of its modules, in milliseconds.",
            labels=("namespace", "deployment", "module", "robot", "node"),
        )
        for row in view.modules:
            if row["rtt_ms"] is not None:
                labels = (row["namespace"], row["deployment"], row["module"], row["robot"], row["node"])
                module_rtt.add_metric(labels, row["rtt_ms"])
        yield module_rtt
        limit = GaugeMetricFamily(
            "kuberos_module_max_latency_ms", "A module's max_latency requirement, in milliseconds.",
            labels=("namespace", "deployment", "module"),
        )  # fmt: skip
        for entry in view.max_latency:
            limit.add_metric((entry["namespace"], entry["deployment"], entry["module"]), entry["max_latency_ms"])
        yield limit

        identity, leading = self.leader_of()
        leader = GaugeMetricFamily(
            "kuberos_controller_leader", "1 on the controller replica that holds the Lease and acts, 0 on the others.",
            labels=("identity",),
        )  # fmt: skip
        leader.add_metric((identity,), 1 if leading else 0)
        yield leader


class CertificateCollector:
    """The API server certificate's remaining lifetime (``certificates.ApiServerCertificate``), read at scrape time."""

    def __init__(self, certificate):
        self.certificate = certificate

    def describe(self):
        return []

    def collect(self):
        from prometheus_client.core import GaugeMetricFamily

        found = self.certificate.remaining()
        if found is None:
            return
        expiry = GaugeMetricFamily(
            "kuberos_apiserver_certificate_expiry_seconds",
            "Seconds until the serving certificate of the API server the controller talks to expires.",
            labels=("endpoint",),
        )
        expiry.add_metric((found[0],), found[1])
        yield expiry


class ControllerMetrics:
    """The registry of one controller process."""

    def __init__(self, view_of, leader_of, certificate=None):
        from prometheus_client import CollectorRegistry, Counter, Histogram  # imported when a controller runs one

        self.registry = CollectorRegistry(auto_describe=False)
        self.moves = Counter(
            "kuberos_module_moves", "Module instances the controller moved, by the fault that moved them.", ("reason",),
            registry=self.registry,
        )  # fmt: skip
        for reason in MOVE_REASONS:
            self.moves.labels(reason)  # every series exists from the start (rate() needs a first sample)
        self.reconcile = Histogram(
            "kuberos_reconcile_duration_seconds", "Time of one reconcile pass over every deployment record.",
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30), registry=self.registry,
        )  # fmt: skip
        self.scaling = Counter(
            "kuberos_module_scaling", "Scaling steps of shared modules: ModuleScaledUp, ModuleScaledDown, "
            "ModuleInstanceStopped (drained), ModuleScaleBlocked (no node for another instance).",
            ("deployment", "module", "reason"), registry=self.registry,
        )  # fmt: skip
        self.registry.register(ViewCollector(view_of, leader_of))
        if certificate is not None:
            self.registry.register(CertificateCollector(certificate))

    def scaled(self, deployment: str, module: str, reason: str) -> None:
        self.scaling.labels(deployment, module, reason).inc()

    def moved(self, why: str) -> None:
        self.moves.labels(move_reason(why)).inc()
