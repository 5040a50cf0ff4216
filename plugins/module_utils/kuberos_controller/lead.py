"""How the controller runs: a pass now, or the loop (watches, passes on change and when a fault's grace ends),
who may act (the Lease), what a replica that lost the lead forgets, when a replica should not lead."""

from __future__ import annotations

import logging
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election

log = logging.getLogger("kuberos.controller")


LEASE_NAME = "kuberos-controller"


LEASE_NAMESPACE = "kuberos-system"


class Leading:
    """The controller's running and leading: the loop, the passes, the Lease, the fence.
    A part of ``controller.Controller``, whose ``__init__`` sets up the state the parts share."""

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
