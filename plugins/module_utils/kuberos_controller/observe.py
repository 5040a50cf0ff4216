"""What the controller sees: the cluster view its watch caches give, each record read (and cached by version),
the nodes of a fleet, what runs on each node, the Ready pods of instances."""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import INSTANCE
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    NodeView,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    Record,
    parse_record,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import Scheduler
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.views import RTT_ANNOTATION, pod_view
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import store_key

log = logging.getLogger("kuberos.controller")


def _epoch(stamp: str | None) -> float | None:
    if not stamp:
        return None
    try:
        return datetime.datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


def _pod_requests(pod: dict) -> dict:
    cpu = memory = gpu = 0
    for container in pod.get("spec", {}).get("containers", []):
        requests = (container.get("resources") or {}).get("requests") or {}
        cpu += quantities.parse_cpu(requests.get("cpu", "0"))
        memory += quantities.parse_memory(requests.get("memory", "0"))
        gpu += int(requests.get("nvidia.com/gpu", "0"))
    return {"cpu": cpu, "memory": memory, "gpu": gpu}


class Observing:
    """The controller's observing: the cluster view, the records, what runs where.
    A part of ``controller.Controller``, whose ``__init__`` sets up the state the parts share."""

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
