"""What the controller decides and does in a pass: the record's placement written first, Deployments re-pinned,
pods left on a dead node deleted, shared modules scaled, every record reconciled."""

from __future__ import annotations

import concurrent.futures
import logging
import os
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity, naming, scaling
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    discovery_from_deployments,
    render_deployment,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import (
    RUNNING,
    ClusterView,
    Decision,
    Memory,
    PodView,
    decide,
    instance_phase,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    WRITER_CONTROLLER,
    Record,
    pin_live_discovery,
    placement_patch,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.report import now_rfc3339
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.watch import store_key
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import status_of

log = logging.getLogger("kuberos.controller")


WRITERS = 4  # parallel requests when a pass re-pins, deletes or reports several things


# Tests: "after-record" exits right after a record write; "after-record-once:<file>" does so only in the first
# replica to get there (it creates the file), so that the replica taking over passes.
FAILPOINT_ENV = "KUBEROS_CONTROLLER_FAILPOINT"


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


class Acting:
    """The controller's deciding and acting: one pass per record, re-placement, re-pinning, scaling.
    A part of ``controller.Controller``, whose ``__init__`` sets up the state the parts share."""

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
                        "at": now_rfc3339(),
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
