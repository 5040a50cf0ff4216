"""Running a batch job (``kuberos/batch.py``) on the cluster: place, render, apply wave by wave, watch, collect.

``run_batch(params, check_mode, progress)`` reads the batch file and the inventory, places the job's slots with the
scheduler (beside what already runs), renders every object into ``dest/manifests``, and, when applying, deletes the
job's Jobs of an earlier run, applies its parameter maps, then each wave's Jobs; it watches their pods every
``poll`` seconds, enforces the start-up timeout (a run whose pod has not started by then is stopped and counted as
failed) while Kubernetes enforces the running timeout (``activeDeadlineSeconds``), and reports progress at least
every 30 s. Each finished run's container logs and termination message are collected into ``dest/runs/<run>-<repeat>``;
``dest/results.json`` and ``dest/results.csv`` list every run with its parameters, outcome, node and times.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import batch, naming, pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import (
    KuberosError,
    PlacementError,
    Problem,
    SpecError,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    RenderOptions,
    device_options,
    namespace_levels,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import file_reader
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.yaml_source import read_text
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_dir import apply_plan, plan_files
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, status_of

PROGRESS_EVERY_S = 30.0
INDEX_LABEL = "batch.kubernetes.io/job-completion-index"
PLAN_JSON = "batch.json"


def place(job: batch.BatchJob, inventory, allocated=None, unavailable=None) -> list:
    """The job's slots (one Instance each, in slot order), placed by the scheduler for the job's robots in turn."""
    robots = list(job.deployment.robots or inventory.fleets.get(job.fleet, ()))
    if not robots:
        raise SpecError([Problem(job.source, "metadata.targetFleet", f"fleet {job.fleet} has no robots in the inventory")])
    deployments = batch.slot_deployments(job, robots)
    try:
        placement = place_modules(deployments, inventory, allocated, unavailable)
    except PlacementError as exc:
        field = "jobSpec.maxParallelism" if job.kind == batch.REFERENCE_KIND else "job.parallelism"
        unit = batch.run_unit(job)
        needs = f"cpu {unit.resources.cpu_millis}m, memory {unit.resources.memory_bytes // 2**20}Mi"
        if unit.requirements.devices:
            needs += f", devices {', '.join(unit.requirements.devices)}"
        first = [line for line in exc.failures if f"{job.name}-slot-0" in line] or exc.failures[:1]
        more = len(exc.failures) - len(first)
        raise KuberosError(
            f"{job.source}: the runs of {job.name} cannot be placed: each run needs every module of the job on one node "
            f"({needs}), {job.slots} at once ({field}). Where the first run was tried:\n"
            + "\n".join(first)
            + (f"\n(and {more} more runs at once alike; a lower {field} needs fewer nodes at once)" if more else "")
        ) from None
    by_deployment = {i.deployment: i for i in placement.instances}
    return [by_deployment[d.name] for d in deployments]


def plan_rows(job: batch.BatchJob, slots: list) -> list[dict]:
    rows = []
    for number, combination in enumerate(job.combinations()):
        slot = slots[number % len(slots)]
        rows.append(
            {
                "run": number,
                "job": batch.run_name(job.name, number),
                "wave": number // len(slots),
                "node": slot.node,
                "tier": slot.tier,
                "robot": slot.robots[0],
                "parameters": {f"{m}.{k}": v for m, k, v in combination},
                "repeats": job.repeat,
            }
        )
    return rows


def plan_table(rows: list[dict]) -> str:
    lines = [f"{'RUN':<5}{'WAVE':<6}{'NODE':<12}{'REPEATS':<9}PARAMETERS"]
    for row in rows:
        parameters = ", ".join(f"{k}={v}" for k, v in row["parameters"].items()) or "-"
        lines.append(f"{row['run']:<5}{row['wave']:<6}{row['node']:<12}{row['repeats']:<9}{parameters}")
    return "\n".join(lines)


def plan_render(dest: str, job: batch.BatchJob, objects: list[dict], rows: list[dict]):
    """The render directory's plan (``render_dir``): the job's manifests (one file per object), ``batch.json`` and
    ``plan.txt``; files no longer rendered go."""
    summary = {"name": job.name, "fleet": job.fleet, "kind": job.kind, "source": job.source, "runs": rows}
    files = {PLAN_JSON: json.dumps(summary, indent=2, sort_keys=True) + "\n", "plan.txt": plan_table(rows) + "\n"}
    return plan_files(dest, objects, files)


class Cluster:
    """The calls a batch run makes, through the access layer."""

    def __init__(self, clients, field_manager: str):
        self.kube = Kube(clients, field_manager)

    def apply(self, obj: dict) -> None:
        if obj["kind"] not in ("Namespace", "ConfigMap", "NetworkPolicy", "Job"):
            raise KuberosError(f"a batch job does not apply a {obj['kind']}")
        self.kube.apply(obj)

    def jobs(self, namespace: str, name: str) -> list[dict]:
        return self.kube.list("Job", namespace, selector=f"{batch.BATCH}={name}")

    def pods(self, namespace: str, name: str) -> list[dict]:
        return self.kube.list("Pod", namespace, selector=f"{batch.BATCH}={name}")

    def enforced_level(self, namespace: str) -> str | None:
        """The Pod Security level ``namespace`` enforces; None when it enforces none or does not exist."""
        found = self.kube.get("Namespace", namespace) or {}
        return ((found.get("metadata") or {}).get("labels") or {}).get(pod_security.ENFORCE)

    def configmaps(self, namespace: str, name: str) -> list[dict]:
        return self.kube.list("ConfigMap", namespace, selector=f"{batch.BATCH}={name}")

    def delete_job(self, namespace: str, name: str) -> None:
        self.kube.delete("Job", name, namespace)

    def delete_pod(self, namespace: str, name: str) -> None:
        self.kube.delete("Pod", name, namespace, grace_seconds=0)

    def delete_configmap(self, namespace: str, name: str) -> None:
        self.kube.delete("ConfigMap", name, namespace)

    def log(self, namespace: str, pod: str, container: str) -> str:
        try:
            return self.kube.log(pod, namespace, container)
        except Exception as exc:  # a node without a kubelet (kwok) keeps no logs
            status = status_of(exc)
            return f"(no log: {exc.status} {exc.reason})\n" if status is not None else f"(no log: {exc})\n"


def _outcome(pod: dict) -> tuple[str, str]:
    """(state, why) of a run's pod: pending, running, succeeded or failed."""
    status = pod.get("status") or {}
    phase = status.get("phase", "Pending")
    if phase == "Succeeded":
        return "succeeded", ""
    if phase == "Failed":
        if status.get("reason") == "DeadlineExceeded":
            return "failed", "running timeout"
        for container in status.get("containerStatuses") or []:
            terminated = (container.get("state") or {}).get("terminated") or {}
            if terminated.get("exitCode"):
                return "failed", f"{container['name']} exited {terminated['exitCode']} ({terminated.get('reason', '')})"
        return "failed", status.get("reason") or status.get("message") or "failed"
    if phase == "Running":
        return "running", ""
    return "pending", ""


class Watch:
    """Every run of a job (combination, repeat) and what became of it."""

    def __init__(self, job: batch.BatchJob, rows: list[dict], cluster: Cluster, dest: str, progress, poll: float):
        self.job, self.rows, self.cluster, self.dest, self.progress, self.poll = job, rows, cluster, dest, progress, poll
        self.namespace = naming.fleet_namespace(job.fleet)
        self.runs: dict[tuple[int, int], dict] = {}
        for row in rows:
            for repeat in range(job.repeat):
                self.runs[(row["run"], repeat)] = {**row, "repeat": repeat, "state": "waiting", "why": ""}
        self.pending_since: dict[str, float] = {}
        self.collected: set[str] = set()
        self.last_report = 0.0

    def counts(self) -> dict:
        out: dict[str, int] = {}
        for run in self.runs.values():
            out[run["state"]] = out.get(run["state"], 0) + 1
        return out

    def observe(self, wave: int, now: float) -> None:
        """Read the pods; record each run's state; stop runs that did not start in time; collect finished ones."""
        for pod in self.cluster.pods(self.namespace, self.job.name):
            labels = pod["metadata"].get("labels") or {}
            try:
                key = (int(labels[batch.RUN]), int(labels[INDEX_LABEL]))
            except (KeyError, ValueError):
                continue
            run = self.runs.get(key)
            if run is None or run["wave"] != wave or run["state"] in ("succeeded", "failed"):
                continue
            name = pod["metadata"]["name"]
            state, why = _outcome(pod)
            if state == "pending":
                since = self.pending_since.setdefault(name, now)
                if now - since > self.job.startup_timeout_s:
                    self.cluster.delete_pod(self.namespace, name)
                    state, why = "failed", f"startup timeout: not started within {self.job.startup_timeout_s:g} s"
            run.update(state=state, why=why, pod=name, node=(pod.get("spec") or {}).get("nodeName") or run["node"])
            if state in ("succeeded", "failed") and name not in self.collected:
                self.collect(run, pod)
                self.collected.add(name)

    def collect(self, run: dict, pod: dict) -> None:
        folder = os.path.join(self.dest, "runs", f"{run['run']}-{run['repeat']}")
        os.makedirs(folder, exist_ok=True)
        status = pod.get("status") or {}
        containers = [c["name"] for c in (pod.get("spec") or {}).get("initContainers") or []]
        containers += [c["name"] for c in (pod.get("spec") or {}).get("containers") or []]
        started = bool(status.get("startTime"))
        for container in containers:
            text = self.cluster.log(self.namespace, pod["metadata"]["name"], container) if started else "(never started)\n"
            with open(os.path.join(folder, f"{container}.log"), "w", encoding="utf-8") as handle:
                handle.write(text)
        messages = {
            c["name"]: ((c.get("state") or {}).get("terminated") or {}).get("message", "")
            for c in status.get("containerStatuses") or []
        }
        terminated = [(c.get("state") or {}).get("terminated") or {} for c in status.get("containerStatuses") or []]
        run["message"] = messages.get(next(iter(messages), ""), "") if messages else ""
        run["started"] = status.get("startTime", "")
        run["finished"] = max((t.get("finishedAt") or "" for t in terminated), default="")
        with open(os.path.join(folder, "result.json"), "w", encoding="utf-8") as handle:
            json.dump(
                {k: v for k, v in run.items() if k != "pod"} | {"pod": pod["metadata"]["name"]}, handle, indent=2, sort_keys=True
            )

    def report(self, wave: int, waves: int, started: float, now: float, force: bool = False) -> None:
        counts = self.counts()
        line = (
            f"wave {wave + 1}/{waves}: {counts.get('succeeded', 0) + counts.get('failed', 0)} of {len(self.runs)} runs done "
            f"({counts.get('succeeded', 0)} succeeded, {counts.get('failed', 0)} failed), {counts.get('running', 0)} running, "
            f"{counts.get('pending', 0)} starting, {now - started:.0f} s"
        )
        if (
            force
            or line.split(", ")[:-1] != getattr(self, "_last_line", "").split(", ")[:-1]
            or now - self.last_report >= PROGRESS_EVERY_S
        ):
            self.progress(line)
            self._last_line, self.last_report = line, now

    def wave_done(self, wave: int) -> bool:
        return all(r["state"] in ("succeeded", "failed") for r in self.runs.values() if r["wave"] == wave)

    def run_wave(self, wave: int, waves: int, started: float, clock=time.monotonic, sleep=time.sleep) -> None:
        # a wave's runs are sequential per combination: each repeat may take the start-up and the running time
        limit = clock() + self.job.repeat * (self.job.startup_timeout_s + self.job.running_timeout_s) + 60.0
        while True:
            now = clock()
            self.observe(wave, now)
            self.report(wave, waves, started, now)
            if self.wave_done(wave):
                return
            if now > limit:
                for run in self.runs.values():
                    if run["wave"] == wave and run["state"] not in ("succeeded", "failed"):
                        run.update(state="failed", why="the job did not finish it in time")
                return
            sleep(self.poll)


def write_results(dest: str, runs: list[dict]) -> None:
    fields = ["run", "repeat", "state", "why", "node", "started", "finished", "message", "parameters"]
    with open(os.path.join(dest, "results.json"), "w", encoding="utf-8") as handle:
        json.dump(runs, handle, indent=2, sort_keys=True)
    with open(os.path.join(dest, "results.csv"), "w", encoding="utf-8", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for run in runs:
            writer.writerow({**run, "parameters": json.dumps(run["parameters"], sort_keys=True)})


def load(params: dict, documents=None):
    """The batch job of ``params["src"]`` (one per file; ``documents``: the file's, when the caller has read them),
    in its fleet, and the inventory model."""
    text = "" if documents is not None else read_text(params["src"], params["src"])
    jobs = batch.load_batch_jobs(text, params["src"], read_file=file_reader(params["src"]), documents=documents)
    if len(jobs) != 1:
        raise SpecError([Problem(params["src"], "", f"holds {len(jobs)} batch jobs; expected one per file")])
    inventory = load_inventory(params["inventory"])
    return batch.with_fleet(jobs[0], list(inventory.fleets)), inventory


def _batch_namespace(namespace: str, enforced: str | None, needed: str | None) -> dict:
    """The fleet namespace a batch run applies: it keeps the Pod Security level the namespace enforces (its
    deployments set it), or enforces what the runs need in a namespace that enforces none (a new one). A namespace
    stricter than the runs need is an error before anything runs, naming both levels."""
    needed = needed or "restricted"
    labels = {"app.kubernetes.io/managed-by": "kuberos"}
    if enforced is None:
        labels.update(pod_security.namespace_labels(needed))
    elif pod_security.LEVELS.index(needed) > pod_security.LEVELS.index(enforced):
        raise KuberosError(
            f"namespace {namespace} enforces the {enforced} Pod Security level, and this batch job's runs need {needed} "
            "(a module with user: 0 needs baseline, privileged: true needs privileged); nothing was run"
        )
    return {"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": namespace, "labels": labels}}


def run_batch(clients_factory, params: dict, check_mode: bool, progress, documents=None) -> dict:
    """The whole batch run; ``clients_factory()`` gives the API clients (only called when applying)."""
    job, inventory = load(params, documents)
    options = RenderOptions(**device_options(inventory))
    cluster = None
    allocated, unavailable = dict(params.get("allocated") or {}), {}
    if params["apply"]:
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import (
            node_allocations,
            unavailable_nodes,
        )

        clients = clients_factory()
        cluster = Cluster(clients, params["field_manager"])
        namespace = naming.fleet_namespace(job.fleet)
        for old in cluster.jobs(namespace, job.name):  # an earlier run's Jobs hold their nodes no longer, but block names
            cluster.delete_job(namespace, old["metadata"]["name"])
        allocated = node_allocations(clients, [], [job.fleet])
        unavailable = unavailable_nodes(clients, list(inventory.nodes))
    slots = place(job, inventory, allocated, unavailable)
    objects = batch.render_batch(job, slots, options)
    rows = plan_rows(job, slots)
    plan = plan_render(params["dest"], job, objects, rows)
    if plan.changed and not check_mode:
        apply_plan(plan)
    result = {
        "changed": plan.changed,
        "name": job.name,
        "fleet": job.fleet,
        "notes": list(job.notes),
        "plan": plan_table(rows),
        "runs": len(rows) * job.repeat,
        "dest": params["dest"],
    }
    if cluster is None or check_mode:
        return result
    namespace = naming.fleet_namespace(job.fleet)
    _wait_gone(cluster, namespace, job.name)
    cluster.apply(_batch_namespace(namespace, cluster.enforced_level(namespace), namespace_levels(objects).get(namespace)))
    wanted = {o["metadata"]["name"] for o in objects if o["kind"] == "ConfigMap"}
    for old in cluster.configmaps(namespace, job.name):
        if old["metadata"]["name"] not in wanted:
            cluster.delete_configmap(namespace, old["metadata"]["name"])
    for obj in objects:
        if obj["kind"] in ("NetworkPolicy", "ConfigMap"):
            cluster.apply(obj)
    watch = Watch(job, rows, cluster, params["dest"], progress, float(params.get("poll", 2.0)))
    shutil.rmtree(os.path.join(params["dest"], "runs"), ignore_errors=True)
    jobs = {o["metadata"]["name"]: o for o in objects if o["kind"] == "Job"}
    all_waves = batch.waves(job)
    started = time.monotonic()
    for wave, numbers in enumerate(all_waves):
        progress(f"wave {wave + 1}/{len(all_waves)}: starting runs {', '.join(str(n) for n in numbers)}")
        for number in numbers:
            cluster.apply(jobs[batch.run_name(job.name, number)])
        watch.run_wave(wave, len(all_waves), started)
        watch.report(wave, len(all_waves), started, time.monotonic(), force=True)
    runs = sorted(watch.runs.values(), key=lambda r: (r["run"], r["repeat"]))
    write_results(params["dest"], runs)
    counts = watch.counts()
    result.update(
        changed=True,
        runs_succeeded=counts.get("succeeded", 0),  # not "failed": Ansible would take a count for the task failing
        runs_failed=counts.get("failed", 0),
        failures=[f"run {r['run']} repeat {r['repeat']} ({_params(r)}): {r['why']}" for r in runs if r["state"] == "failed"],
        seconds=round(time.monotonic() - started, 1),
    )
    return result


def _params(run: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in run["parameters"].items()) or "no parameters"


def _wait_gone(cluster: Cluster, namespace: str, name: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while cluster.jobs(namespace, name):
        if time.monotonic() > deadline:
            raise KuberosError(f"the Jobs of an earlier run of {name} are still being deleted after {timeout:.0f} s")
        time.sleep(0.5)


def remove_batch(clients, params: dict) -> dict:
    """Delete the job's Jobs (and their pods) and parameter maps from the cluster."""
    job, _inventory = load(params)
    cluster = Cluster(clients, params["field_manager"])
    namespace = naming.fleet_namespace(job.fleet)
    removed = []
    for old in cluster.jobs(namespace, job.name):
        cluster.delete_job(namespace, old["metadata"]["name"])
        removed.append(f"Job/{namespace}/{old['metadata']['name']}")
    for old in cluster.configmaps(namespace, job.name):
        cluster.delete_configmap(namespace, old["metadata"]["name"])
        removed.append(f"ConfigMap/{namespace}/{old['metadata']['name']}")
    return {"changed": bool(removed), "removed": removed, "name": job.name}
