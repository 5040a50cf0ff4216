"""The controller's scaling of shared modules, run against the simulator's runtime.

The simulator has no API server: the rendered Deployments run as processes (runtime/). ``SimScaler`` does what
the controller does for a module with a ``scaling`` policy (``kuberos_controller.controller.Controller.scale``),
with the same pure step (``kuberos.scaling.step``): every ``period`` seconds it reads each instance's gauge,
decides, re-renders with the collection's ``render_deployment`` and acts on the runtime: a new instance's
Deployment is added and started, the robots ConfigMap is rewritten in the instances' mounted volume (as the
kubelet updates a mounted ConfigMap), a drained instance's processes are stopped.

The signal is the module's own Prometheus exposition. In a cluster the controller reads it over HTTP from the pod
(``/metrics``); here the evaluation process is outside the hosts' network namespaces, so it reads the same text
from the file the runtime names in ``KUBEROS_METRICS_FILE`` (the pick-and-place planner writes it beside serving
it). An instance counts as Ready once its process runs and has written the file.

With a ``cloud`` (``kuberos_sim.cloud.SimCloud``) it also does the controller's part of a burst: the instances a
blocked step could not place are what the fleet lacks (``kuberos.capacity``: the demand the controller writes to
``kuberos-capacity``), handed to the cloud's provisioner run each pass; the VMs that have become nodes join the
resource model the next step places against, as the controller adds the nodes labelled with the fleet's access.

Every step is kept in ``timeline`` (time, instances, the mean signal, the VMs, the event), for the evaluation's
instances-over-time plot.
"""

from __future__ import annotations

import glob
import os
import threading
import time

import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import capacity, naming, scaling
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scaling import gauge_value
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import Scheduler

from .runtime.runtime import metrics_file


def load_record(rendered_dir: str):
    """The deployment record deploy rendered (the spec, the resource model, the placement and the options)."""
    found = glob.glob(os.path.join(rendered_dir, "manifests", "*", "configmap-kuberos-record-*.yaml"))
    if len(found) != 1:
        raise FileNotFoundError(f"{rendered_dir} holds {len(found)} deployment records (configmap-kuberos-record-*.yaml)")
    with open(found[0], encoding="utf-8") as handle:
        return parse_record(yaml.safe_load(handle))


class SimScaler:
    def __init__(self, runtime, record, period: float = 2.0, cloud=None):
        self.runtime = runtime
        self.record = record
        self.cloud = cloud
        self.demand: dict | None = None  # the fleet's demand.json as the controller would write it
        self.lacking: dict[str, str | None] = {}  # module -> why it still lacks a node (scaling.lacking)
        self.period = period
        self.states: dict[str, scaling.ScaleState] = {}
        self.windows: dict[str, scaling.Windows] = {}
        self.timeline: list[dict] = []
        self.errors: list[str] = []
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="sim-scaler", daemon=True)
        self.modules = [m for m in record.spec.modules if m.scaling is not None]
        self._robots_data: dict[str, dict] = {}
        self.placed: dict[str, str] = {}  # every instance this scaler started -> its node

    def start(self) -> SimScaler:
        self.started = time.monotonic()
        if self.cloud is not None:
            self.cloud.start()
        for module in self.modules:  # where it starts, before any step
            count = len(self._instances(module))
            self.timeline.append({"t": 0.0, "module": module.name, "instances": count, "running": count, "value": None,
                                  "held": "", "vms": 0, "events": []})  # fmt: skip
        self.thread.start()
        return self

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=30)

    def _loop(self) -> None:
        while not self.stop_event.wait(self.period):
            try:
                self.tick(time.time())
            except Exception as exc:  # reported with the run's results; the run goes on with what it has
                self.errors.append(f"{type(exc).__name__}: {exc}")

    def _instances(self, module) -> list:
        dep = self.record.spec
        return [i for i in self.record.placement.instances if i.deployment == dep.name and i.module == module.name]

    def _signal(self, name: str) -> str | None:
        process = self.runtime.processes.get(name)
        if process is None or not process.running:
            return None
        try:
            with open(metrics_file(self.runtime.run_dir, name), encoding="utf-8") as handle:
                return handle.read()
        except OSError:
            return None

    def inventory(self):
        """The record's resource model with the cloud's VMs that are nodes now."""
        if self.cloud is None:
            return self.record.inventory
        return self.record.inventory.with_nodes(self.cloud.nodes())

    def tick(self, now: float) -> None:
        dep = self.record.spec
        inventory = self.inventory()
        scheduler = Scheduler.around(inventory, self.record.placement)
        shortfalls = []
        for module in self.modules:
            instances = self._instances(module)
            texts = {i.name: self._signal(i.name) for i in instances}
            ready = {n for n, text in texts.items() if text is not None}
            gauges = {n: gauge_value(text, module.scaling.metric) for n, text in texts.items() if text is not None}
            values = {n: v for n, v in gauges.items() if v is not None}
            result = scaling.step(
                dep, module, instances, self.states.get(module.name, scaling.ScaleState()), ready, values,
                self.windows.setdefault(module.name, scaling.Windows()), now,
                lambda robots, module=module: scheduler.choose(dep, module, tuple(robots)),
                scaling.within_latency(module, inventory),
            )  # fmt: skip
            why = scaling.lacking(result, self.lacking.get(module.name))
            self.lacking[module.name] = why
            found = capacity.shortfall(module, instances[0], why) if why is not None else None
            if found is not None:
                shortfalls.append(found)
            self.states[module.name] = result.state
            others = [i for i in self.record.placement.instances if i.module != module.name or i.deployment != dep.name]
            self.record.placement.instances = others + result.instances
            self._act(module, result)
            active = [i for i in result.instances if i.name not in result.state.leaving]
            self.timeline.append(
                {
                    "t": round(time.monotonic() - self.started, 2),
                    "module": module.name,
                    "instances": len(active),
                    "running": len(result.instances),
                    "value": result.summary.get("value"),
                    "held": result.summary.get("held", ""),
                    "vms": len(self.cloud.running()) if self.cloud is not None else 0,
                    "events": [f"{reason}: {message}" for _name, reason, message, _warning in result.events],
                }
            )
        if self.cloud is not None:
            self.demand = capacity.advance(self.demand, capacity.demand(shortfalls).get(dep.fleet), capacity.stamp(now))
            for line in self.cloud.reconcile(self.demand, now):
                self.timeline[-1]["events"].append(f"Cloud {line}")
            self.timeline[-1]["vms"] = len(self.cloud.running())  # after this pass's run

    def _act(self, module, result) -> None:
        dep = self.record.spec
        handover = {(dep.name, module.name): result.state.handover}
        objects = render_deployment(self.record.deployments, self.record.placement, self.record.options, handover)
        wanted = naming.robots_configmap_name(dep.name, module.name)
        robots_map = next(o for o in objects if o["kind"] == "ConfigMap" and o["metadata"]["name"] == wanted)
        for name in result.start:
            obj = next(o for o in objects if o["kind"] == "Deployment" and o["metadata"]["name"] == name)
            self.runtime.add_deployment(obj)
        if self._robots_data.get(module.name) != robots_map["data"]:
            self.runtime.update_configmap(robots_map)  # before the new ones start: they mount the current data
            self._robots_data[module.name] = robots_map["data"]
        for name in result.start:
            self.runtime.start_deployment(name)
            self.placed[name] = self.runtime.rendered.deployments[name].node
        for name in result.stop:
            self.runtime.stop_deployment(name)
