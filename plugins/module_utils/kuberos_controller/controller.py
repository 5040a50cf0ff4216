"""The KubeROS controller: keeps every module of every RosDeployment placed well.

It watches (list, then watch from the resourceVersion, relisting after errors or a 410) the nodes,
the KubeROS pods and Deployments, and the deployment records that deploy writes
(``kuberos-record-<deployment>`` ConfigMaps in the fleet namespaces). On every change, and when a
fault's grace period ends, it runs one pass per record:

1. decide (``kuberos.reconcile.decide``, pure): which instances move and where, with the scheduler's
   own rules, or which faults still wait for their grace period;
2. write the new placement into the record first (optimistic: the record's resourceVersion must not
   have changed), so a controller killed mid-move restarts from the truth in the cluster;
3. converge: every Deployment whose pinned node differs from the record is applied again (server-side
   apply, the record's field manager), and pods of moved instances left on a node that is down are
   deleted at once, so the Recreate strategy can start the new pod (the module never runs twice);
4. scale: a shared module with a ``scaling`` policy gets the instances its load signal asks for
   (``kuberos.scaling``, pure; signals from ``signals.py``), when nothing of its deployment moves or rolls out:
   new instances are placed, written to the record and created; robots are handed over once a new instance is
   Ready, and a removed instance is deleted after its drain time;
5. report: a Kubernetes Event per move, scaling step or stranded module, and the status ConfigMap
   ``kuberos-status-<deployment>`` (a table and JSON per robot and module: node, phase, pod, last move).

Run it as a process (``cli.py``): ``python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller
--kubeconfig FILE`` (``--once`` for a single pass; in a pod, without ``--kubeconfig``, it uses the
ServiceAccount). Measured round-trip times come from the robot nodes' ``kuberos.io/rtt-ms``
annotation: JSON mapping a node's inventory name to milliseconds.

Several replicas run side by side: every replica watches, and only the holder of the Lease
``kuberos-system/kuberos-controller`` acts (``leader_election``). Every write is fenced: it is made only
while this replica's right to act lasts, with a client-side timeout of the time left.
"""

from __future__ import annotations

import logging
import threading

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity, scaling
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    Memory,
    Settings,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    RECORD_LABEL,
    Record,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.act import Acting
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.lead import LEASE_NAME, LEASE_NAMESPACE, Leading
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.liveness import NodeProbe
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.observe import Observing
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.report import CONTROLLER_MANAGER, Reporting
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.signals import Signals
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import RTT_ANNOTATION
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, clients_of

__all__ = ["CONTROLLER_MANAGER", "LEASE_NAME", "LEASE_NAMESPACE", "RTT_ANNOTATION", "Controller"]
log = logging.getLogger("kuberos.controller")


class Controller(Observing, Acting, Reporting, Leading):
    """One replica of the controller: its watch caches, its memory of faults and moves, its fence; the passes
    themselves are its parts' (observe, act, report, lead)."""

    def __init__(self, api_client, settings: Settings | None = None, resync_s: float = 30.0, dry_run: bool = False,
                 elector: leader_election.LeaderElector | None = None, identity: str = "",
                 prometheus_url: str = "", node_probe_interval: float = 0.0):  # fmt: skip

        self.api_client = api_client
        # every call through the access layer; each write fenced (``_write_timeout`` refuses one this replica may not make)
        self.kube = Kube(clients_of(api_client), timeout=self._write_timeout)
        self.settings = settings or Settings()
        self.dry_run = dry_run  # decide and report, write nothing (check mode)
        self.resync_s = resync_s
        self.changed = threading.Event()
        self.stop_event = threading.Event()
        managed = f"{MANAGED_BY}=kuberos"
        self.nodes = Store("nodes", self.kube.list_call("Node"), self.changed)
        self.pods = Store("pods", self.kube.list_call("Pod"), self.changed, label_selector=managed)
        self.deployments = Store("deployments", self.kube.list_call("Deployment"), self.changed, label_selector=managed)
        self.records = Store("records", self.kube.list_call("ConfigMap"), self.changed, label_selector=f"{RECORD_LABEL}=true")
        self.stores = (self.nodes, self.pods, self.deployments, self.records)
        # The controller's own probe of the server nodes' kubelets (liveness.py; 0: Kubernetes' node status alone).
        self.probe = NodeProbe(node_probe_interval) if node_probe_interval > 0 else None
        self.memory: dict[tuple[str, str], Memory] = {}
        self.history: dict[tuple[str, str], dict] = {}  # record -> instance -> last move
        self.reported: dict[tuple[str, str], dict] = {}  # record -> stranded instance -> why (events sent once)
        self.offline: dict[tuple[str, str], dict] = {}  # record -> instance on an offline robot -> node (events once)
        self.parsed: dict[tuple[str, str], tuple[str, Record | None, str]] = {}
        self.status_written: dict[tuple[str, str], str] = {}
        self.passes = 0
        self.moves = 0
        self.last_pass: list[dict] = []  # per record: deployment, moves, stranded, waiting, table
        self.elector = elector  # None: this replica acts alone (--once, --no-leader-elect)
        self.identity = identity or (elector.identity if elector else "")
        self.leading = False  # as of the last pass loop; without an elector the first loop turns it on
        self.lead_passes = 0  # completed passes since this replica last became the leader
        self.metrics = None  # the dashboard's ControllerMetrics, when it serves /metrics: counts moves and pass times
        self.signals = Signals(api_client, prometheus_url)  # the load signals of scaled modules
        self.windows: dict[tuple, scaling.Windows] = {}  # (namespace, deployment, module) -> its recommendations
        self.robots_written: dict[tuple, dict] = {}  # (namespace, robots ConfigMap) -> the data last applied
        self.scaling_status: dict[tuple[str, str], list[dict]] = {}  # record -> one summary per scaled module
        self.shortfalls: list[capacity.Shortfall] = []  # this pass: instances that may run in the cloud, without room
        self.demand_written: dict[str, dict] = {}  # fleet namespace -> the demand.json last written
        self.fleet_of: dict[str, str] = {}  # fleet namespace -> fleet
        self.blocked: dict[tuple, str] = {}  # (namespace, deployment, module) -> the blocked scale-up last reported
        self.lacking: dict[tuple, str] = {}  # the same key -> why it still lacks a node (scaling.lacking)
        self.burst = None  # a Burst runner (--burst-command): provisions cloud VMs when a fleet lacks room
        self._access: tuple[int, dict] = (-1, {})  # (node store generation, fleet -> the nodes labelled with its access)
