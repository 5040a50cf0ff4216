"""What the controller says: Events, each deployment's status ConfigMap (and the moves it remembers across
restarts), each fleet's demand for a cloud provisioner."""

from __future__ import annotations

import json
import logging
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import DEPLOYMENT, MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    ClusterView,
    status_rows,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    STATUS_LABEL,
    Record,
    status_name,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import controller_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import status_of

log = logging.getLogger("kuberos.controller")


CONTROLLER_MANAGER = "kuberos-controller"


def now_rfc3339() -> str:
    return capacity.stamp(time.time())


class Reporting:
    """The controller's reporting: Events, status ConfigMaps, a fleet's demand.
    A part of ``controller.Controller``, whose ``__init__`` sets up the state the parts share."""

    def _event(self, record: Record, name: str, reason: str, message: str, warning: bool) -> None:
        if self.dry_run:
            return
        now = now_rfc3339()
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
                        "updated": now_rfc3339(),
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
            current = capacity.advance(previous, by_fleet.get(fleet), now_rfc3339())
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
