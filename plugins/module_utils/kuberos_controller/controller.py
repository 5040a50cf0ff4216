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

import concurrent.futures
import dataclasses
import datetime
import json
import logging
import os
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity, naming, quantities, scaling
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import DEPLOYMENT, INSTANCE, MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    discovery_from_deployments,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    RUNNING,
    ClusterView,
    Decision,
    Memory,
    NodeView,
    PodView,
    Settings,
    decide,
    instance_phase,
    status_rows,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    RECORD_LABEL,
    STATUS_LABEL,
    WRITER_CONTROLLER,
    Record,
    parse_record,
    pin_live_discovery,
    placement_patch,
    status_name,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import Scheduler
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import controller_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.liveness import NodeProbe
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.signals import Signals
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import RTT_ANNOTATION, pod_view
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store, store_key
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, clients_of, status_of

WRITERS = 4  # parallel requests when a pass re-pins, deletes or reports several things
CONTROLLER_MANAGER = "kuberos-controller"
LEASE_NAME = "kuberos-controller"
LEASE_NAMESPACE = "kuberos-system"
# Tests: "after-record" exits right after a record write; "after-record-once:<file>" does so only in the first
# replica to get there (it creates the file), so that the replica taking over passes.
FAILPOINT_ENV = "KUBEROS_CONTROLLER_FAILPOINT"
log = logging.getLogger("kuberos.controller")


def _epoch(stamp: str | None) -> float | None:
    if not stamp:
        return None
    try:
        return datetime.datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


def _now_rfc3339() -> str:
    return capacity.stamp(time.time())


def _failpoint(name: str) -> bool:
    value = os.environ.get(FAILPOINT_ENV, "")
    if value == name:
        return True
    if value.startswith(name + "-once:"):
        try:
            os.close(os.open(value.split(":", 1)[1], os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return False
        return True
    return False


def _pod_requests(pod: dict) -> dict:
    cpu = memory = gpu = 0
    for container in pod.get("spec", {}).get("containers", []):
        requests = (container.get("resources") or {}).get("requests") or {}
        cpu += quantities.parse_cpu(requests.get("cpu", "0"))
        memory += quantities.parse_memory(requests.get("memory", "0"))
        gpu += int(requests.get("nvidia.com/gpu", "0"))
    return {"cpu": cpu, "memory": memory, "gpu": gpu}


class Controller:
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

    # -- fencing --------------------------------------------------------------------------------
    def _write_timeout(self) -> float | None:
        """Before every write: NotLeader when this replica may not act; else the request's client-side timeout."""
        return None if self.elector is None else self.elector.check()

    def _forget(self) -> None:
        """What a replica knew as leader is stale once another replica has acted: start again from the cluster."""
        self.memory.clear()
        self.history.clear()
        self.reported.clear()
        self.offline.clear()
        self.status_written.clear()
        self.parsed.clear()
        self.windows.clear()
        self.robots_written.clear()
        self.demand_written.clear()
        self.blocked.clear()
        self.lacking.clear()

    # -- observing --------------------------------------------------------------------------
    def _node_names(self) -> dict[str, str]:
        """Kubernetes node name -> inventory name (the hostname label, else the node name)."""
        return {
            n["metadata"]["name"]: (n["metadata"].get("labels") or {}).get(node_labels.HOSTNAME, n["metadata"]["name"])
            for n in self.nodes.snapshot()
        }

    def cluster_view(self) -> ClusterView:
        view = ClusterView()
        names = self._node_names()
        down = self.probe.down() if self.probe is not None else {}
        for node in self.nodes.snapshot():
            meta = node["metadata"]
            name = names[meta["name"]]
            ready = next((c for c in node.get("status", {}).get("conditions", []) if c.get("type") == "Ready"), None)
            ok = bool(ready) and ready.get("status") == "True"
            condition = f"Ready={ready.get('status')} ({ready.get('reason', '')})" if ready else ""
            since = _epoch(ready.get("lastTransitionTime")) if ready else None
            probe = ""
            if ok and meta["name"] in down:  # Ready to Kubernetes, but its kubelet stopped answering the probe
                ok, since = False, down[meta["name"]]
                probe = (
                    f"its kubelet has not answered the controller's probes since {time.strftime('%H:%M:%S', time.gmtime(since))}"
                )
            view.nodes[name] = NodeView(name, ok, condition, since, probe)
            robot = (meta.get("labels") or {}).get(node_labels.ROBOT)
            rtt = (meta.get("annotations") or {}).get(RTT_ANNOTATION)
            if robot and rtt:
                try:
                    view.measured[robot] = {str(k): float(v) for k, v in json.loads(rtt).items()}
                except (ValueError, TypeError, AttributeError):
                    log.warning("node %s: annotation %s is not a JSON mapping of node to ms: %.80r", name, RTT_ANNOTATION, rtt)
        for pod in self.pods.snapshot():
            found = pod_view(pod, names)
            if found is not None:
                view.pods.setdefault(f"{found.namespace}/{found.instance}", []).append(found)
        return view

    @staticmethod
    def _record_view(view: ClusterView, namespace: str) -> ClusterView:
        """The view with pods keyed by bare instance name, for one namespace."""
        prefix = namespace + "/"
        pods = {k[len(prefix) :]: v for k, v in view.pods.items() if k.startswith(prefix)}
        return ClusterView(view.nodes, view.measured, pods)

    def _allocated(self, record: Record) -> dict:
        """Requests of every other KubeROS pod per node (this record's own modules are placed again)."""
        names = self._node_names()
        used: dict[str, dict] = {}
        own = {i.name for i in record.placement.instances} | {
            s.name for servers in record.placement.discovery.values() for s in servers
        }
        for pod in self.pods.snapshot():
            meta = pod["metadata"]
            node = pod.get("spec", {}).get("nodeName")
            if not node or meta.get("deletionTimestamp") or pod.get("status", {}).get("phase") in ("Succeeded", "Failed"):
                continue
            if meta.get("namespace") == record.namespace and (meta.get("labels") or {}).get(INSTANCE) in own:
                continue
            entry = used.setdefault(names.get(node, node), {"cpu": 0, "memory": 0, "gpu": 0, "pods": 0})
            entry["pods"] += 1
            for k, v in _pod_requests(pod).items():
                entry[k] += v
        return {n: {**e, "cpu": f"{e['cpu']}m"} for n, e in used.items()}

    def _record(self, configmap: dict) -> Record | None:
        key = store_key(configmap)
        version = configmap["metadata"].get("resourceVersion", "")
        cached = self.parsed.get(key)
        if cached and cached[0] == version:
            return cached[1]
        try:
            record = parse_record(configmap)
            error = ""
        except KuberosError as exc:
            record, error = None, str(exc)
            log.error("record %s/%s cannot be read: %s", *key, error)
        self.parsed[key] = (version, record, error)
        return record

    # -- acting -----------------------------------------------------------------------------
    def _write_placement(self, record: Record, placement, scaling_state: dict | None = None) -> bool:
        if self.dry_run:
            return True
        patch = placement_patch(record.name, record.namespace, placement, scaling_state)
        patch["metadata"]["resourceVersion"] = record.resource_version  # refuse if deploy rewrote it meanwhile
        try:
            self.kube.patch("ConfigMap", record.name, record.namespace, patch)
        except Exception as exc:
            if status_of(exc) in (404, 409):
                log.info("record %s/%s changed while moving (%s); deciding again", record.namespace, record.name, exc.status)
                return False
            raise
        if _failpoint("after-record"):
            log.error("failpoint after-record: exiting before applying")
            os._exit(3)
        return True

    def _apply(self, obj: dict, manager: str) -> None:
        if self.dry_run:
            return
        self.kube.apply(obj, manager=manager)

    def converge(self, record: Record, view: ClusterView) -> int:
        """Finish the controller's own moves: re-pin every Deployment whose node differs from the record, and
        delete pods of moved instances left on a node that is down. A placement deploy wrote is deploy's to apply."""
        if record.writer != WRITER_CONTROLLER:
            return 0
        wanted = render_deployment(record.deployments, record.placement, record.options)
        live = {store_key(d): d for d in self.deployments.snapshot() if d["metadata"].get("namespace") == record.namespace}
        calls = []
        for obj in wanted:
            if obj["kind"] != "Deployment":
                continue
            current = live.get(store_key(obj))
            if current is None:
                continue  # not created yet (deploy is applying) or removed (undeploy): not the controller's to create
            want = obj["spec"]["template"]["spec"]["nodeSelector"]
            have = current.get("spec", {}).get("template", {}).get("spec", {}).get("nodeSelector")
            if want != have:
                calls.append(lambda obj=obj: self._apply(obj, record.field_manager))
        applied = len(calls)
        placed = {i.name: i.node for i in record.placement.instances}
        placed.update({s.name: s.node for servers in record.placement.discovery.values() for s in servers})
        for instance, pods in view.pods.items():
            for pod in pods:
                target = placed.get(instance)
                down = view.nodes.get(pod.node) is None or not view.nodes[pod.node].ready
                if target and pod.node and pod.node != target and down:
                    calls.append(lambda pod=pod: self._force_delete(pod))
        self._in_parallel(calls)
        return applied

    @staticmethod
    def _in_parallel(calls: list) -> None:
        """Run independent writes side by side; the first error (NotLeader included) is raised once all ended."""
        if len(calls) <= 1:
            for call in calls:
                call()
            return
        with concurrent.futures.ThreadPoolExecutor(max_workers=min(WRITERS, len(calls))) as pool:
            futures = [pool.submit(call) for call in calls]
        errors = [f.exception() for f in futures if f.exception() is not None]
        if errors:
            raise errors[0]

    def _force_delete(self, pod: PodView) -> None:
        if self.dry_run:
            return
        if self.kube.delete("Pod", pod.name, pod.namespace, grace_seconds=0):
            log.info("deleted pod %s/%s left on %s, which is down", pod.namespace, pod.name, pod.node)

    def _event(self, record: Record, name: str, reason: str, message: str, warning: bool) -> None:
        if self.dry_run:
            return
        now = _now_rfc3339()
        body = {
            "apiVersion": "v1",
            "kind": "Event",
            "metadata": {"generateName": f"{name}.", "namespace": record.namespace},
            "involvedObject": {"apiVersion": "apps/v1", "kind": "Deployment", "name": name, "namespace": record.namespace},
            "reason": reason,
            "message": message[:1000],
            "type": "Warning" if warning else "Normal",
            "source": {"component": CONTROLLER_MANAGER, **({"host": self.identity} if self.identity else {})},
            "reportingComponent": CONTROLLER_MANAGER,
            "reportingInstance": self.identity,
            "firstTimestamp": now,
            "lastTimestamp": now,
            "count": 1,
        }
        try:
            self.kube.create(body)
        except Exception as exc:
            if status_of(exc) is None:
                raise
            log.warning("event %s for %s not recorded: %s %s", reason, name, exc.status, exc.reason)

    def _write_status(self, record: Record, view: ClusterView, stranded: dict[str, str], waiting: list[str]) -> str:
        key = (record.namespace, record.name)
        rows = status_rows(record, view, stranded, self.history.get(key, {}))
        table = controller_table(record.deployment + (f" (revision {record.revision})" if record.revision else ""), rows)
        scaled = self.scaling_status.get(key, [])
        content = json.dumps({"rows": rows, "waiting": waiting, "scaling": scaled}, sort_keys=True)
        if self.status_written.get(key) == content:
            return table
        configmap = self.records.items.get(key, {})
        owner = {
            "apiVersion": "v1",
            "kind": "ConfigMap",
            "name": record.name,
            "uid": configmap.get("metadata", {}).get("uid", ""),
        }
        body = {
            "apiVersion": "v1",
            "kind": "ConfigMap",
            "metadata": {
                "name": status_name(record.deployment),
                "namespace": record.namespace,
                "labels": {MANAGED_BY: CONTROLLER_MANAGER, STATUS_LABEL: "true", DEPLOYMENT: record.deployment},
                "ownerReferences": [owner] if owner["uid"] else [],
            },
            "data": {
                "table": table + "\n",
                "status.json": json.dumps(
                    {
                        "deployment": record.deployment,
                        "updated": _now_rfc3339(),
                        "rows": rows,
                        "waiting": waiting,
                        "scaling": scaled,
                    }
                ),
                "moves.json": json.dumps(self.history.get(key, {}), sort_keys=True),
            },
        }
        self._apply(body, CONTROLLER_MANAGER)
        self.status_written[key] = content
        return table

    def _load_history(self, record: Record) -> None:
        """After a restart, the last moves come back from the status ConfigMap."""
        key = (record.namespace, record.name)
        if key in self.history:
            return
        self.history[key] = {}
        configmap = self.kube.get("ConfigMap", status_name(record.deployment), record.namespace) or {}
        try:
            self.history[key] = json.loads((configmap.get("data") or {}).get("moves.json", "{}"))
        except ValueError:
            pass

    def _with_live_nodes(self, record: Record) -> Record:
        """The record with the edge and cloud nodes that joined the cluster since deploy for the record's fleet (cloud VMs
        provisioned for a peak: labelled with the fleet's access) added to its resource model
        (``labels.node_from_cluster``); a node without a latency annotation takes the largest latency of the record's
        own nodes of its tier. Other new nodes are the inventory's to announce (deploy again)."""
        latency: dict[str, float] = {}
        for node in record.inventory.nodes.values():
            latency[node.tier] = max(latency.get(node.tier, 0.0), node.latency_ms)
        extra = []
        for name, tier, obj in self._fleet_nodes(record.spec.fleet):
            if name not in record.inventory.nodes:
                node = node_labels.node_from_cluster(obj, latency.get(tier, 50.0))
                if node is not None:
                    extra.append(node)
        return dataclasses.replace(record, inventory=record.inventory.with_nodes(extra)) if extra else record

    def _fleet_nodes(self, fleet: str) -> list[tuple[str, str, dict]]:
        """(inventory name, tier, Node object) of the edge and cloud nodes labelled with ``fleet``'s access; the nodes
        are gone through once per change of the node store, not once per record and pass."""
        generation = self.nodes.generation
        if self._access[0] != generation:
            by_fleet: dict[str, list] = {}
            for obj in self.nodes.snapshot():
                labels = obj["metadata"].get("labels") or {}
                tier = node_labels.TIER_OF_ROLE.get(labels.get(node_labels.ROLE, ""), "")
                if tier not in ("edge", "cloud"):
                    continue
                name = labels.get(node_labels.HOSTNAME, obj["metadata"]["name"])
                for key, value in labels.items():
                    if key.startswith(node_labels.FLEET_ACCESS_PREFIX) and value == "true":
                        by_fleet.setdefault(key[len(node_labels.FLEET_ACCESS_PREFIX) :], []).append((name, tier, obj))
            self._access = (generation, by_fleet)
        return self._access[1].get(fleet, [])

    def reconcile_record(self, configmap: dict, view: ClusterView, now: float) -> float | None:
        record = self._record(configmap)
        if record is None:
            return None
        record = self._with_live_nodes(record)
        self.fleet_of[record.namespace] = record.spec.fleet
        # A fleet's discovery servers are the fleet's: where their Deployments pin them is the truth for every
        # record of the fleet (another deployment's pass, or a deploy, may have moved one since this record was written).
        live = discovery_from_deployments(
            [d for d in self.deployments.snapshot() if d["metadata"].get("namespace") == record.namespace]
        )
        pin_live_discovery(record, live)
        key = (record.namespace, record.name)
        self._load_history(record)
        memory = self.memory.setdefault(key, Memory())
        rview = self._record_view(view, record.namespace)
        if record.rollout:
            # A rollout owns the deployment's modules until it ends (it clears the marker, also when it fails): nothing
            # of it is re-placed or re-pinned meanwhile; faults are seen again on the first pass after it.
            decision = Decision(record, waiting=[f"rollout to revision {record.rollout.get('revision')} in progress"])
        else:
            decision = decide(record, rview, memory, self.settings, now, self._allocated(record))
        stranded = dict(self.reported.get(key, {}))
        events = []  # sent after the moves are applied: reporting never delays a module's new pod
        if decision.replacement is not None:
            replacement = decision.replacement
            stranded = {s.instance: s.why for s in replacement.stranded}
            if replacement.moves:
                if not self._write_placement(record, replacement.placement):
                    self.changed.set()
                    return None
                record.placement = replacement.placement
                record.writer = WRITER_CONTROLLER
                self.parsed.pop(key, None)
                for move in replacement.moves:
                    who = f"{move.module} for {', '.join(move.robots)}" if move.robots else move.instance
                    message = f"{who} moved from {move.from_node} to {move.to_node}: {move.why}"
                    log.info("%s/%s: %s", record.namespace, record.deployment, message)
                    self.history[key][move.instance] = {
                        "at": _now_rfc3339(),
                        "from": move.from_node,
                        "to": move.to_node,
                        "why": move.why,
                    }
                    events.append((move.instance, "ModuleMoved", message, False))
                    self.moves += 1
                    if self.metrics is not None:
                        self.metrics.moved(move.why)
            for inst, why in stranded.items():
                if self.reported.get(key, {}).get(inst) != why:
                    log.warning("%s/%s: %s stays on its node: %s", record.namespace, record.deployment, inst, why)
                    events.append((inst, "ModuleStranded", why, True))
        else:
            # Still stranded while its node is down; once the node is back it runs where it was.
            where = {i.name: i.node for i in record.placement.instances}
            stranded = {
                i: w for i, w in stranded.items() if i in where and not getattr(rview.nodes.get(where[i]), "ready", False)
            }
        self.reported[key] = stranded
        if not record.rollout:
            events.extend(self._offline_events(key, record, decision.offline))
        modules = {m.name: m for m in record.spec.modules}
        for inst in record.placement.instances:
            if inst.name in stranded:
                self._lacks(modules.get(inst.module), inst, stranded[inst.name])
        for line in decision.waiting:
            log.debug("%s/%s waits: %s", record.namespace, record.deployment, line)
        applied = 0 if record.rollout else self.converge(record, rview)
        scale_wake = None
        if not record.rollout and decision.replacement is None:
            scale_wake, scale_events = self.scale(record, rview, now)
            events.extend(scale_events)
        self._in_parallel([lambda e=e: self._event(record, *e) for e in events])
        table = self._write_status(record, rview, stranded, decision.waiting)
        moves = decision.replacement.moves if decision.replacement is not None else []
        self.last_pass.append(
            {
                "namespace": record.namespace,
                "deployment": record.deployment,
                "moves": [{"instance": m.instance, "from": m.from_node, "to": m.to_node, "why": m.why} for m in moves],
                "stranded": stranded,
                "waiting": decision.waiting,
                "applied": applied,
                "table": table,
            }
        )
        wakes = [t for t in (decision.wake_at, scale_wake) if t is not None]
        return min(wakes) if wakes else None

    def _offline_events(self, key: tuple[str, str], record: Record, offline: dict[str, str]) -> list[tuple]:
        """ "Robot offline" once when a robot's computer drops off (its modules stay: they are not stranded, nothing
        failed), "robot online" once when it is back."""
        now = {i.name: i for i in record.placement.instances if i.node in offline}
        before = self.offline.get(key, {})
        events = []
        for name, inst in now.items():
            if name not in before:
                robot = inst.robots[0] if len(inst.robots) == 1 else inst.node
                why = offline[inst.node]
                message = f"robot {robot} is offline ({why}): {inst.module} stays on {inst.node}, nothing moves or restarts"
                log.info("%s/%s: %s", record.namespace, record.deployment, message)
                events.append((name, "RobotOffline", message, True))
        for name, node in before.items():
            if name not in now:
                events.append((name, "RobotOnline", f"{node} is back online: its modules ran on through the absence", False))
        self.offline[key] = {name: inst.node for name, inst in now.items()}
        return events

    # -- scaling ----------------------------------------------------------------------------
    def _scheduler(self, record: Record, view: ClusterView) -> Scheduler:
        """A scheduler that sees every KubeROS pod's requests, this record's own instances included."""
        unavailable = {n: f"node {n} is NotReady" for n, v in view.nodes.items() if not v.ready}
        inventory = record.inventory.with_measured_latency(view.measured) if view.measured else record.inventory
        return Scheduler.around(inventory, record.placement, self._allocated(record), unavailable)

    def _ready_pods(self, namespace: str, names: set[str]) -> dict[str, dict]:
        """Instance name -> its Running, Ready pod (plain dict), for the instances ``names``."""
        found = {}
        for pod in self.pods.snapshot():
            seen = pod_view(pod, {})
            if seen and seen.namespace == namespace and seen.instance in names and seen.phase == "Running" and seen.ready:
                if not seen.deleting:
                    found[seen.instance] = pod
        return found

    def scale(self, record: Record, view: ClusterView, now: float) -> tuple[float | None, list]:
        """One scaling step for every scaled module of the record; returns (wake time, events)."""
        key = (record.namespace, record.name)
        dep = record.spec
        modules = [m for m in dep.modules if m.scaling is not None]
        if not modules:
            self.scaling_status.pop(key, None)
            return None, []
        states = dict(record.scaling)
        placement = record.placement
        summaries, events, wakes, start, stop = [], [], [], [], []
        scheduler = None
        for module in modules:
            instances = [i for i in placement.instances if i.deployment == dep.name and i.module == module.name and i.shared]
            if not instances:
                continue
            state_key = f"{dep.name}/{module.name}"
            ready = {i.name for i in instances if instance_phase(i, view.pods.get(i.name, []), False)[0] == RUNNING}
            pods = self._ready_pods(record.namespace, {i.name for i in instances})
            requests = instances[0].cpu_millis
            values = self.signals.values(record.namespace, module.scaling, pods, requests, now)
            windows = self.windows.setdefault((record.namespace, dep.name, module.name), scaling.Windows())
            if scheduler is None:
                scheduler = self._scheduler(record, view)
            result = scaling.step(
                dep, module, instances, scaling.ScaleState.from_dict(states.get(state_key)), ready, values, windows, now,
                lambda robots, module=module, chooser=scheduler: chooser.choose(dep, module, tuple(robots)),
                scaling.within_latency(module, scheduler.inventory),
            )  # fmt: skip
            summaries.append(result.summary)
            blocked_key = (record.namespace, dep.name, module.name)
            if not any(reason == "ModuleScaleBlocked" for _n, reason, _m, _w in result.events):
                self.blocked.pop(blocked_key, None)
            if result.wake_at is not None:
                wakes.append(result.wake_at)
            states[state_key] = result.state.to_dict()
            if result.instances != instances:
                others = [i for i in placement.instances if not (i.deployment == dep.name and i.module == module.name)]
                placement = type(placement)(**{**placement.__dict__, "instances": others + result.instances})
            start.extend(result.start)
            stop.extend(result.stop)
            why = scaling.lacking(result, self.lacking.get(blocked_key))
            if why is None:
                self.lacking.pop(blocked_key, None)
            else:  # one more instance of the module has no node (and, while the step waits, still has none)
                self.lacking[blocked_key] = why
                self._lacks(module, instances[0], why)
            for name, reason, message, warning in result.events:
                if reason == "ModuleScaleBlocked":
                    if self.blocked.get(blocked_key) == message:
                        continue  # said once; the shortfall above stands each pass
                    self.blocked[blocked_key] = message
                log.info("%s/%s: %s", record.namespace, dep.name, message)
                events.append((name, reason, message, warning))
                if self.metrics is not None:
                    self.metrics.scaled(dep.name, module.name, reason)
        self.scaling_status[key] = summaries
        states = {k: v for k, v in states.items() if v.get("handover") or v.get("leaving")}
        if placement is not record.placement or states != record.scaling:
            if not self._write_placement(record, placement, states):
                self.changed.set()
                return None, []
            record.placement, record.scaling, record.writer = placement, states, WRITER_CONTROLLER
            self.parsed.pop(key, None)
        self._apply_scaled(record, modules, start, stop)
        return (min(wakes) if wakes else None), events

    def _lacks(self, module, inst, why: str) -> None:
        """An instance like ``inst`` found no node: the fleet lacks its resources, if the module may run in the cloud."""
        found = capacity.shortfall(module, inst, why)
        if found is not None:
            self.shortfalls.append(found)

    def _apply_robots(self, obj: dict, manager: str, cache_key: tuple) -> None:
        self._apply(obj, manager)
        self.robots_written[cache_key] = obj["data"]

    def _apply_scaled(self, record: Record, modules, start: list[str], stop: list[str]) -> None:
        """Create the new instances' Deployments (and any the record has but the cluster lacks, after a takeover),
        apply the robots ConfigMaps that changed, and delete drained instances' Deployments."""
        handover = {
            (record.spec.name, m.name): scaling.ScaleState.from_dict(record.scaling.get(f"{record.spec.name}/{m.name}")).handover
            for m in modules
        }
        wanted = render_deployment(record.deployments, record.placement, record.options, scaling_state=handover)
        names = {i.name for i in record.placement.instances if any(i.module == m.name for m in modules)}
        live = {d["metadata"]["name"] for d in self.deployments.snapshot() if d["metadata"].get("namespace") == record.namespace}
        robots_maps = {naming.robots_configmap_name(record.spec.name, m.name) for m in modules}
        calls = []
        for obj in wanted:
            meta = obj["metadata"]
            if obj["kind"] == "ConfigMap" and meta["name"] in robots_maps:
                cache_key = (meta["namespace"], meta["name"])
                if self.robots_written.get(cache_key) != obj["data"]:
                    calls.append(lambda obj=obj, k=cache_key: self._apply_robots(obj, record.field_manager, k))
            elif obj["kind"] == "Deployment" and meta["name"] in names:
                if meta["name"] in start or (meta["name"] not in live and record.writer == WRITER_CONTROLLER):
                    calls.append(lambda obj=obj: self._apply(obj, record.field_manager))
        self._in_parallel(calls)
        for name in stop:
            if self.dry_run:
                continue
            self.kube.delete("Deployment", name, record.namespace)

    def reconcile(self) -> float | None:
        """One pass over every record; returns when the earliest waiting fault becomes due."""
        self.passes += 1
        self.last_pass = []
        view = self.cluster_view()
        now = time.time()
        wake = []
        self.shortfalls = []
        fleets = set()
        for configmap in sorted(self.records.snapshot(), key=store_key):
            fleets.add(configmap["metadata"].get("namespace", ""))
            try:
                at = self.reconcile_record(configmap, view, now)
            except leader_election.NotLeader:
                raise
            except KuberosError as exc:
                log.error("record %s/%s: %s", *store_key(configmap), exc)
                continue
            if at is not None:
                wake.append(at)
        self._write_demand(sorted(fleets))
        return min(wake) if wake else None

    def _read_demand(self, namespace: str) -> dict | None:
        configmap = self.kube.get("ConfigMap", capacity.CONFIGMAP, namespace) or {}
        try:
            return json.loads((configmap.get("data") or {}).get(capacity.KEY) or "null")
        except ValueError:
            return None

    def _write_demand(self, namespaces: list[str]) -> None:
        """What each fleet lacks (``capacity.demand``) into its ``kuberos-capacity`` ConfigMap, for a cloud
        provisioner (docs/cloud.md); written when it changes."""
        by_fleet = capacity.demand(self.shortfalls)
        for namespace in namespaces:
            fleet = self.fleet_of.get(namespace, "")
            if namespace not in self.demand_written:
                self.demand_written[namespace] = self._read_demand(namespace)  # what an earlier leader wrote
            previous = self.demand_written[namespace]
            if previous is None and fleet not in by_fleet:
                continue  # nothing lacking, and nothing said before: no ConfigMap to write
            current = capacity.advance(previous, by_fleet.get(fleet), _now_rfc3339())
            if current == previous:
                continue
            body = {
                "apiVersion": "v1",
                "kind": "ConfigMap",
                "metadata": {
                    "name": capacity.CONFIGMAP,
                    "namespace": namespace,
                    "labels": {MANAGED_BY: CONTROLLER_MANAGER, node_labels.FLEET: fleet},
                },
                "data": {capacity.KEY: json.dumps(current, sort_keys=True)},
            }
            self._apply(body, CONTROLLER_MANAGER)
            self.demand_written[namespace] = current
            if self.burst is not None:
                self.burst.demand_changed(fleet, current)

    # -- running ----------------------------------------------------------------------------
    def run_once(self) -> None:
        for store in self.stores:
            store.relist()
        self.reconcile()

    def run(self) -> None:
        threads = [threading.Thread(target=s.run, args=(self.stop_event,), name=s.name, daemon=True) for s in self.stores]
        if self.elector is not None:
            threads.append(threading.Thread(target=self.elector.run, args=(self.stop_event,), name="lease", daemon=True))
        if self.probe is not None:
            probing = (self.stop_event, self.nodes.snapshot, self.changed)
            threads.append(threading.Thread(target=self.probe.run, args=probing, name="probe", daemon=True))
        for thread in threads:
            thread.start()
        log.info(
            "controller started (grace %.1f s, resync %.0f s%s)", self.settings.grace_s, self.resync_s,
            f", identity {self.identity}, lease {self.elector.namespace}/{self.elector.name}" if self.elector else "",
        )  # fmt: skip
        wake_at = None
        while not self.stop_event.is_set():
            timeout = self.resync_s if wake_at is None else max(0.05, min(self.resync_s, wake_at - time.time() + 0.05))
            self.changed.wait(timeout)
            self.changed.clear()
            if self.stop_event.is_set():
                break
            if not self._lead():
                wake_at = None
                continue
            if not all(s.synced.is_set() for s in self.stores):
                continue
            time.sleep(0.05)  # let a burst of events land in one pass
            self.changed.clear()
            started = time.monotonic()
            try:
                wake_at = self.reconcile()
            except leader_election.NotLeader as exc:
                log.warning("pass stopped: %s", exc)
                continue
            except Exception as exc:  # the API server restarting, a conflict: try again shortly
                log.warning("pass failed (%s: %s); retrying", exc.__class__.__name__, str(exc)[:300])
                wake_at = time.time() + 1.0
                continue
            self.lead_passes += 1
            if self.metrics is not None:
                self.metrics.reconcile.observe(time.monotonic() - started)
            if self.elector is not None and self.lead_passes == 1:
                log.info(
                    "first pass as leader completed at %.3f (%.3f s)", time.time(), time.monotonic() - started
                )  # the takeover benchmark reads this line
        if self.elector is not None:
            for thread in threads:
                if thread.name == "lease":
                    thread.join(timeout=self.elector.timings.renew_deadline_s + 1)  # it releases the Lease
        log.info("controller stopped after %d passes, %d moves", self.passes, self.moves)

    def _lead(self) -> bool:
        """Whether this replica acts now; forgets what it knew when it stopped leading."""
        leading = self.elector is None or self.elector.is_leader()
        if leading != self.leading:
            self.leading = leading
            self.lead_passes = 0
            if not leading:
                self._forget()
        return leading

    def stand_down(self, node_name: str) -> str | None:
        """Why this replica should not lead: its own node (in-cluster: the pod's node) is NotReady."""
        if not node_name or not self.nodes.synced.is_set():
            return None
        for node in self.nodes.snapshot():
            meta = node["metadata"]
            if node_name not in (meta["name"], (meta.get("labels") or {}).get(node_labels.HOSTNAME)):
                continue
            ready = next((c for c in node.get("status", {}).get("conditions", []) if c.get("type") == "Ready"), None)
            if not ready or ready.get("status") != "True":
                return f"node {node_name} is NotReady"
        return None
