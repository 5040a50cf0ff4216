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
4. report: a Kubernetes Event per move or stranded module, and the status ConfigMap
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
import datetime
import json
import logging
import os
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    DEPLOYMENT,
    INSTANCE,
    MANAGED_BY,
    discovery_from_deployments,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    Decision,
    Memory,
    NodeView,
    PodView,
    Settings,
    decide,
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
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import controller_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import RTT_ANNOTATION, pod_view
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import Store, object_key

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
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


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
                 elector: leader_election.LeaderElector | None = None, identity: str = ""):  # fmt: skip
        from kubernetes import client

        self.api_client = api_client
        self.core = client.CoreV1Api(api_client)
        self.apps = client.AppsV1Api(api_client)
        self.settings = settings or Settings()
        self.dry_run = dry_run  # decide and report, write nothing (check mode)
        self.resync_s = resync_s
        self.changed = threading.Event()
        self.stop_event = threading.Event()
        managed = f"{MANAGED_BY}=kuberos"
        self.nodes = Store("nodes", self.core.list_node, self.changed)
        self.pods = Store("pods", self.core.list_pod_for_all_namespaces, self.changed, label_selector=managed)
        self.deployments = Store(
            "deployments", self.apps.list_deployment_for_all_namespaces, self.changed, label_selector=managed
        )
        self.records = Store(
            "records", self.core.list_config_map_for_all_namespaces, self.changed, label_selector=f"{RECORD_LABEL}=true"
        )
        self.stores = (self.nodes, self.pods, self.deployments, self.records)
        self.memory: dict[tuple[str, str], Memory] = {}
        self.history: dict[tuple[str, str], dict] = {}  # record -> instance -> last move
        self.reported: dict[tuple[str, str], dict] = {}  # record -> stranded instance -> why (events sent once)
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

    # -- fencing --------------------------------------------------------------------------------
    def _may_write(self) -> dict:
        """Before every write: NotLeader when this replica may not act; else the request's client-side timeout."""
        if self.elector is None:
            return {}
        return {"_request_timeout": self.elector.check()}

    def _forget(self) -> None:
        """What a replica knew as leader is stale once another replica has acted: start again from the cluster."""
        self.memory.clear()
        self.history.clear()
        self.reported.clear()
        self.status_written.clear()
        self.parsed.clear()

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
        for node in self.nodes.snapshot():
            meta = node["metadata"]
            name = names[meta["name"]]
            ready = next((c for c in node.get("status", {}).get("conditions", []) if c.get("type") == "Ready"), None)
            ok = bool(ready) and ready.get("status") == "True"
            condition = f"Ready={ready.get('status')} ({ready.get('reason', '')})" if ready else ""
            view.nodes[name] = NodeView(name, ok, condition, _epoch(ready.get("lastTransitionTime")) if ready else None)
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
        key = object_key(configmap)
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
    def _write_placement(self, record: Record, placement) -> bool:
        from kubernetes.client.exceptions import ApiException

        if self.dry_run:
            return True
        patch = placement_patch(record.name, record.namespace, placement)
        patch["metadata"]["resourceVersion"] = record.resource_version  # refuse if deploy rewrote it meanwhile
        try:
            self.core.patch_namespaced_config_map(record.name, record.namespace, patch, **self._may_write())
        except ApiException as exc:
            if exc.status in (404, 409):
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
        meta = obj["metadata"]
        body = json.dumps(obj)
        patch = self.apps.patch_namespaced_deployment if obj["kind"] == "Deployment" else self.core.patch_namespaced_config_map
        patch(
            meta["name"], meta["namespace"], json.loads(body), field_manager=manager, force=True,
            _content_type="application/apply-patch+yaml", **self._may_write(),
        )  # fmt: skip

    def converge(self, record: Record, view: ClusterView) -> int:
        """Finish the controller's own moves: re-pin every Deployment whose node differs from the record, and
        delete pods of moved instances left on a node that is down. A placement deploy wrote is deploy's to apply."""
        if record.writer != WRITER_CONTROLLER:
            return 0
        wanted = render_deployment(record.deployments, record.placement, record.options)
        live = {object_key(d): d for d in self.deployments.snapshot() if d["metadata"].get("namespace") == record.namespace}
        calls = []
        for obj in wanted:
            if obj["kind"] != "Deployment":
                continue
            current = live.get(object_key(obj))
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
        from kubernetes.client.exceptions import ApiException

        if self.dry_run:
            return
        try:
            self.core.delete_namespaced_pod(pod.name, pod.namespace, grace_period_seconds=0, **self._may_write())
            log.info("deleted pod %s/%s left on %s, which is down", pod.namespace, pod.name, pod.node)
        except ApiException as exc:
            if exc.status != 404:
                raise

    def _event(self, record: Record, name: str, reason: str, message: str, warning: bool) -> None:
        from kubernetes.client.exceptions import ApiException

        if self.dry_run:
            return
        now = _now_rfc3339()
        body = {
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
            self.core.create_namespaced_event(record.namespace, body, **self._may_write())
        except ApiException as exc:
            log.warning("event %s for %s not recorded: %s %s", reason, name, exc.status, exc.reason)

    def _write_status(self, record: Record, view: ClusterView, stranded: dict[str, str], waiting: list[str]) -> str:
        key = (record.namespace, record.name)
        rows = status_rows(record, view, stranded, self.history.get(key, {}))
        table = controller_table(record.deployment + (f" (revision {record.revision})" if record.revision else ""), rows)
        content = json.dumps({"rows": rows, "waiting": waiting}, sort_keys=True)
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
                    {"deployment": record.deployment, "updated": _now_rfc3339(), "rows": rows, "waiting": waiting}
                ),
                "moves.json": json.dumps(self.history.get(key, {}), sort_keys=True),
            },
        }
        self._apply(body, CONTROLLER_MANAGER)
        self.status_written[key] = content
        return table

    def _load_history(self, record: Record) -> None:
        """After a restart, the last moves come back from the status ConfigMap."""
        from kubernetes.client.exceptions import ApiException

        key = (record.namespace, record.name)
        if key in self.history:
            return
        self.history[key] = {}
        try:
            configmap = self.core.read_namespaced_config_map(status_name(record.deployment), record.namespace)
            self.history[key] = json.loads((configmap.data or {}).get("moves.json", "{}"))
        except ApiException as exc:
            if exc.status != 404:
                raise
        except ValueError:
            pass

    def reconcile_record(self, configmap: dict, view: ClusterView, now: float) -> float | None:
        record = self._record(configmap)
        if record is None:
            return None
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
        for line in decision.waiting:
            log.debug("%s/%s waits: %s", record.namespace, record.deployment, line)
        applied = 0 if record.rollout else self.converge(record, rview)
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
        return decision.wake_at

    def reconcile(self) -> float | None:
        """One pass over every record; returns when the earliest waiting fault becomes due."""
        self.passes += 1
        self.last_pass = []
        view = self.cluster_view()
        now = time.time()
        wake = []
        for configmap in sorted(self.records.snapshot(), key=object_key):
            try:
                at = self.reconcile_record(configmap, view, now)
            except leader_election.NotLeader:
                raise
            except KuberosError as exc:
                log.error("record %s/%s: %s", *object_key(configmap), exc)
                continue
            if at is not None:
                wake.append(at)
        return min(wake) if wake else None

    # -- running ----------------------------------------------------------------------------
    def run_once(self) -> None:
        for store in self.stores:
            store.relist()
        self.reconcile()

    def run(self) -> None:
        threads = [threading.Thread(target=s.run, args=(self.stop_event,), name=s.name, daemon=True) for s in self.stores]
        if self.elector is not None:
            threads.append(threading.Thread(target=self.elector.run, args=(self.stop_event,), name="lease", daemon=True))
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
